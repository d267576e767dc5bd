"""GLSL compute-shader path tracer that emits per-sample feature vectors (T, Z, albedo, normal, ...).

>>> from torchmanifold.render import create_context, default_scene, PathTracer, write_frame_exr
>>> tracer = PathTracer(default_scene(), width=128, height=128)
>>> res = tracer.render(times=[0.0, 1.0], spp=1, seed=0, sample_offset=0)
>>> write_frame_exr("frame_0000.exr", res, 0)
"""
from torchmanifold.render.context import create_context
from torchmanifold.render.frames import RenderResult, read_frame_exr, write_frame_exr
from torchmanifold.render.scene import (
    MATERIAL_TYPES,
    PRIM_KINDS,
    Camera,
    CameraKey,
    Keyframe,
    Material,
    Mesh,
    Quad,
    Scene,
    Sphere,
    default_scene,
    load_scene,
    scene_from_dict,
)
from torchmanifold.render.tracer import PathTracer

__all__ = [
    "create_context", "load_scene", "default_scene", "scene_from_dict", "PathTracer", "RenderResult",
    "write_frame_exr", "read_frame_exr", "MATERIAL_TYPES", "PRIM_KINDS", "Scene", "Material", "Sphere",
    "Quad", "Mesh", "Camera", "CameraKey", "Keyframe",
]
