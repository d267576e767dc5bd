"""Loads the compiled ``torchmanifold._C`` library loudly.

Importing the shared library runs its static ``TORCH_LIBRARY`` registrations. A broken or missing
build raises here with the real loader error instead of an opaque "operator does not exist" later.
"""
import importlib

import torch

try:
    _C = importlib.import_module("torchmanifold._C")
except ImportError as exc:  # pragma: no cover - exercised only on a broken install
    raise ImportError(
        "torchmanifold._C failed to load; build it with "
        "`pip install --no-build-isolation -e .` (or run scripts/setup.sh). Loader error: " + str(exc)
    ) from exc


def build_info() -> dict:
    """How the extension was built: ``{"openmp": bool, "isa": str, "parallel": str}``.

    ``isa`` is the instruction set the CPU kernel was compiled for (``avx2+fma``, ``sse2`` or
    ``generic``; see ``TORCHMANIFOLD_MARCH`` in setup.py), ``parallel`` ATen's parallel settings.
    """
    raw = torch.ops.torchmanifold._build_info()
    # the last field (ATen's description) may itself contain ';'
    fields = dict(item.split("=", 1) for item in raw.split(";", 2))
    return {"openmp": fields["openmp"] == "1", "isa": fields["isa"], "parallel": fields["parallel"]}
