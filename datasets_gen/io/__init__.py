"""The generator's files, plain side: the dataset folder (`output_dir`: names, resume, atomic
writes), the JSON documents (`dataset_json`), PNG and EXR (`png_image`, `png_check`, `exr`,
`depth_normals`), the surface mesh (`surface_mesh`), other tools' layouts (`formats`, with
`colmap_model` and `colmap_export`) and joining shards (`shards`). Imports `core` only; no bpy."""
