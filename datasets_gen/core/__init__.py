"""The generator's plain side, lowest layer: options and their flags (`options`), the camera rig
(`trajectories`), pixel intrinsics (`intrinsics`), the similarity into the protocol's frame
(`frame_fit`), camera-path maths (`camera_path`), what refuses a scene (`scene_checks`), view
dependence and transparency (`materials`), voxelising triangles (`voxelise`), the z-buffer
(`zbuffer`), the registry of scenes built in code (`builtin_scenes`) and progress lines
(`progress`). No bpy, no files: it runs and is tested in any Python."""
