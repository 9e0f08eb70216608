"""Real spherical harmonics of a direction, up to degree 3: the view-dependent colour of
Plenoxels and PlenOctrees (a colour channel is a weighted sum of the basis, 9 coefficients at
degree 2). The constants are the orthonormal real basis (∫ Y_i Y_j dω = δ_ij over the
sphere), in the order and signs PlenOctrees and svox2 use, so coefficients read as theirs do.

Example:
    >>> import torch
    >>> sh_basis(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), degree=1).tolist()
    [[0.28209479177387814, -0.0, 0.4886025119029199, -0.0]]
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435)
MAX_DEGREE = 3


def sh_count(degree: int) -> int:
    """Basis functions up to ``degree``: (degree + 1)²."""
    return (degree + 1) ** 2


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """The basis at unit ``directions [P, 3]``: ``[P, (degree + 1)²]``, in their dtype."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"spherical harmonics of degree {degree}: 0 to {MAX_DEGREE} are supported")
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, C0)]
    if degree >= 1:
        terms += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        terms += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2.0 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
                  C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy),
                  C3[5] * z * (xx - yy), C3[6] * x * (xx - 3 * yy)]
    return torch.stack(terms, dim=-1)
