"""Positional (Fourier-feature) encoding, the NeRF paper's γ(p)."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class PositionalEncoding(nn.Module):
    """γ(p) = (p, sin(2⁰p), cos(2⁰p), …, sin(2^{L-1}p), cos(2^{L-1}p)), per coordinate.

    As in the authors' released code the input itself is kept and the frequencies are
    2^k without the paper's factor π (the scene sits in about [-1.5, 1.5], so the lowest
    band already spans it). ``num_frequencies = 0`` is the identity: the "no positional
    encoding" ablation.

    Example:
        >>> enc = PositionalEncoding(in_dims=3, num_frequencies=10)
        >>> enc(torch.zeros(5, 3)).shape
        torch.Size([5, 63])
    """

    def __init__(self, in_dims: int, num_frequencies: int) -> None:
        super().__init__()
        self.in_dims = in_dims
        self.num_frequencies = num_frequencies
        self.register_buffer(
            "frequencies", 2.0 ** torch.arange(num_frequencies, dtype=torch.float32), persistent=False
        )

    @property
    def out_dims(self) -> int:
        return self.in_dims * (1 + 2 * self.num_frequencies)

    def forward(self, x: Tensor) -> Tensor:
        """``x [..., in_dims]`` → ``[..., out_dims]``, ordered (x, sin band 0, cos band 0, …)."""
        if self.num_frequencies == 0:
            return x
        scaled = x[..., None, :] * self.frequencies[:, None]  # [..., L, D]
        bands = torch.stack([torch.sin(scaled), torch.cos(scaled)], dim=-2)  # [..., L, 2, D]
        return torch.cat([x, bands.flatten(-3)], dim=-1)
