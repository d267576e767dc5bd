"""The adaptive-manifold filter op: public functions and modules, the pure-PyTorch reference and oracle."""
from torchmanifold.ops._reference import adaptive_manifold_torch
from torchmanifold.ops.reference import bilateral_brute_force

__all__ = ["adaptive_manifold_torch", "bilateral_brute_force"]
