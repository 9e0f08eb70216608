"""A textured triangle mesh as one glTF binary file (``.glb``), the format Blender and every
engine import with its material, built with ``pygltflib`` (a maintained, pure-Python model of
the glTF 2.0 schema) rather than by packing the container here.

The material is unlit (``KHR_materials_unlit``) with the baked texture as its base colour: the
texture already holds the scene's lighting as the NeRF learnt it, so a renderer shows it as it
is instead of lighting it again (Blender's importer makes it an emission-like shader). glTF is
Y-up and Blender Z-up: positions given in Blender's world are written as ``(x, z, -y)``, which
Blender's importer turns back, so the asset lands where the scene's objects were.

Example:
    >>> import tempfile, torch
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "triangle.glb"
    >>> size = write_glb(path, torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0.0, 0, 1]] * 3),
    ...           torch.tensor([[0.0, 0], [1, 0], [0, 1]]), torch.tensor([[0, 1, 2]]), torch.ones(4, 4, 3), "triangle")
    >>> path.read_bytes()[:4], size == path.stat().st_size
    (b'glTF', True)
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pygltflib
import torch
from torch import Tensor

from ..core.files import atomic_write

UNLIT = "KHR_materials_unlit"
_LINEAR, _LINEAR_MIPMAP_LINEAR = 9729, 9987
# The atlas's charts reach the texture's edges: glTF's default wrap (repeat) would filter them
# with texels of the opposite edge's charts, so the texture is clamped (Blender: Extend).
CLAMP_TO_EDGE = 33071


def blender_to_gltf(points: Tensor) -> Tensor:
    """Blender's Z-up ``(x, y, z)`` as glTF's Y-up ``(x, z, -y)`` (a rotation: windings keep).

    Example:
        >>> blender_to_gltf(torch.tensor([[1.0, 2.0, 3.0]])).tolist()
        [[1.0, 3.0, -2.0]]
    """
    return torch.stack([points[:, 0], points[:, 2], -points[:, 1]], dim=1)


def write_glb(path: Path, vertices: Tensor, normals: Tensor, uv: Tensor, faces: Tensor, texture: Tensor,
              name: str) -> int:
    """Write the mesh (``vertices``/``normals [V, 3]`` in Blender's world, ``uv [V, 2]`` with v
    down the image, ``faces [F, 3]`` counter-clockwise seen from outside) and its ``texture
    [H, W, 3]`` in [0, 1] (sRGB, as glTF's base colour is) to ``path``; returns its size in bytes."""
    arrays = [
        blender_to_gltf(vertices.double()).numpy().astype(np.float32),
        blender_to_gltf(normals.double()).numpy().astype(np.float32),
        uv.numpy().astype(np.float32),
        faces.numpy().astype(np.uint32).reshape(-1),
        iio.imwrite("<bytes>", np.clip(np.round(texture.numpy() * 255), 0, 255).astype(np.uint8), extension=".png"),
    ]
    blob, views = b"", []
    for array in arrays:
        data = array if isinstance(array, bytes) else array.tobytes()
        blob += b"\0" * (-len(blob) % 4)  # each view starts on a 4-byte boundary
        views.append(pygltflib.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data)))
        blob += data
    positions = arrays[0]
    for view in views[:3]:
        view.target = pygltflib.ARRAY_BUFFER
    views[3].target = pygltflib.ELEMENT_ARRAY_BUFFER
    accessors = [
        pygltflib.Accessor(bufferView=0, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC3,
                           min=positions.min(axis=0).tolist(), max=positions.max(axis=0).tolist()),
        pygltflib.Accessor(bufferView=1, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC3),
        pygltflib.Accessor(bufferView=2, componentType=pygltflib.FLOAT, count=len(positions), type=pygltflib.VEC2),
        pygltflib.Accessor(bufferView=3, componentType=pygltflib.UNSIGNED_INT, count=len(arrays[3]),
                           type=pygltflib.SCALAR),
    ]
    material = pygltflib.Material(
        name=f"{name} (baked NeRF colour)", extensions={UNLIT: {}},
        pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(baseColorTexture=pygltflib.TextureInfo(index=0),
                                                            metallicFactor=0.0, roughnessFactor=1.0))
    primitive = pygltflib.Primitive(attributes=pygltflib.Attributes(POSITION=0, NORMAL=1, TEXCOORD_0=2), indices=3,
                                    material=0)
    document = pygltflib.GLTF2(
        asset=pygltflib.Asset(generator="python -m nerf_backend export", version="2.0"),
        scene=0, scenes=[pygltflib.Scene(nodes=[0])], nodes=[pygltflib.Node(mesh=0, name=name)],
        meshes=[pygltflib.Mesh(name=name, primitives=[primitive])], materials=[material],
        textures=[pygltflib.Texture(sampler=0, source=0)],
        samplers=[pygltflib.Sampler(magFilter=_LINEAR, minFilter=_LINEAR_MIPMAP_LINEAR, wrapS=CLAMP_TO_EDGE,
                                   wrapT=CLAMP_TO_EDGE)],
        images=[pygltflib.Image(bufferView=4, mimeType="image/png", name=f"{name} baked colour")],
        accessors=accessors, bufferViews=views, buffers=[pygltflib.Buffer(byteLength=len(blob))],
        extensionsUsed=[UNLIT],
    )
    document.set_binary_blob(blob)
    encoded = b"".join(document.save_to_bytes())
    atomic_write(path, lambda tmp: tmp.write_bytes(encoded))
    return len(encoded)
