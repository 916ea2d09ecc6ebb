"""Frames, poses and cameras, in numpy (float64 unless stated).

Notation follows the paper: ``T_a_b`` is a 4x4 rigid transform that takes points in frame b to
frame a (``points_a = T_a_b @ points_b``).  Frames:

* ``world``: z up (the authors' ScanNet convention); other up axes are passed as ``up``;
* ``camera``: OpenCV axes, x right, y down, z forward;
* ``pseudo``: the gravity-aligned camera of one view: origin at the camera centre, y = world up,
  z = the camera's forward direction projected on the horizontal plane, x = y cross z (the
  camera's left).  A level camera has ``R_camera_pseudo = diag(-1, -1, 1)``;
* ``local``: the snippet frame, the pseudo camera of view ``int(N * 0.5)``; every box is
  predicted in it;
* ``object``: a box's own axes, y up, the box spanning [-size/2, size/2].

A pinhole ``camera`` is (fx, fy, cx, cy); pixel (u, v) has its centre at integer coordinates.
"""
from __future__ import annotations

import numpy as np

from .errors import ParqError

UP_Z = (0.0, 0.0, 1.0)

# Corner order of the authors' Obb3D: (x, y, z) signs of the half extents.
CORNER_SIGNS = np.array([[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
                         [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], dtype=np.float64)
# The 12 edges of a box as pairs of corner indices.
BOX_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
             (0, 4), (1, 5), (2, 6), (3, 7))


def invert(T_a_b: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): T_b_a."""
    R = T_a_b[..., :3, :3]
    t = T_a_b[..., :3, 3]
    T_b_a = np.zeros_like(T_a_b)
    T_b_a[..., :3, :3] = np.swapaxes(R, -1, -2)
    T_b_a[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    T_b_a[..., 3, 3] = 1.0
    return T_b_a


def transform(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply T_a_b (4, 4) to points (..., 3)."""
    return points_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


# Metres a pose may lie from the world's origin: an Earth-centred frame fits, a value that
# would overflow the float32 arithmetic downstream (or a pose in micrometres) does not.
MAX_TRANSLATION = 1e8


def check_rigid(T: np.ndarray, what: str = "pose", tol: float = 1e-3) -> None:
    """Raise ParqError unless T (..., 4, 4) holds finite rigid transforms (rotation with
    det +1, bottom row 0 0 0 1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ParqError(f"{what}: expected 4x4 matrices, got shape {T.shape}")
    flat = T.reshape(-1, 4, 4)
    for i, M in enumerate(flat):
        where = what if len(flat) == 1 else f"{what} {i}"
        if not np.all(np.isfinite(M)):
            raise ParqError(f"{where}: holds NaN or infinite values")
        if np.abs(M[:3, 3]).max() > MAX_TRANSLATION:
            raise ParqError(f"{where}: translation {M[:3, 3].tolist()} is beyond "
                            f"{MAX_TRANSLATION:.0e} m (wrong units?)")
        if np.abs(M[3] - (0, 0, 0, 1)).max() > tol:
            raise ParqError(f"{where}: bottom row is {M[3].tolist()}, not [0, 0, 0, 1]")
        R = M[:3, :3]
        err = np.abs(R.T @ R - np.eye(3)).max()
        if err > tol or np.linalg.det(R) < 0:
            raise ParqError(f"{where}: rotation part is not a rotation "
                            f"(|R^T R - I| = {err:.2g}, det = {np.linalg.det(R):.3g})")


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def pseudo_cameras(T_world_camera: np.ndarray, up=UP_Z) -> np.ndarray:
    """Gravity-aligned pseudo camera of each view: (N, 4, 4) T_world_camera -> T_world_pseudo."""
    up = unit(np.asarray(up, dtype=np.float64))
    forward = T_world_camera[:, :3, 2]
    horizontal = forward - (forward @ up)[:, None] * up
    norm = np.linalg.norm(horizontal, axis=-1)
    if np.any(norm < 1e-6):
        i = int(np.argmax(norm < 1e-6))
        raise ParqError(f"view {i} looks straight along the up axis; its gravity-aligned frame "
                        "is undefined (check the poses or --up)")
    z = horizontal / norm[:, None]
    y = np.broadcast_to(up, z.shape)
    x = unit(np.cross(y, z))
    T_world_pseudo = np.array(T_world_camera, dtype=np.float64, copy=True)
    T_world_pseudo[:, :3, :3] = np.stack([x, y, z], -1)
    return T_world_pseudo


def local_view(num_views: int) -> int:
    """Index of the view whose pseudo camera is the snippet frame (the authors' int(N * 0.5))."""
    return int(num_views * 0.5)


def snippet_frame(T_world_camera: np.ndarray, up=UP_Z) -> np.ndarray:
    """T_world_local (4, 4) of a snippet given its views' poses (N, 4, 4)."""
    return pseudo_cameras(T_world_camera, up)[local_view(len(T_world_camera))]


def scale_camera(camera: np.ndarray, s: float) -> np.ndarray:
    """Pinhole (..., 4) after resizing an image by s: f * s, c' = (c + 0.5) * s - 0.5."""
    camera = np.asarray(camera, dtype=np.float64)
    return np.concatenate([camera[..., :2] * s, (camera[..., 2:] + 0.5) * s - 0.5], -1)


def pinhole(K: np.ndarray) -> np.ndarray:
    """3x3 intrinsics (..., 3, 3) -> (..., 4) = (fx, fy, cx, cy)."""
    K = np.asarray(K, dtype=np.float64)
    return np.stack([K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]], -1)


def project(points_camera: np.ndarray, camera: np.ndarray, size, eps: float = 1e-3):
    """Project points (..., 3) in camera frames with pinholes (..., 4) broadcastable to them.

    Returns uv (..., 2) and valid (...): z > eps and 0 <= u <= w - 1 and 0 <= v <= h - 1,
    with z clamped to eps before dividing (the authors' Camera.project).
    """
    w, h = size
    z = points_camera[..., 2]
    zc = np.maximum(z, eps)
    u = points_camera[..., 0] / zc * camera[..., 0] + camera[..., 2]
    v = points_camera[..., 1] / zc * camera[..., 1] + camera[..., 3]
    valid = (z > eps) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    return np.stack([u, v], -1), valid


def rotation_from_6d(a: np.ndarray) -> np.ndarray:
    """6D rotation (..., 6) -> (..., 3, 3), columns x = normalise(a[0:3]),
    z = normalise(x cross a[3:6]), y = z cross x."""
    a = np.asarray(a, dtype=np.float64)
    x = a[..., 0:3] / np.maximum(np.linalg.norm(a[..., 0:3], axis=-1, keepdims=True), 1e-8)
    z = np.cross(x, a[..., 3:6])
    z = z / np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), 1e-8)
    return np.stack([x, np.cross(z, x), z], -1)


def box_corners(center: np.ndarray, size: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Corners (..., 8, 3) of boxes with centers (..., 3), full extents (..., 3) and rotations
    (..., 3, 3) = R_frame_object, in the authors' corner order (CORNER_SIGNS)."""
    corners_object = CORNER_SIGNS * (np.asarray(size)[..., None, :] / 2)
    return corners_object @ np.swapaxes(R, -1, -2) + np.asarray(center)[..., None, :]


def yaw(R_world_object: np.ndarray, up=UP_Z) -> np.ndarray:
    """Heading of boxes (..., 3, 3) about the up axis, radians in (-pi, pi]: the angle of the
    object's x axis projected on the horizontal plane, counter-clockwise seen from above, from
    the world x axis (for up = +z) or from the first horizontal axis of the world's basis."""
    up = unit(np.asarray(up, dtype=np.float64))
    e1, e2 = horizontal_basis(up)
    x_axis = np.asarray(R_world_object)[..., :, 0]
    return np.arctan2(x_axis @ e2, x_axis @ e1)


def horizontal_basis(up) -> tuple:
    """Two unit vectors (e1, e2) spanning the plane normal to ``up`` with e1 x e2 = up; for up
    = +z they are the world x and y axes."""
    up = unit(np.asarray(up, dtype=np.float64))
    ref = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = unit(ref - (ref @ up) * up)
    return e1, np.cross(up, e1)


def camera_pose(position, yaw: float, tilt: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """T_world_camera (4, 4) of an OpenCV camera in a z-up world at ``position``, heading ``yaw``
    (radians, counter-clockwise from world x), pitched down by ``tilt`` and rolled clockwise (as
    seen by the camera) by ``roll``."""
    forward = np.array([np.cos(yaw) * np.cos(tilt), np.sin(yaw) * np.cos(tilt), -np.sin(tilt)])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    T = np.eye(4)
    T[:3, 0] = c * right + s * down
    T[:3, 1] = -s * right + c * down
    T[:3, 2] = forward
    T[:3, 3] = position
    return T
