"""Makes blender5_frame.exr: a 32x24, 1-spp Cycles render as Blender 5.0.1 writes it (multilayer EXR,
one part per pass, with the denoising data, Normal, Depth, Position and Emission passes), the real
file the tests read. Not needed to run the tests; to remake it:

    python3 -m venv /work/venvs/bpy && /work/venvs/bpy/bin/pip install bpy==5.0.1
    /work/venvs/bpy/bin/python make_blender5_frame.py -- blender5_frame.exr
"""
import sys

import bpy

out = sys.argv[-1]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.render.engine = "CYCLES"
sc.cycles.device = "CPU"
sc.cycles.samples = 1
sc.cycles.seed = 0
sc.cycles.use_adaptive_sampling = False
sc.cycles.use_denoising = False
sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = 32, 24, 100
bpy.ops.mesh.primitive_plane_add(size=4, location=(0, 0, 0))
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.5, location=(0, 0, 0.5))
bpy.ops.object.light_add(type="POINT", location=(1, 1, 3))
bpy.context.object.data.energy = 500
bpy.ops.mesh.primitive_plane_add(size=0.6, location=(0.9, 0.3, 0.01))  # an emitting tile on the floor
lamp = bpy.data.materials.new("lamp")
lamp.use_nodes = True
bsdf = lamp.node_tree.nodes["Principled BSDF"]
bsdf.inputs["Emission Strength"].default_value = 5.0
bsdf.inputs["Emission Color"].default_value = (1.0, 0.5, 0.2, 1.0)
bpy.context.object.data.materials.append(lamp)
bpy.ops.object.camera_add(location=(0, -4, 2), rotation=(1.2, 0, 0))  # clip_start: the default 0.1
sc.camera = bpy.context.object
vl = sc.view_layers[0]
vl.cycles.denoising_store_passes = True  # Denoising Albedo / Normal / Depth
vl.use_pass_normal = True
vl.use_pass_z = True
vl.use_pass_position = True
vl.use_pass_emit = True  # the "Emission" pass
sc.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
sc.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
sc.render.image_settings.color_depth = "32"
sc.render.filepath = out
bpy.ops.render.render(write_still=True)
