"""parq-train --mirror: a mirrored training snippet is the snippet of the mirrored room."""
import numpy as np
import torch

from parq_runtime import geometry
from parq_runtime.mirror import F_FLIP, mirror_snippet, world_reflection
from parq_train import mirror, train
from parq_train.data import Snippet

from conftest import tiny_config
from test_train import tiny_snippets


def yaw_pitch_pose(yaw, pitch, position):
    """T_world_camera (4, 4) of a camera at ``position`` looking along yaw (about world z,
    up) tilted down by pitch; camera x right, y down, z forward."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw),
                        -np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], -1)
    T[:3, 3] = position
    return T


def snippet_of(images, K, T_world_camera, centers_world, R_world_object, stride):
    """A Snippet as parq_train.data cuts one: targets and cameras in the local frame."""
    T_local_world = geometry.invert(geometry.snippet_frame(T_world_camera))
    camera = geometry.scale_camera(geometry.pinhole(K), 1.0 / stride)
    return Snippet("s", np.stack(images), camera.astype(np.float32),
                   (T_local_world @ T_world_camera).astype(np.float32),
                   np.array([0, 4]),
                   geometry.transform(T_local_world, centers_world).astype(np.float32),
                   np.array([[0.5, 0.8, 0.6], [1.0, 1.3, 0.3]], np.float32),
                   (T_local_world[:3, :3] @ R_world_object).astype(np.float32))


def test_a_mirrored_snippet_is_the_snippet_cut_from_the_mirrored_world():
    """parq_train.mirror works in the local frame; parq_runtime.mirror reflects the world
    (poses, intrinsics, images).  Cutting the snippet out of the reflected world, with its
    boxes reflected as parq_runtime.mirror reflects boxes, must give the same snippet."""
    rng = np.random.default_rng(3)
    w, h, stride = 160, 120, 4
    T_world_camera = np.stack([yaw_pitch_pose(0.7 + 0.1 * i, 0.3, [1.0 + 0.1 * i, 2.0, 1.5])
                               for i in range(3)])
    K = np.array([[[156.0, 0, 81.3], [0, 155.0, 58.9], [0, 0, 1]]] * 3)
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(3)]
    centers_world = np.array([[2.5, 3.0, 0.4], [1.0, 4.0, 0.9]])
    R_world_object = np.stack([_yaw(a) for a in (0.4, -2.0)])
    plain = snippet_of(images, K, T_world_camera, centers_world, R_world_object, stride)

    M = world_reflection()
    images_m, K_m, T_m = mirror_snippet(images, K, T_world_camera)
    expected = snippet_of(images_m, K_m, T_m, centers_world @ M.T,
                          M @ R_world_object @ F_FLIP, stride)
    got = mirror.mirrored(plain, stride)

    np.testing.assert_array_equal(got.images, expected.images)
    for name in ("camera", "T_local_camera", "centers", "rotations"):
        np.testing.assert_allclose(getattr(got, name), getattr(expected, name), atol=1e-5,
                                   err_msg=name)
    np.testing.assert_array_equal(got.sizes, plain.sizes)
    np.testing.assert_array_equal(got.labels, plain.labels)
    # proper rotations, and the object's up and front (object y and +z) stay up and front
    assert np.allclose(np.linalg.det(got.rotations), 1.0, atol=1e-5)
    assert np.allclose(np.linalg.det(got.T_local_camera[:, :3, :3]), 1.0, atol=1e-5)
    np.testing.assert_allclose(got.rotations[:, :, 1:], plain.rotations[:, :, 1:] *
                               np.array([-1.0, 1.0, 1.0])[None, :, None], atol=1e-6)
    # mirroring twice gives the snippet back
    twice = mirror.mirrored(got, stride)
    for name in ("images", "camera", "T_local_camera", "centers", "rotations"):
        np.testing.assert_allclose(getattr(twice, name), getattr(plain, name), atol=1e-6)


def _yaw(angle):
    """R_world_object of an upright object (object y = world z) turned by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    x = np.array([c, s, 0.0])
    y = np.array([0.0, 0.0, 1.0])
    return np.stack([x, y, np.cross(x, y)], -1)


def test_a_target_projects_to_the_mirrored_pixel():
    """In the mirrored snippet a target's center lands at feature pixel (w - 1 - u, v)."""
    config = tiny_config(num_queries=16)
    plain = tiny_snippets(config)[0]
    stride = config.feature_stride
    got = mirror.mirrored(plain, stride)
    width = plain.images.shape[2] / stride

    def pixels(s):
        T_camera_local = geometry.invert(s.T_local_camera.astype(np.float64))
        points = np.einsum("nij,mj->nmi", T_camera_local[:, :3, :3], s.centers) \
            + T_camera_local[:, None, :3, 3]
        u = points[..., 0] / points[..., 2] * s.camera[:, None, 0] + s.camera[:, None, 2]
        v = points[..., 1] / points[..., 2] * s.camera[:, None, 1] + s.camera[:, None, 3]
        return u, v

    u, v = pixels(plain)
    u_m, v_m = pixels(got)
    np.testing.assert_allclose(u_m, width - 1 - u, atol=1e-4)
    np.testing.assert_allclose(v_m, v, atol=1e-4)


def test_mirror_training_changes_the_weights_and_repeats_for_a_seed():
    """--mirror changes the weights (some batches are mirrored) and gives the same weights
    for the same seed, as rebuilding a model from its command needs."""
    config = tiny_config(num_queries=16)
    snippets = tiny_snippets(config)

    def weights(**kwargs):
        model, _ = train.train(config, snippets, steps=4, seed=0, folds_of_class=[1] * 9,
                               batch_size=2, iterations=2, lr=2e-3, log=lambda *_: None,
                               **kwargs)
        return model.state_dict()

    plain, a, b = weights(), weights(mirror=True), weights(mirror=True)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], plain[k]) for k in a)
