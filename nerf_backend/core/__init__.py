"""Layer 0: what everything shares and nothing here imports from the rest: errors, files, devices, progress
bars, cameras (rays through pixel centres), the scene's box (``SceneBounds``), plotting and
PLY meshes read as arrays."""
