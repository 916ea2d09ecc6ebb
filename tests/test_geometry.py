"""Geometry against values computed by hand."""
import numpy as np
import pytest

from parq_runtime import geometry, keyframes
from parq_runtime.errors import ParqError


def test_level_camera_pseudo_frame_flips_x_and_y():
    # Camera at (1, 2, 1.5) looking along world +y, level.
    T_world_camera = geometry.camera_pose([1, 2, 1.5], np.pi / 2)
    T_world_pseudo = geometry.pseudo_cameras(T_world_camera[None])[0]
    T_camera_pseudo = geometry.invert(T_world_camera) @ T_world_pseudo
    np.testing.assert_allclose(T_camera_pseudo, np.diag([-1.0, -1, 1, 1]), atol=1e-12)
    # pseudo axes in the world: y = up, z = forward (+y), x = y cross z = -x (camera's left)
    np.testing.assert_allclose(T_world_pseudo[:3, :3],
                               [[-1, 0, 0], [0, 0, 1], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(T_world_pseudo[:3, 3], [1, 2, 1.5])


def test_tilted_camera_pseudo_frame_is_level_and_keeps_heading():
    tilt = np.radians(30)
    T_world_camera = geometry.camera_pose([0, 0, 1.5], 0.0, tilt)
    # forward = (cos 30, 0, -sin 30); the pseudo z is its horizontal part, normalised.
    np.testing.assert_allclose(T_world_camera[:3, 2], [np.cos(tilt), 0, -np.sin(tilt)],
                               atol=1e-12)
    R_world_pseudo = geometry.pseudo_cameras(T_world_camera[None])[0][:3, :3]
    np.testing.assert_allclose(R_world_pseudo, [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-12)
    # In the pseudo frame the camera's optical axis points 30 degrees below the horizon.
    R_pseudo_camera = R_world_pseudo.T @ T_world_camera[:3, :3]
    np.testing.assert_allclose(R_pseudo_camera[:, 2], [0, -np.sin(tilt), np.cos(tilt)],
                               atol=1e-12)


def test_snippet_frame_is_the_middle_views_pseudo_camera():
    poses = np.stack([geometry.camera_pose([x, 0, 1.4], 0.1 * x, 0.2) for x in range(4)])
    for n in (1, 2, 3, 4):
        expected = geometry.pseudo_cameras(poses[:n])[int(n * 0.5)]
        np.testing.assert_array_equal(geometry.snippet_frame(poses[:n]), expected)
    assert [geometry.local_view(n) for n in (1, 2, 3, 4, 5)] == [0, 1, 1, 2, 2]


def test_pseudo_frame_rejects_camera_looking_straight_down():
    T = geometry.camera_pose([0, 0, 1], 0.0, np.pi / 2)
    with pytest.raises(ParqError, match="straight along the up axis"):
        geometry.pseudo_cameras(T[None])


def test_projection_by_hand():
    camera = np.array([100.0, 110.0, 40.0, 30.0])
    points = np.array([[0.2, -0.1, 2.0],     # u = 0.1*100+40 = 50, v = -0.05*110+30 = 24.5
                       [0.0, 0.0, -1.0],     # behind: invalid even though it lands at c
                       [10.0, 0.0, 1.0],     # far right: u = 1040
                       [-0.8, 0.0, 2.0]])    # u = -0.4*100 + 40 = 0: on the border, valid
    uv, valid = geometry.project(points, camera, (80, 60))
    np.testing.assert_allclose(uv[0], [50.0, 24.5])
    np.testing.assert_allclose(uv[1], [40.0, 30.0])  # z clamped to 1e-3, x = y = 0
    np.testing.assert_allclose(uv[3], [0.0, 30.0])
    assert valid.tolist() == [True, False, False, True]


def test_scale_to_feature_resolution():
    # s = 1/4: f * s and c' = (c + 0.5) * s - 0.5; a 320x240 camera centred at (159.5, 119.5)
    # maps to the centre of the 80x60 grid, (39.5, 29.5).
    scaled = geometry.scale_camera(np.array([288.0, 290.0, 159.5, 119.5]), 0.25)
    np.testing.assert_allclose(scaled, [72.0, 72.5, 39.5, 29.5])
    np.testing.assert_allclose(geometry.pinhole(np.array([[1, 0, 3], [0, 2, 4], [0, 0, 1.]])),
                               [1, 2, 3, 4])


def test_rotation_from_6d():
    np.testing.assert_allclose(geometry.rotation_from_6d([1, 0, 0, 0, 1, 0]), np.eye(3))
    # columns x = (0, 1, 0), second vector (-1, 0, 0): 90 degrees about z
    R = geometry.rotation_from_6d([0, 2, 0, -3, 0.5, 0])
    np.testing.assert_allclose(R, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # Gram-Schmidt: the second vector's component along x is removed
    R = geometry.rotation_from_6d([1, 0, 0, 1, 1, 0])
    np.testing.assert_allclose(R, np.eye(3), atol=1e-12)
    R = geometry.rotation_from_6d(np.random.default_rng(0).normal(size=(50, 6)))
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0)


def test_box_corners_and_yaw():
    yaw = np.radians(30)
    x = [np.cos(yaw), np.sin(yaw), 0]
    R = np.stack([x, [0, 0, 1], np.cross(x, [0, 0, 1])], -1)
    corners = geometry.box_corners(np.array([1.0, 2.0, 0.5]), np.array([2.0, 1.0, 4.0]), R)
    # corner 0 = center - x * 1 - up * 0.5 - z * 2
    expected0 = np.array([1, 2, 0.5]) - np.array(x) - [0, 0, 0.5] - 2 * np.cross(x, [0, 0, 1])
    np.testing.assert_allclose(corners[0], expected0)
    np.testing.assert_allclose(corners.mean(0), [1, 2, 0.5])
    assert geometry.yaw(R) == pytest.approx(yaw)


def test_invert_and_rigid_checks():
    T = geometry.camera_pose([1, 2, 3], 0.4, 0.3, 0.1)
    np.testing.assert_allclose(geometry.invert(T) @ T, np.eye(4), atol=1e-12)
    geometry.check_rigid(T)
    bad = T.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ParqError, match="NaN"):
        geometry.check_rigid(bad, "pose/3.txt")
    scaled = T.copy()
    scaled[:3, :3] *= 2
    with pytest.raises(ParqError, match="not a rotation"):
        geometry.check_rigid(scaled)
    mirrored = T.copy()
    mirrored[:3, 0] *= -1
    with pytest.raises(ParqError, match="det"):
        geometry.check_rigid(mirrored)


def test_keyframes_by_turn_and_motion():
    poses = [geometry.camera_pose([0, 0, 1.5], np.radians(a)) for a in (0, 10, 16, 20, 40)]
    assert keyframes.select(poses) == [0, 2, 4]         # 16 deg > 15; 40 - 16 = 24 > 15
    moves = [geometry.camera_pose([d, 0, 1.5], 0) for d in (0, 0.05, 0.09, 0.11, 0.2, 0.25)]
    assert keyframes.select(moves) == [0, 3, 5]        # 0.11 > 0.1; 0.25 - 0.11 > 0.1
    assert keyframes.windows(list(range(8)), 3) == [[0, 1, 2], [3, 4, 5]]
    assert keyframes.windows(list(range(5)), 3, 1) == [[0, 1, 2], [1, 2, 3], [2, 3, 4]]
    assert keyframes.windows(list(range(8)), 3, 1, gap=3) == [[0, 3, 6], [1, 4, 7]]
    assert keyframes.windows(list(range(11)), 3, gap=2) == [[0, 2, 4], [3, 5, 7], [6, 8, 10]]
    assert keyframes.windows(list(range(4)), 3, gap=2) == []      # spans 5 keyframes
    with pytest.raises(ParqError, match="gap"):
        keyframes.windows(list(range(8)), 3, gap=0)
