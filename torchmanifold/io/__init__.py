"""File I/O: multi-channel EXR files (OpenEXR), rendered frames of any renderer's layout, PNG, video,
and the atomic write they all go through."""
from torchmanifold.io.exr import read_exr, write_exr
from torchmanifold.io.files import atomic_path, prepare_out, write_text
from torchmanifold.io.frames import RenderFrame, read_render_frame, write_color

__all__ = ["read_exr", "write_exr", "atomic_path", "prepare_out", "write_text", "RenderFrame",
           "read_render_frame", "write_color"]
