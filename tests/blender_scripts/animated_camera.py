"""Build a scene whose camera follows a known animation (a parent moving along a line, the
camera's own rotation keyed, its lens zooming) and export its camera path through the Python
API. Run with the bpy module's Python: ``python animated_camera.py DATASET OUT_JSON``.

The path (frames 1..5, a key on each): parent at (f, 0, 0); camera at (0, -4, 1) in the
parent, rotated 90° about X (looking along +Y), then ``f * 10°`` about Z; lens 20 + 5 f mm;
sensor 36 mm, 64×48 at 50 %."""

import math
import sys

import bpy

sys.path.insert(0, sys.argv[-3])
from datasets_gen.camera_path_export import export_camera_path  # noqa: E402

dataset, out = sys.argv[-2], sys.argv[-1]
scene = bpy.context.scene
for obj in list(scene.objects):
    bpy.data.objects.remove(obj)
rig = bpy.data.objects.new("rig", None)
scene.collection.objects.link(rig)
data = bpy.data.cameras.new("moving")
data.sensor_width, data.sensor_fit = 36.0, "AUTO"
camera = bpy.data.objects.new("moving camera", data)
camera.parent = rig
camera.location = (0.0, -4.0, 1.0)
scene.collection.objects.link(camera)
for frame in range(1, 6):
    rig.location = (float(frame), 0.0, 0.0)
    rig.keyframe_insert("location", frame=frame)
    camera.rotation_euler = (math.radians(90.0), 0.0, math.radians(10.0 * frame))
    camera.keyframe_insert("rotation_euler", frame=frame)
    data.lens = 20.0 + 5.0 * frame
    data.keyframe_insert("lens", frame=frame)
scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 64, 48, 50
scene.render.fps, scene.render.fps_base = 30, 1.001
scene.frame_set(3)
path = export_camera_path(dataset, "moving camera", "1:5:2", scene=scene, out_dir=out, progress=False)
print("frame after export:", scene.frame_current, "percentage:", scene.render.resolution_percentage)
print("written:", path)
