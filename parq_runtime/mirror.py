"""A snippet's mirror image, for test-time augmentation: flip every image left-right and
reflect the world across a vertical plane, so that the network sees a room it could have been
trained on, then reflect its boxes back.

A left-right flip of an image is the camera frame reflected across its y-z plane,
``points_camera' = F @ points_camera`` with ``F = diag(-1, 1, 1)``.  Reflecting the world too,
``points_world' = M @ points_world`` with ``M = I - 2 e e^T`` for a horizontal unit ``e``,
keeps every pose a rotation, and up stays up:

    R_world_camera' = M @ R_world_camera @ F        t_world_camera' = M @ t_world_camera

(``points_world' = M (R F F points_camera + t) = R' points_camera' + t'``; det(M R F) = +1).
A pixel (u, v) of a W-pixel-wide image moves to (W - 1 - u, v) (pixel centres at integer
coordinates, geometry's convention), so the principal point goes to W - 1 - cx.  A box the
network predicts in the mirrored world goes back with the same reflection, its object frame
reflected across the object's y-z plane (``R_world_object = M @ R' @ F``): a box is symmetric
under that, so its size is unchanged.  The mirrored snippet's local frame is the original's
with x negated, so the evaluation region (symmetric in x for every card made here and for the
authors') and the axis-aligned NMS keep the same boxes as they would unmirrored.

``benchmarks/mirror_tta.py`` measures what running each snippet both ways and fusing the
detections buys (docs/demo-experiments.md, "Mirror test-time augmentation"): on the demo's
120 held-out scenes F1 0.504 / 0.354 against 0.489 / 0.307, for twice the time.  A card
tuned with them (``parq_train.tune --mirror``, the demo's) makes them parq-run's default.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import geometry

F_FLIP = np.diag([-1.0, 1.0, 1.0])


def world_reflection(up=geometry.UP_Z) -> np.ndarray:
    """M (3, 3): the reflection across the vertical plane normal to the first horizontal axis
    of ``up``'s basis (the world x axis for up = +z); M @ M = I, M @ up = up."""
    e1, _ = geometry.horizontal_basis(up)
    return np.eye(3) - 2.0 * np.outer(e1, e1)


def mirror_snippet(images: list, intrinsics: np.ndarray, T_world_camera: np.ndarray,
                   up=geometry.UP_Z) -> tuple:
    """The mirror image of a snippet.  images: N RGB arrays (H_i, W_i, 3); intrinsics (N, 3, 3);
    T_world_camera (N, 4, 4).  Returns (images flipped left-right, intrinsics with cx -> W_i -
    1 - cx, T_world'_camera' (N, 4, 4) in the reflected world)."""
    M = world_reflection(up)
    flipped = [np.ascontiguousarray(np.asarray(image)[:, ::-1]) for image in images]
    K = np.array(intrinsics, dtype=np.float64)
    for i, image in enumerate(images):
        K[i, 0, 2] = np.asarray(image).shape[1] - 1 - K[i, 0, 2]
    T = np.array(T_world_camera, dtype=np.float64)
    T[:, :3, :3] = M @ T[:, :3, :3] @ F_FLIP
    T[:, :3, 3] = T[:, :3, 3] @ M.T
    return flipped, K, T


def unmirror_box(box, up=geometry.UP_Z):
    """A boxes.Box predicted in the reflected world, back in the real one."""
    M = world_reflection(up)
    center = M @ box.center
    rotation = M @ box.rotation @ F_FLIP
    viewpoint = None if box.viewpoint is None else M @ box.viewpoint
    return replace(box, center=center, rotation=rotation,
                   yaw=float(geometry.yaw(rotation, up)),
                   corners=geometry.box_corners(center, box.size, rotation),
                   viewpoint=viewpoint)
