"""Rays through pixel centres with exact intrinsics."""

import math

import pytest
import torch

from nerf_backend.core.cameras import Intrinsics, camera_rays, pixel_centres, project_points, ray_box_intersection


def _look_at(position, target=(0.0, 0.0, 0.0)):
    position = torch.tensor(position, dtype=torch.float64)
    forward = torch.tensor(target, dtype=torch.float64) - position
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = right / right.norm()
    up = torch.linalg.cross(right, forward)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, -forward, position
    return pose


@pytest.mark.parametrize("intrinsics", [
    Intrinsics(800, 800, 1111.111, 1111.111, 400.0, 400.0),
    Intrinsics(800, 600, 1111.111, 1111.111, 320.0, 340.0),  # lens shift (PROTOCOL.md's measured case)
    Intrinsics(48, 64, 80.0, 90.0, 23.0, 33.5),  # portrait, non-square pixels
])
def test_ray_through_a_points_pixel_passes_through_the_point(intrinsics):
    pose = _look_at((2.5, -3.0, 1.5))
    points = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.3, -0.2], [0.0, 0.0, 0.0]], dtype=torch.float64)
    pixels = project_points(intrinsics, pose, points)
    origins, directions = camera_rays(intrinsics, pose, pixels)
    to_point = points - origins
    # Distance from each point to its ray.
    along = (to_point * directions).sum(-1, keepdim=True)
    assert (to_point - along * directions).norm(dim=-1).max().item() < 1e-9
    assert torch.allclose(directions.norm(dim=-1), torch.ones(3, dtype=torch.float64))


def test_pixel_centres_are_at_half_integers_and_the_centre_ray_is_the_optical_axis():
    k = Intrinsics.from_camera_angle_x(4, 4, 0.6911112)
    assert k.fl_x == pytest.approx(0.5 * 4 / math.tan(0.5 * 0.6911112))
    centres = pixel_centres(4, torch.arange(16))
    assert centres[0].tolist() == [0.5, 0.5] and centres[5].tolist() == [1.5, 1.5]
    _, d = camera_rays(k, torch.eye(4), torch.tensor([[2.0, 2.0]]))
    assert d.tolist() == [[0.0, 0.0, -1.0]]
    # Image x right = camera +X; image y down = camera −Y.
    _, d = camera_rays(k, torch.eye(4), torch.tensor([[3.5, 0.5]]))
    assert d[0, 0] > 0 and d[0, 1] > 0


def test_ray_box_intersection():
    box_min, box_max = -torch.ones(3), torch.ones(3)
    origins = torch.tensor([[0.0, -5.0, 0.0], [0.0, -5.0, 3.0], [0.0, 0.0, 0.0], [1.0, -5.0, 0.0]])
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    t_near, t_far, hit = ray_box_intersection(origins, directions, box_min, box_max)
    assert hit.tolist() == [True, False, True, False]  # hit, miss, inside, tangent (zero length)
    assert (t_near[0].item(), t_far[0].item()) == (4.0, 6.0)
    assert t_near[1] == t_far[1]  # a miss gives a zero-length interval
    assert (t_near[2].item(), t_far[2].item()) == (0.0, 1.0)  # a camera inside starts at itself
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
