"""File I/O: multi-channel EXR frames (OpenEXR) and video."""
from torchmanifold.io.exr import read_exr, write_exr

__all__ = ["read_exr", "write_exr"]
