"""The mirrored snippet is the same scene seen in a mirror: projections, poses and boxes agree,
and the demo model finds the same objects in it."""
from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from parq_runtime import Detector, geometry, mirror, model_card, readers, scene
from parq_runtime.boxes import Box

DEMO = pathlib.Path(__file__).resolve().parents[1] / "models" / "parq-demo"


def _camera_ring(up):
    """Three level-ish cameras in a world with ``up``, as (N, 4, 4), OpenCV axes."""
    poses = np.stack([geometry.camera_pose([0.3 * i, -1.0, 1.4], 0.4 + 0.2 * i, 0.25, 0.05)
                      for i in range(3)])
    if tuple(up) == geometry.UP_Z:
        return poses
    R_y_z = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])    # z-up world -> y-up world
    poses[:, :3, :3] = R_y_z @ poses[:, :3, :3]
    poses[:, :3, 3] = poses[:, :3, 3] @ R_y_z.T
    return poses


@pytest.mark.parametrize("up", [geometry.UP_Z, (0.0, 1.0, 0.0)])
def test_a_point_projects_to_the_flipped_pixel(up):
    W, H = 160, 120
    K = np.tile(np.array([[150.0, 0, 77.3], [0, 150.0, 61.0], [0, 0, 1]]), (3, 1, 1))
    T_world_camera = _camera_ring(up)
    images = [np.random.default_rng(i).integers(0, 255, (H, W, 3), dtype=np.uint8)
              for i in range(3)]
    flipped, K_m, T_m = mirror.mirror_snippet(images, K, T_world_camera, up)
    geometry.check_rigid(T_m, "mirrored pose")           # still rotations, not reflections
    M = mirror.world_reflection(up)
    np.testing.assert_allclose(M @ np.asarray(up), up, atol=1e-12)
    points_camera = np.array([[0.2, 0.1, 2.0], [-0.5, -0.2, 3.0], [0.1, 0.3, 1.5]])
    for i in range(3):
        cam = geometry.pinhole(K[i])
        cam_m = geometry.pinhole(K_m[i])
        points_world = geometry.transform(T_world_camera[i], points_camera)
        uv, valid = geometry.project(
            geometry.transform(geometry.invert(T_world_camera[i]), points_world), cam, (W, H))
        uv_m, valid_m = geometry.project(
            geometry.transform(geometry.invert(T_m[i]), points_world @ M.T), cam_m, (W, H))
        assert valid.all()
        np.testing.assert_array_equal(valid, valid_m)
        np.testing.assert_allclose(uv_m[:, 0], W - 1 - uv[:, 0], atol=1e-9)
        np.testing.assert_allclose(uv_m[:, 1], uv[:, 1], atol=1e-9)
        # and the pixel there is the one the original image has at (u, v)
        np.testing.assert_array_equal(flipped[i][17, W - 1 - 23], images[i][17, 23])


@pytest.mark.parametrize("up", [geometry.UP_Z, (0.0, 1.0, 0.0)])
def test_a_mirrored_box_comes_back_as_itself(up):
    M = mirror.world_reflection(up)
    R = geometry.camera_pose([0, 0, 0], 0.7)[:3, :3] if tuple(up) == geometry.UP_Z else \
        np.array([[np.cos(0.7), 0, np.sin(0.7)], [0, 1, 0], [-np.sin(0.7), 0, np.cos(0.7)]])
    center, size = np.array([1.0, 2.0, 0.5]), np.array([0.6, 0.9, 0.4])
    box = Box(center, size, R, float(geometry.yaw(R, up)), 0, "chair", 0.9,
              geometry.box_corners(center, size, R), viewpoint=np.array([0.1, 0.2, 1.4]))
    # the box as the network would predict it in the mirrored world: the same object, reflected
    R_m = M @ R @ mirror.F_FLIP
    seen = Box(M @ center, size, R_m, 0.0, 0, "chair", 0.9,
               geometry.box_corners(M @ center, size, R_m), viewpoint=M @ box.viewpoint)
    assert np.linalg.det(R_m) == pytest.approx(1.0)
    # its corners are the original's, reflected (as a set)
    np.testing.assert_allclose(np.sort(seen.corners @ M.T, axis=0), np.sort(box.corners, axis=0),
                               atol=1e-12)
    back = mirror.unmirror_box(seen, up)
    np.testing.assert_allclose(back.center, box.center, atol=1e-12)
    np.testing.assert_allclose(back.rotation, box.rotation, atol=1e-12)
    np.testing.assert_allclose(back.corners, box.corners, atol=1e-12)
    np.testing.assert_allclose(back.viewpoint, box.viewpoint, atol=1e-12)
    assert back.yaw == pytest.approx(box.yaw)


def test_the_demo_model_finds_the_same_objects_in_the_mirror():
    """Each detection has a mirrored one nearby once reflected back (the two differ by about
    the model's depth error, 0.2 m along the ray), and not before: the reflection matters."""
    detector = Detector(DEMO)
    capture = readers.open_capture(DEMO / "sample-scene")
    _, snippets = scene.plan(capture, scene.resolved(scene.RunSettings(), detector.card),
                             detector.card)
    back_dist, raw_dist = [], []
    for indices in snippets:
        frames = [capture.frames[i] for i in indices]
        images = [f.load_image() for f in frames]
        K = np.stack([f.intrinsics for f in frames])
        T = np.stack([f.cam_to_world for f in frames])
        found = detector.detect(images, K, T, up=capture.up).boxes
        # the partner may score a little lower: look for it among all but the weakest
        seen = detector.detect(*mirror.mirror_snippet(images, K, T, capture.up),
                               score_threshold=0.3, up=capture.up).boxes
        back = [mirror.unmirror_box(b, capture.up) for b in seen]
        for box in found:
            back_dist.append(min([np.linalg.norm(b.center - box.center) for b in back]
                                 + [np.inf]))
            raw_dist.append(min([np.linalg.norm(b.center - box.center) for b in seen]
                                + [np.inf]))
    back_dist, raw_dist = np.array(back_dist), np.array(raw_dist)
    assert len(back_dist) >= 10
    assert np.median(back_dist) < 0.3 and np.mean(back_dist < 0.6) >= 0.85, back_dist
    assert np.median(raw_dist) > 1.0, raw_dist


def test_parq_run_mirror_fuses_both_runs_and_counts_them_as_support(tmp_path):
    from parq_runtime import cli

    plain, mirrored = tmp_path / "plain.json", tmp_path / "mirror.json"
    sample = str(DEMO / "sample-scene")
    assert cli.main([sample, "-q", "--no-mirror", "-o", str(plain)]) == 0
    assert cli.main([sample, "-q", "--mirror", "-o", str(mirrored)]) == 0
    a, b = (json.loads(p.read_text()) for p in (plain, mirrored))
    # support counts runs: the demo card's (chosen with mirror runs) is the mirrored run's,
    # and a plain run, one run a snippet, asks half of it, rounded up
    card_support = model_card.load(DEMO).min_support
    assert a["settings"]["mirror"] is False and "mirrored_boxes" not in a["snippets"][0]
    assert b["settings"]["mirror"] is True
    assert b["settings"]["min_support"] == card_support
    assert a["settings"]["min_support"] == -(-card_support // 2)
    # the unmirrored runs are the plain run, box for box
    assert [s["boxes"] for s in b["snippets"]] == [s["boxes"] for s in a["snippets"]]
    assert sum(len(s["mirrored_boxes"]) for s in b["snippets"]) > 0
    supports = [box["support"] for box in b["scene"]["boxes"]]
    assert supports and min(supports) >= card_support
    assert max(supports) <= 2 * len(b["snippets"])
    assert max(supports) > max(box["support"] for box in a["scene"]["boxes"])
    # the demo card's run setting has mirror runs: no flag is --mirror
    default = tmp_path / "default.json"
    assert cli.main([sample, "-q", "-o", str(default)]) == 0
    d = json.loads(default.read_text())
    assert d["settings"] == b["settings"] and d["scene"]["boxes"] == b["scene"]["boxes"]
    # overlapping snippets (the feature cache) run mirrored too
    assert cli.main([sample, "-q", "--mirror", "--stride", "1", "--max-snippets", "4",
                     "--min-support", "1", "-o", str(mirrored)]) == 0
    c = json.loads(mirrored.read_text())
    assert c["settings"]["min_support"] == 1 and len(c["snippets"]) == 4
    assert all("mirrored_boxes" in s for s in c["snippets"])
