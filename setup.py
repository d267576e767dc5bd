"""Builds torchmanifold and its C++ extension ``torchmanifold._C`` from ``csrc/``.

Build with ``pip install --no-build-isolation -e .`` so the extension compiles against the torch
already in the environment. ``DEBUG=1`` builds without optimisation.

The CPU kernel is compiled for the building machine's instruction set (``-march=native``; its hottest
loops have AVX2 + FMA paths, and the whole kernel ran 1.25x faster than the baseline x86-64 SSE2 build
at 1 MP before those were added). For a binary that must run on other machines set
``TORCHMANIFOLD_MARCH`` to a portable target (``x86-64-v2``) or to an empty string for the compiler's
default.
"""
import glob
import os
import platform

from setuptools import find_packages, setup
from torch.utils.cpp_extension import BuildExtension, CppExtension, CUDAExtension, CUDA_HOME
import torch


def get_extensions():
    debug = os.getenv("DEBUG", "0") == "1"
    sources = sorted(glob.glob("csrc/**/*.cpp", recursive=True))
    cuda_sources = sorted(glob.glob("csrc/**/*.cu", recursive=True))
    opt = ["-O0", "-g"] if debug else ["-O3"]
    march = os.getenv("TORCHMANIFOLD_MARCH", "native" if platform.machine() in ("x86_64", "aarch64") else "")
    isa = [f"-march={march}"] if march and not debug else []
    # -fno-trapping-math: nothing here reads floating-point exception flags, and with it the compiler
    # may vectorise loops that select between a quotient and a fallback (IEEE results unchanged);
    # -fno-math-errno: nothing reads errno either, and sqrt loops vectorise without it
    extra_compile_args = {"cxx": opt + isa + ["-fno-trapping-math", "-fno-math-errno", "-fopenmp", "-std=c++17"]}
    extra_link_args = ["-fopenmp"]
    extension = CppExtension
    use_cuda = bool(cuda_sources) and torch.cuda.is_available() and CUDA_HOME is not None
    if use_cuda or os.getenv("FORCE_CUDA", "0") == "1":
        extension = CUDAExtension
        sources += cuda_sources
        extra_compile_args["nvcc"] = opt + ["--use_fast_math"]
    return [
        extension(
            "torchmanifold._C",
            sources,
            include_dirs=[os.path.abspath("csrc")],
            extra_compile_args=extra_compile_args,
            extra_link_args=extra_link_args,
        )
    ]


setup(
    packages=find_packages(include=["torchmanifold", "torchmanifold.*"]),
    package_data={"torchmanifold": ["render/shaders/*", "render/scenes/*"]},
    ext_modules=get_extensions(),
    cmdclass={"build_ext": BuildExtension.with_options(use_ninja=True)},
)
