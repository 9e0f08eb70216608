"""A deliberately plain NeRF training step, the yardstick of ``python -m nerf_backend bench-step``.

The same maths as a NeRF preset (the paper's by default): the MLP of the preset's
``FieldConfig`` (ReLU trunk, the encoded position fed again at the skip layers, a
direction branch), Fourier features of the same L, the same stratified + importance
sample counts, rays per batch and Adam. It is written the way most NeRF code is written:
every sample of a pass through one MLP call, alpha compositing with a cumulative product of
``1 - α + 1e-10``, a last interval of 1e10, inverse-CDF sampling with ``searchsorted``,
near/far fixed at the protocol's 2 and 6. Nothing in training uses it; it exists so the
project's own per-iteration cost is measured against something outside the project.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..configs.train_config import TrainConfig


def fourier_features(x: Tensor, frequencies: int) -> Tensor:
    parts = [x]
    for k in range(frequencies):
        parts += [torch.sin(x * 2.0**k), torch.cos(x * 2.0**k)]
    return torch.cat(parts, dim=-1)


class PlainMLP(nn.Module):
    """The NeRF MLP as one module: ``forward(encoded_x, encoded_d) -> (sigma [N], rgb [N, 3])``."""

    def __init__(self, config: TrainConfig) -> None:
        super().__init__()
        field = config.field
        self.skips = set(field.skips)
        x_dims, d_dims = 3 + 6 * field.position_frequencies, 3 + 6 * field.direction_frequencies
        self.layers = nn.ModuleList(
            nn.Linear((x_dims if i == 0 else field.width) + (x_dims if i in self.skips else 0), field.width)
            for i in range(field.depth)
        )
        self.sigma = nn.Linear(field.width, 1)
        self.feature = nn.Linear(field.width, field.width)
        self.view = nn.Linear(field.width + d_dims, field.colour_width)
        self.rgb = nn.Linear(field.colour_width, 3)

    def forward(self, ex: Tensor, ed: Tensor) -> tuple[Tensor, Tensor]:
        h = ex
        for i, layer in enumerate(self.layers):
            h = F.relu(layer(torch.cat([h, ex], -1) if i in self.skips else h))
        sigma = F.relu(self.sigma(h)[:, 0])
        h = F.relu(self.view(torch.cat([self.feature(h), ed], -1)))
        return sigma, torch.sigmoid(self.rgb(h))


def _composite(mlp: PlainMLP, config: TrainConfig, rays_o: Tensor, rays_d: Tensor, z: Tensor) -> tuple[Tensor, Tensor]:
    """RGB over white ``[R, 3]`` and weights ``[R, S]`` for samples at depths ``z [R, S]``."""
    points = rays_o[:, None] + rays_d[:, None] * z[..., None]
    view_dirs = F.normalize(rays_d, dim=-1)[:, None].expand(points.shape)
    field = config.field
    sigma, rgb = mlp(fourier_features(points.reshape(-1, 3), field.position_frequencies),
                     fourier_features(view_dirs.reshape(-1, 3), field.direction_frequencies))
    sigma, rgb = sigma.view(z.shape), rgb.view(*z.shape, 3)
    dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], 1e10)], -1) * rays_d.norm(dim=-1, keepdim=True)
    alpha = 1.0 - torch.exp(-sigma * dists)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1), -1)[:, :-1]
    weights = alpha * transmittance
    return (weights[..., None] * rgb).sum(1) + (1.0 - weights.sum(-1, keepdim=True)), weights


def _importance(bins: Tensor, weights: Tensor, count: int) -> Tensor:
    pdf = (weights + 1e-5) / (weights + 1e-5).sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    u = torch.rand(cdf.shape[0], count).contiguous()
    above = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    cdf_lo, cdf_hi = cdf.gather(1, above - 1), cdf.gather(1, above)
    bin_lo, bin_hi = bins.gather(1, above - 1), bins.gather(1, above)
    span = torch.where(cdf_hi - cdf_lo < 1e-5, torch.ones_like(cdf_lo), cdf_hi - cdf_lo)
    return bin_lo + (u - cdf_lo) / span * (bin_hi - bin_lo)


class PlainNerf(nn.Module):
    """Coarse and fine ``PlainMLP`` and one training step of the paper's loss."""

    def __init__(self, config: TrainConfig) -> None:
        super().__init__()
        self.config = config
        self.coarse = PlainMLP(config)
        self.fine = PlainMLP(config) if config.sampling.fine_samples > 0 else None

    def loss(self, rays_o: Tensor, rays_d: Tensor, target: Tensor) -> Tensor:
        sampling = self.config.sampling
        near, far = 2.0, 6.0
        edges = torch.linspace(near, far, sampling.coarse_samples + 1)
        lower, upper = edges[:-1].expand(len(rays_o), -1), edges[1:].expand(len(rays_o), -1)
        z = lower + (upper - lower) * torch.rand_like(lower)
        rgb, weights = _composite(self.coarse, self.config, rays_o, rays_d, z)
        loss = F.mse_loss(rgb, target)
        if self.fine is not None:
            mids = 0.5 * (z[:, 1:] + z[:, :-1])
            extra = _importance(mids, weights[:, 1:-1].detach(), sampling.fine_samples)
            z_fine, _ = torch.sort(torch.cat([z, extra.detach()], -1), -1)
            rgb_fine, _ = _composite(self.fine, self.config, rays_o, rays_d, z_fine)
            loss = loss + F.mse_loss(rgb_fine, target)
        return loss


def plain_rays(fx: float, fy: float, cx: float, cy: float, c2w: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, Tensor]:
    """Pinhole rays through pixel centres (Blender/OpenGL camera: -z forward, +y up)."""
    dirs = torch.stack([(px + 0.5 - cx) / fx, -(py + 0.5 - cy) / fy, -torch.ones_like(px)], -1)
    rays_d = (dirs[:, None, :] * c2w[:, :3, :3]).sum(-1)
    return c2w[:, :3, 3], rays_d
