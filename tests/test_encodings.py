import math

import pytest
import torch

from nerf_backend.field_components.encodings import PositionalEncoding


def test_positional_encoding_values():
    enc = PositionalEncoding(in_dims=3, num_frequencies=10)
    x = torch.tensor([[0.5, -1.0, 0.25]], dtype=torch.float64)
    out = enc(x)[0]
    assert enc.out_dims == 63 and out.shape == (63,)
    assert out[:3].tolist() == [0.5, -1.0, 0.25]
    for k in range(10):
        sin_band = out[3 + 6 * k: 6 + 6 * k]
        cos_band = out[6 + 6 * k: 9 + 6 * k]
        for d, value in enumerate((0.5, -1.0, 0.25)):
            assert sin_band[d].item() == pytest.approx(math.sin(2**k * value), abs=1e-6)
            assert cos_band[d].item() == pytest.approx(math.cos(2**k * value), abs=1e-6)


def test_direction_encoding_size_and_identity_ablation():
    assert PositionalEncoding(3, 4).out_dims == 27
    x = torch.randn(7, 3)
    assert torch.equal(PositionalEncoding(3, 0)(x), x)
