"""Clear glass whose shape and index of refraction Blender knows: rays bent through it.

A NeRF has no way to show a checkerboard through a glass ball except to learn, for every point of
the ball's surface, a colour that changes quickly with the view: what is seen there is the board,
refracted and flipped, and it moves as the camera moves. Blender knows the ball's triangles and its
IOR (the dataset's ``scene_geometry.ply`` and the profile's materials), so the model traces each
ray that meets the glass as Cycles does: Snell's law at the entry, through the glass (total
internal reflection included), Snell's law at the exit; and the share Fresnel's equations give to
the mirror reflection at the entry. The field is then marched along the ray up to the glass, and
along the two rays beyond it: what it learns there is the board itself, seen straight and bent,
one field for both (``MarchedModel.forward``).

The light through the glass is tinted by the glass's colour, learned from Blender's (its square
to start with: Cycles tints the light at each crossing of the surface, in and out). Left out,
knowingly: the reflections inside the glass after the first (Cycles follows them; at IOR 1.45
they carry a few percent), absorption by depth (a volume), rough glass (the rule takes only
smooth, fully transmissive materials), thin-walled glass (a dish, a cup: left to the field,
straight, ``data.occupancy_prior.GLASS_MIN_WALL_SHARE``), and a camera inside glass.
A mesh that is not closed (a single-sided pane) lets the ray through unbent where no exit is found.

Example:
    >>> import torch
    >>> glass = GlassSurfaces()
    >>> square = torch.tensor([[[-1.0, -1, 1], [1, -1, 1], [1, 1, 1]], [[-1.0, -1, 1], [1, 1, 1], [-1, 1, 1]]])
    >>> glass.set(square, torch.tensor([0.0, 0, 1]).expand(2, 3, 3), torch.tensor([1.5, 1.5]))  # colourless
    >>> paths = glass.trace(torch.tensor([[0.0, 0, 0], [5.0, 0, 0]]), torch.tensor([[0.0, 0, 1], [0, 0, 1]]))
    >>> paths.rays.tolist(), paths.t_entry.tolist(), round(float(paths.fresnel[0]), 3)
    ([0], [1.0], 0.04)
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from ..core.cameras import ray_box_intersection
from ..core.refraction import build_bvh, fresnel_reflectance, nearest_triangle_hits, reflect, refract
from ..kernels.build import load_kernel

# Crossings of the glass's surface from inside, before a ray still trapped by total internal
# reflection leaves along its last direction (a sphere's paths leave at the first).
INTERNAL_CROSSINGS = 4
# The continuing rays start this share of the glass's size off its surface (no self-crossing).
SURFACE_OFFSET = 1e-4


@dataclass
class GlassPaths:
    """The rays that meet glass: their indices ``rays [H]``, the distance to the glass
    ``t_entry [H]``, the Fresnel reflectance there ``fresnel [H]``, the tint of the glass they
    pass through ``tint [H, 3]``, and the rays beyond, ``origins``/``directions [2H, 3]``: first
    the ones leaving the glass, then the reflected."""

    rays: Tensor
    t_entry: Tensor
    fresnel: Tensor
    tint: Tensor
    origins: Tensor
    directions: Tensor

    def colour_seen(self, beyond: Tensor) -> Tensor:
        """``[H, 3]``: what each ray sees at the glass, from the colours ``beyond [2H, 3]`` its
        two rays beyond brought back: the light through the glass tinted, the reflection not."""
        count = self.rays.numel()
        share = self.fresnel[:, None].to(beyond.dtype)
        return (1.0 - share) * self.tint.to(beyond.dtype) * beyond[:count] + share * beyond[count:]


class GlassSurfaces(nn.Module):
    """Buffers: the glass's triangles ``corners [T, 3, 3]``, their smooth ``normals`` at each
    corner ``[T, 3, 3]``, each triangle's ``ior [T]`` and ``glass [T]`` (which of the scene's
    glass materials it is); a parameter, each glass material's tint, learned from Blender's
    (``tint_logits [M, 3]``). What the rays beyond it see where they leave the scene is the
    model's (``field_components.environment``)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("corners", torch.zeros((0, 3, 3)))
        self.register_buffer("normals", torch.zeros((0, 3, 3)))
        self.register_buffer("ior", torch.zeros(0))
        self.register_buffer("glass", torch.zeros(0, dtype=torch.long))
        self.tint_logits = nn.Parameter(torch.zeros((0, 3)))

    def set(self, corners: Tensor, normals: Tensor, ior: Tensor, glass: Tensor | None = None,
            tints: Tensor | None = None) -> None:
        """The glass's triangles, corner normals and IOR; ``glass [T]``, each triangle's glass
        material, and ``tints [M, 3]``, each material's tint as Blender gives it (by default one
        colourless glass). The light through the glass starts tinted by the tint squared (Cycles
        tints it at each crossing of the surface, in and out) and learns its own."""
        device = self.corners.device
        self.corners = corners.to(device, torch.float32).contiguous()
        self.normals = normals.to(device, torch.float32).contiguous()
        self.ior = ior.to(device, torch.float32).contiguous()
        self.glass = (torch.zeros(corners.shape[0], dtype=torch.long) if glass is None else glass).to(device)
        tints = torch.ones((1, 3)) if tints is None else tints.float()
        through = (tints * tints).clamp(1e-3, 1.0 - 1e-3)
        self.tint_logits = nn.Parameter(torch.logit(through).to(device))

    def tint(self, face: Tensor) -> Tensor:
        """``[H, 3]`` the tint of the glass of each triangle ``face``."""
        return torch.sigmoid(self.tint_logits).index_select(0, self.glass.index_select(0, face))

    def _hits(self, origins: Tensor, directions: Tensor, t_min: float) -> tuple[Tensor, Tensor, Tensor]:
        """``nearest_triangle_hits`` against the glass: on the CPU through a bounding volume
        hierarchy in C (kernels/ray_mesh.c; about 30 triangles tested a ray against the ball's
        3 968 of glass_over_checker), elsewhere or without a compiler every triangle in torch."""
        walk = self._compiled_walk() if origins.device.type == "cpu" else None
        if walk is None:
            return nearest_triangle_hits(origins, directions, self.corners, t_min)
        library, lo, hi, child, tri, order = walk[:6]
        count = origins.shape[0]
        o, d = origins.float().contiguous(), directions.float().contiguous()
        t, face, uv = torch.empty(count), torch.empty(count, dtype=torch.int32), torch.empty((count, 2))
        library.ray_mesh_nearest(*(ctypes.c_void_p(x.data_ptr()) for x in (o, d)), ctypes.c_int64(count),
                                 ctypes.c_float(t_min), *(ctypes.c_void_p(x.data_ptr()) for x in (lo, hi, child, tri)),
                                 *(ctypes.c_void_p(x.data_ptr()) for x in (t, face, uv)),
                                 ctypes.c_int64(torch.get_num_threads()))
        face = face.long()
        found = face >= 0
        face = torch.where(found, order.index_select(0, face.clamp(min=0)), face)
        return t, face, torch.cat([1.0 - uv.sum(dim=1, keepdim=True), uv], dim=1)

    def _compiled_walk(self):
        """The C kernel and the hierarchy over the current triangles (built once), or None."""
        key = (self.corners.data_ptr(), self.corners._version, self.corners.shape[0])
        cached = getattr(self, "_walk", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        library, _ = load_kernel("ray_mesh")
        walk = None
        if library is not None:
            library.ray_mesh_nearest.restype = ctypes.c_int
            lo, hi, child, order = build_bvh(self.corners.cpu().numpy())
            tri = self.corners.cpu()[torch.from_numpy(order)].reshape(-1, 9).contiguous()
            library.glass_paths.restype = ctypes.c_int
            reorder = torch.from_numpy(order)
            walk = (library, torch.from_numpy(lo), torch.from_numpy(hi), torch.from_numpy(child), tri, reorder,
                    self.normals.cpu()[reorder].reshape(-1, 9).contiguous(), self.ior.cpu()[reorder].contiguous())
        self._walk = (key, walk)
        return walk

    def match_state(self, state: dict[str, Tensor], prefix: str) -> None:
        """Take the buffers' shapes a checkpoint was saved with (its values are loaded next)."""
        for name in ("corners", "normals", "ior", "glass"):
            saved = state.get(prefix + name)
            if saved is not None and saved.shape != getattr(self, name).shape:
                setattr(self, name, torch.zeros_like(saved, device=self.corners.device))
        saved = state.get(prefix + "tint_logits")
        if saved is not None and saved.shape != self.tint_logits.shape:
            self.tint_logits = nn.Parameter(torch.zeros_like(saved, device=self.corners.device))

    @property
    def empty(self) -> bool:
        return self.corners.shape[0] == 0

    def trace(self, origins: Tensor, directions: Tensor) -> GlassPaths | None:
        """The paths of the rays (unit ``directions``) that meet the glass; None if none does.
        On the CPU in C (kernels/ray_mesh.c's ``glass_paths``: 5 ms of a 21 ms training step
        in torch, on glass_over_checker at 100×100), elsewhere or without a compiler in torch
        (``_torch_trace``); the two give the same paths (tests/test_glass.py)."""
        if self.empty or origins.shape[0] == 0:
            return None
        flat = self.corners.view(-1, 3)
        low, high = flat.min(dim=0).values, flat.max(dim=0).values
        offset = SURFACE_OFFSET * float((high - low).norm())
        walk = self._compiled_walk() if origins.device.type == "cpu" else None
        if walk is None:
            return self._torch_trace(origins, directions, low, high, offset)
        library, lo, hi, child, tri, order, normals, ior = walk
        count = origins.shape[0]
        o, d = origins.float().contiguous(), directions.float().contiguous()
        met, entry_face = torch.empty(count, dtype=torch.uint8), torch.empty(count, dtype=torch.int32)
        t_entry, fresnel = torch.empty(count), torch.empty(count)
        leave, reflected = torch.empty((count, 6)), torch.empty((count, 6))
        library.glass_paths(*(ctypes.c_void_p(x.data_ptr()) for x in (o, d)), ctypes.c_int64(count),
                            *(ctypes.c_void_p(x.data_ptr()) for x in (lo, hi, child, tri, normals, ior)),
                            ctypes.c_float(offset), ctypes.c_int32(INTERNAL_CROSSINGS),
                            *(ctypes.c_void_p(x.data_ptr()) for x in (met, entry_face, t_entry, fresnel, leave,
                                                                        reflected)),
                            ctypes.c_int64(torch.get_num_threads()))
        rays = met.nonzero().squeeze(1)
        if rays.numel() == 0:
            return None
        leave, reflected = leave.index_select(0, rays), reflected.index_select(0, rays)
        face = order.index_select(0, entry_face.index_select(0, rays).long())
        return GlassPaths(rays=rays, t_entry=t_entry.index_select(0, rays), fresnel=fresnel.index_select(0, rays),
                          tint=self.tint(face), origins=torch.cat([leave[:, :3], reflected[:, :3]]).to(origins.dtype),
                          directions=torch.cat([leave[:, 3:], reflected[:, 3:]]).to(directions.dtype))

    def _torch_trace(self, origins: Tensor, directions: Tensor, low: Tensor, high: Tensor,
                     offset: float) -> GlassPaths | None:
        """``trace`` in torch: on any device."""
        near, far, crosses = ray_box_intersection(origins, directions, low - offset, high + offset)
        candidates = (crosses & (far > near)).nonzero().squeeze(1)
        if candidates.numel() == 0:
            return None
        o, d = origins.index_select(0, candidates).float(), directions.index_select(0, candidates).float()
        t, face, weights = self._hits(o, d, 0.0)
        met = torch.isfinite(t).nonzero().squeeze(1)
        if met.numel() == 0:
            return None
        d, t, face, weights = d[met], t[met], face[met], weights[met]
        entry = o[met] + t[:, None] * d
        normal = self._normal(face, weights)
        ior = self.ior.index_select(0, face)
        fresnel = fresnel_reflectance(d, normal, 1.0 / ior)
        reflected = reflect(d, normal)
        inside, _ = refract(d, normal, 1.0 / ior)
        leave_at, leave_along = self._leave(entry, inside, d, offset)
        return GlassPaths(rays=candidates.index_select(0, met), t_entry=t, fresnel=fresnel, tint=self.tint(face),
                          origins=torch.cat([leave_at, entry + offset * reflected]).to(origins.dtype),
                          directions=torch.cat([leave_along, reflected]).to(directions.dtype))

    def _normal(self, face: Tensor, weights: Tensor) -> Tensor:
        """The smooth normal at a crossing: its triangle's corner normals, weighted."""
        normal = (self.normals.index_select(0, face) * weights[:, :, None]).sum(dim=1)
        return normal / normal.norm(dim=1, keepdim=True).clamp(min=1e-12)

    def _leave(self, entry: Tensor, inside: Tensor, seen: Tensor, offset: float) -> tuple[Tensor, Tensor]:
        """Where and along which direction each ray that entered at ``entry`` along ``inside``
        leaves the glass; an open mesh (no crossing ahead) lets it through unbent."""
        at, along = entry.clone(), inside.clone()
        leave_at, leave_along = entry + offset * seen, seen.clone()
        trapped = torch.arange(entry.shape[0], device=entry.device)
        for crossing in range(INTERNAL_CROSSINGS):
            t, face, weights = self._hits(at[trapped], along[trapped], offset)
            found = torch.isfinite(t)
            if crossing == 0:
                trapped = trapped[found]
                t, face, weights = t[found], face[found], weights[found]
            else:  # lost inside (a broken mesh): leave from the last crossing
                lost = trapped[~found]
                leave_at[lost], leave_along[lost] = at[lost] + offset * along[lost], along[lost]
                trapped, t, face, weights = trapped[found], t[found], face[found], weights[found]
            if trapped.numel() == 0:
                break
            point = at[trapped] + t[:, None] * along[trapped]
            out, total = refract(along[trapped], self._normal(face, weights), self.ior.index_select(0, face))
            free = trapped[~total]
            leave_at[free] = point[~total] + offset * out[~total]
            leave_along[free] = out[~total]
            at[trapped], along[trapped] = point, out
            trapped = trapped[total]
            if trapped.numel() == 0:
                break
        if trapped.numel():
            leave_at[trapped], leave_along[trapped] = at[trapped] + offset * along[trapped], along[trapped]
        return leave_at, leave_along
