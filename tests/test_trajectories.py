"""The protocol's camera rig as pure maths (datasets_gen.core.trajectories): no Blender needed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from datasets_gen.core import trajectories as tr

RADIUS = math.sqrt(16.25)
BASE_ELEVATION = math.atan2(0.5, 4.0)  # 7.125 deg: the rig's elevation with no tilt


def as_array(pose: tr.RigPose) -> np.ndarray:
    return np.asarray(pose.matrix, dtype=np.float64)


def elevation(matrix: np.ndarray) -> float:
    position = matrix[:3, 3]
    return math.asin(position[2] / np.linalg.norm(position))


def all_pose_sets() -> dict[str, list[tr.RigPose]]:
    return {
        "hemisphere": tr.hemisphere_poses(300, tr.split_rng(0, "train")),
        "sphere": tr.hemisphere_poses(300, tr.split_rng(0, "train"), full_sphere=True),
        "spiral": tr.test_spiral_poses(200),
        "spiral_odd": tr.test_spiral_poses(37),
    }


def test_look_at_follows_blender_camera_convention() -> None:
    matrix = np.asarray(tr.look_at((0.0, -4.0, 0.0)))
    # Looking along +Y from -Y: camera -Z is +Y, image right (+X) is world +X, image up is +Z.
    np.testing.assert_allclose(-matrix[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(matrix[:3, 1], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(matrix[3], [0, 0, 0, 1])


@pytest.mark.parametrize("height", [3.0, -3.0])
def test_look_at_straight_down_or_up_at_the_pole(height: float) -> None:
    """The up vector is degenerate there: the pose is still a proper rotation looking at the
    target, and straight down it is the limit of views approaching at azimuth 0."""
    pose = tr.look_at((0.0, 0.0, height))
    rotation = [row[:3] for row in pose[:3]]
    for i in range(3):
        for j in range(3):
            dot = sum(rotation[k][i] * rotation[k][j] for k in range(3))
            assert dot == pytest.approx(1.0 if i == j else 0.0, abs=1e-12)
    determinant = (rotation[0][0] * (rotation[1][1] * rotation[2][2] - rotation[1][2] * rotation[2][1])
                   - rotation[0][1] * (rotation[1][0] * rotation[2][2] - rotation[1][2] * rotation[2][0])
                   + rotation[0][2] * (rotation[1][0] * rotation[2][1] - rotation[1][1] * rotation[2][0]))
    assert determinant == pytest.approx(1.0, abs=1e-12)
    assert [pose[k][2] for k in range(3)] == pytest.approx([0.0, 0.0, 1.0 if height > 0 else -1.0])
    if height > 0:
        near_pole = tr.look_at((0.0, -1e-6, height))
        for row, near_row in zip(pose, near_pole):
            assert row == pytest.approx(near_row, abs=1e-5)


def test_radius_constant() -> None:
    assert tr.RIG_RADIUS == pytest.approx(4.0311, abs=1e-4)


@pytest.mark.parametrize("name", ["hemisphere", "sphere", "spiral", "spiral_odd"])
def test_every_pose_is_a_rig_pose(name: str) -> None:
    """Radius sqrt(16.25), camera -Z at the origin, proper rotation, upright camera."""
    for pose in all_pose_sets()[name]:
        matrix = as_array(pose)
        position = matrix[:3, 3]
        rotation = matrix[:3, :3]
        assert np.linalg.norm(position) == pytest.approx(RADIUS, abs=1e-6)
        np.testing.assert_allclose(-rotation[:, 2], -position / np.linalg.norm(position), atol=1e-9)
        np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-9)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-9)
        assert rotation[2, 1] >= -1e-12, "camera +Y must not point below the horizon (Track-To up)"
        np.testing.assert_allclose(matrix[3], [0, 0, 0, 1])


def test_hemisphere_elevation_follows_the_rig_tilt() -> None:
    """elevation = X + atan(0.5/4), folded back past the pole: asin(z/r) lies in [7.1, 90] deg."""
    poses = tr.hemisphere_poses(2000, tr.split_rng(3, "train"))
    elevations = []
    for pose in poses:
        expected = pose.tilt_x + BASE_ELEVATION
        expected = min(expected, math.pi - expected)  # past the pole the camera comes down the far side
        measured = elevation(as_array(pose))
        assert measured == pytest.approx(expected, abs=1e-9)
        assert 0.0 <= pose.tilt_x <= math.pi / 2
        elevations.append(math.degrees(measured))
    assert min(elevations) >= 7.1 and max(elevations) <= 90.0
    # Uniform directions: half the hemisphere lies below a 30 deg tilt, i.e. 37.1 deg elevation.
    assert np.mean(np.asarray(elevations) < 30.0 + math.degrees(BASE_ELEVATION)) == pytest.approx(0.5, abs=0.05)


def test_hemisphere_azimuth_covers_the_circle() -> None:
    poses = tr.hemisphere_poses(2000, tr.split_rng(0, "val"))
    azimuths = np.asarray([pose.azimuth_z for pose in poses])
    assert azimuths.min() >= 0.0 and azimuths.max() < 2 * math.pi
    counts, _ = np.histogram(azimuths, bins=8, range=(0, 2 * math.pi))
    assert counts.min() > 180


def test_full_sphere_goes_below_the_horizon() -> None:
    poses = tr.hemisphere_poses(2000, tr.split_rng(0, "train"), full_sphere=True)
    tilts = np.asarray([pose.tilt_x for pose in poses])
    assert tilts.min() >= -math.pi / 2 and tilts.max() <= math.pi / 2
    elevations = np.degrees([elevation(as_array(pose)) for pose in poses])
    assert (elevations < -30).any() and (elevations > 60).any()
    # Below the horizon means a tilt below -7.125 deg: probability (1 - sin 7.125 deg) / 2 = 0.438.
    assert np.mean(elevations < 0) == pytest.approx((1 - math.sin(BASE_ELEVATION)) / 2, abs=0.04)


def test_test_spiral_matches_the_published_path() -> None:
    poses = tr.test_spiral_poses(200)
    first = as_array(poses[0])
    assert first[0, 3] == pytest.approx(0.0, abs=1e-12) and first[1, 3] > 0, "frame 0 looks from +Y"
    assert math.degrees(elevation(first)) == pytest.approx(47.2, abs=0.05)
    assert math.degrees(elevation(as_array(poses[100]))) == pytest.approx(7.1, abs=0.05)
    assert poses[1].azimuth_z - poses[0].azimuth_z == pytest.approx(math.radians(3.6))
    assert poses[1].tilt_x == pytest.approx((math.cos(math.radians(1.8)) + 1) / 2 * 0.7)


@pytest.mark.parametrize("count", [200, 37, 8])
def test_test_spiral_is_two_turns_and_closes(count: int) -> None:
    """Azimuth advances 720/n deg per frame, including from the last frame back to frame 0 (two turns)."""
    poses = tr.test_spiral_poses(count)
    positions = np.asarray([as_array(pose)[:3, 3] for pose in poses])
    angles = np.unwrap(np.arctan2(positions[:, 1], positions[:, 0]))
    steps = np.diff(np.append(angles, angles[0] + 4 * math.pi))
    np.testing.assert_allclose(steps, 4 * math.pi / count, atol=1e-9)
    # The tilt makes one cosine period, so frame n would repeat frame 0: elevation(i) = elevation(n - i).
    elevations = [elevation(as_array(pose)) for pose in poses]
    for index in range(1, count):
        assert elevations[index] == pytest.approx(elevations[count - index], abs=1e-9)


def test_same_seed_same_poses_different_seed_different() -> None:
    first = tr.hemisphere_poses(20, tr.split_rng(7, "train"))
    again = tr.hemisphere_poses(20, tr.split_rng(7, "train"))
    other_seed = tr.hemisphere_poses(20, tr.split_rng(8, "train"))
    other_split = tr.hemisphere_poses(20, tr.split_rng(7, "val"))
    assert [p.matrix for p in first] == [p.matrix for p in again]
    assert not np.allclose([p.matrix for p in first], [p.matrix for p in other_seed])
    assert not np.allclose([p.matrix for p in first], [p.matrix for p in other_split])


def test_rotation_step_matches_the_published_test_files() -> None:
    assert tr.rotation_step(200) == pytest.approx(0.031415926535897934)
    assert tr.rotation_step(0) == 0.0
