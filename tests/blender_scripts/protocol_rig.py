"""Build the protocol's camera rig in Blender and report the camera's matrix_world per Empty rotation.

Run as `python protocol_rig.py ANGLES.json OUT.json` with a Python that has the bpy module.
ANGLES.json holds [[tilt_x, azimuth_z], ...] in radians. The rig is the one of the original
nerf_synthetic script: an Empty at the origin, the camera parented to it at (0, 4, 0.5), and a
Track-To constraint on the camera (-Z forward, +Y up) aimed at the Empty.
"""

from __future__ import annotations

import json
import sys

import bpy


def main() -> None:
    angles_path, out_path = sys.argv[1], sys.argv[2]
    with open(angles_path) as handle:
        angles = json.load(handle)
    scene = bpy.data.scenes.new("rig")
    empty = bpy.data.objects.new("empty", None)
    scene.collection.objects.link(empty)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    camera.parent = empty
    camera.location = (0.0, 4.0, 0.5)
    track = camera.constraints.new("TRACK_TO")
    track.target = empty
    track.track_axis = "TRACK_NEGATIVE_Z"
    track.up_axis = "UP_Y"
    matrices = []
    for tilt_x, azimuth_z in angles:
        empty.rotation_euler = (tilt_x, 0.0, azimuth_z)
        scene.view_layers[0].update()
        matrices.append([list(row) for row in camera.matrix_world])
    with open(out_path, "w") as handle:
        json.dump(matrices, handle)


if __name__ == "__main__":
    main()
