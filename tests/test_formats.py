"""One scene, five capture formats, the same boxes.

A generated scene (parq_synth when it is importable, else conftest.write_scannet) is read as a
ScanNet export and written again in every other layout, each in its own convention and with its
own world frame:

    arkitscenes  world-to-camera axis-angle traj, timestamps a little off the frames', z-up
                 world moved and turned about z (ARKitScenes' convention);
    arkit y-up   the same layout from an ARKit session's own y-up world, run with --up +y;
    nerfstudio   OpenGL camera axes, half-pixel principal point, y-up world (up estimated);
    colmap       world-to-camera quaternions, half-pixel principal point, the world of a COLMAP
                 reconstruction: up along -y, moved (up estimated);
    demo         fragments.pkl with PlanarRecon's 1.5 m shift, PNG frames.

parq-run (tiny model, --score-threshold 0 --all-regions) must find the same boxes in each, to
1 cm, once its world is mapped back to the ScanNet one.
"""
from __future__ import annotations

import json
import os
import pathlib
import pickle

import cv2
import numpy as np
import pytest

from parq_runtime import cli, geometry
from parq_runtime.readers import open_capture

from conftest import write_scannet


# ----------------------------------------------------------------------------- the source scene

def make_scene(folder: pathlib.Path, frames: int = 12, size=(96, 72)) -> pathlib.Path:
    """A ScanNet-layout scene: parq_synth's when it is importable, else noise images."""
    try:
        import parq_synth
    except ImportError:
        return write_scannet(folder, frames=frames, size=size)
    parq_synth.generate_scene(folder, seed=7, frames=frames, size=size)
    return folder


def rotation_about(axis, degrees: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.radians(degrees) * np.asarray(axis, dtype=np.float64))
    return R


def world_change(R=np.eye(3), t=(0, 0, 0)) -> np.ndarray:
    """W = T_new_old (4, 4)."""
    W = np.eye(4)
    W[:3, :3] = R
    W[:3, 3] = t
    return W


def _link(src: pathlib.Path, dst: pathlib.Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        dst.write_bytes(src.read_bytes())


def _frames(scene: pathlib.Path) -> list:
    return open_capture(scene, "scannet").frames


# ----------------------------------------------------------------------------- format writers

def write_arkit(scene, out: pathlib.Path, W=np.eye(4), video="41069042", time_offset=0.002):
    """ARKitScenes raw layout: traj lines are world-to-camera axis-angle + translation."""
    frames = _frames(scene)
    (out / "lowres_wide").mkdir(parents=True)
    (out / "lowres_wide_intrinsics").mkdir()
    lines = []
    for i, f in enumerate(frames):
        stamp = f"{6000.0 + 0.1 * i:.3f}"
        _link(f.image_path, out / "lowres_wide" / f"{video}_{stamp}.png")
        h, w = f.load_image().shape[:2]
        K = f.intrinsics
        (out / "lowres_wide_intrinsics" / f"{video}_{stamp}.pincam").write_text(
            " ".join(repr(float(v)) for v in (w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])) + "\n")
        T_camera_world = geometry.invert(W @ f.cam_to_world)
        r, _ = cv2.Rodrigues(T_camera_world[:3, :3])
        t = T_camera_world[:3, 3]
        lines.append(" ".join(repr(float(v)) for v in
                              [6000.0 + 0.1 * i + time_offset, *r.ravel(), *t]))
    # poses between the frames (the trajectory is denser than the frames) and unordered
    lines.insert(1, f"{6000.05:.3f} 0 0 0 0 0 0")
    (out / "lowres_wide.traj").write_text("\n".join(reversed(lines)) + "\n")
    return out


def write_nerfstudio(scene, out: pathlib.Path, W=np.eye(4)):
    """transforms.json: camera-to-world in OpenGL axes, principal point at half pixels."""
    frames = _frames(scene)
    entries = []
    for i, f in enumerate(frames):
        T = W @ f.cam_to_world
        T[:3, 1:3] *= -1
        _link(f.image_path, out / "images" / f"frame_{i + 1:05d}.png")
        entries.append({"file_path": f"images/frame_{i + 1:05d}.png",
                        "transform_matrix": T.tolist()})
    K = frames[0].intrinsics
    h, w = frames[0].load_image().shape[:2]
    entries.reverse()                       # the reader sorts by file name
    meta = {"camera_model": "OPENCV", "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5, "w": w, "h": h,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": entries}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return out


def quaternion(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2 * np.sqrt(tr + 1)
        q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q)
    return q if q[0] >= 0 else -q


def write_colmap(scene, out: pathlib.Path, W=np.eye(4), model="PINHOLE", sparse=True,
                 points=True):
    """COLMAP text model: world-to-camera quaternions, principal point at half pixels."""
    frames = _frames(scene)
    K = frames[0].intrinsics
    h, w = frames[0].load_image().shape[:2]
    folder = out / "sparse" / "0" if sparse else out
    folder.mkdir(parents=True, exist_ok=True)
    params = {"PINHOLE": [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5],
              "SIMPLE_PINHOLE": [K[0, 0], K[0, 2] + 0.5, K[1, 2] + 0.5]}[model]
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        f"1 {model} {w} {h} {' '.join(repr(float(p)) for p in params)}\n")
    lines = ["# Image list with two lines of data per image:"]
    for i, f in enumerate(reversed(frames)):
        n = len(frames) - 1 - i
        T_camera_world = geometry.invert(W @ f.cam_to_world)
        q = quaternion(T_camera_world[:3, :3])
        t = T_camera_world[:3, 3]
        name = f"img{n}.png"
        _link(f.image_path, out / "images" / name)
        lines.append(f"{n + 1} {' '.join(repr(float(v)) for v in (*q, *t))} 1 {name}")
        if points:
            lines.append("12.5 30.25 -1 40.0 8.5 17" if n % 2 else "")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    return out


def write_demo(scene, out: pathlib.Path, W=np.eye(4), fragment=4):
    """fragments.pkl (lists of numpy arrays, as PlanarRecon's tool pickles them)."""
    frames = _frames(scene)
    (out / "images").mkdir(parents=True)
    fragments = []
    for start in range(0, len(frames), fragment):
        part = frames[start:start + fragment]
        ids = [f"{start + i:05d}" for i in range(len(part))]
        for image_id, f in zip(ids, part):
            _link(f.image_path, out / "images" / f"{image_id}.png")
        fragments.append({"scene": out.name, "fragment_id": start // fragment,
                          "image_ids": ids,
                          "extrinsics": [W @ f.cam_to_world for f in part],
                          "intrinsics": [f.intrinsics.copy() for f in part]})
    with open(out / "fragments.pkl", "wb") as fh:
        pickle.dump(fragments, fh)
    return out


# ----------------------------------------------------------------------------- the comparison

def run(folder, model, *extra) -> dict:
    out = folder.parent / f"{folder.name}.json"
    code = cli.main([str(folder), "--model", str(model), "--score-threshold", "0",
                     "--all-regions", "--queries", "12", "-q", "-o", str(out), *map(str, extra)])
    assert code == 0
    return json.loads(out.read_text())


def boxes_back(data: dict, W: np.ndarray) -> tuple:
    """Corners of the snippets' and the scene's boxes mapped back through W^-1."""
    back = geometry.invert(W)
    snippets = [np.array([geometry.transform(back, np.array(b["corners"])) for b in s["boxes"]])
                for s in data["snippets"]]
    scene = np.array([geometry.transform(back, np.array(b["corners"]))
                      for b in data["scene"]["boxes"]])
    return snippets, scene, [b["class"] for b in data["scene"]["boxes"]]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return make_scene(tmp_path_factory.mktemp("formats") / "scannet")


@pytest.fixture(scope="module")
def reference(source, tiny_model):
    data = run(source, tiny_model)
    assert data["capture"]["format"] == "scannet"
    assert sum(len(s["boxes"]) for s in data["snippets"]) > 0
    return data


SHIFT = world_change(rotation_about([0, 0, 1], 30), [2.0, -1.0, 0.5])
Y_UP = world_change(rotation_about([1, 0, 0], -90), [0.3, 0.0, -0.2])     # z -> y
COLMAP_WORLD = world_change(rotation_about([1, 0, 0], 90), [-1.0, 0.25, 3.0])  # z -> -y
DEMO = world_change(t=[0, 0, 1.5])

CASES = {
    "arkitscenes": (write_arkit, SHIFT, "arkitscenes", ()),
    "arkit-y-up": (write_arkit, Y_UP, "arkitscenes", ("--up", "+y")),
    "nerfstudio": (write_nerfstudio, Y_UP, "nerfstudio", ()),
    "colmap": (write_colmap, COLMAP_WORLD, "colmap", ()),
    "demo": (write_demo, DEMO, "demo", ()),
}


@pytest.mark.parametrize("case", list(CASES))
def test_same_boxes_in_every_format(case, source, reference, tiny_model, tmp_path):
    writer, W, fmt, extra = CASES[case]
    folder = writer(source, tmp_path / case, W)
    data = run(folder, tiny_model, *extra)
    assert data["capture"]["format"] == fmt
    assert data["capture"]["frames"] == reference["capture"]["frames"]
    up = W[:3, :3] @ np.array([0.0, 0, 1])
    np.testing.assert_allclose(data["capture"]["up"], up, atol=1e-9)
    ref_snippets, ref_scene, ref_classes = boxes_back(reference, np.eye(4))
    snippets, scene, classes = boxes_back(data, W)
    assert [len(s) for s in snippets] == [len(s) for s in ref_snippets]
    for got, want in zip(snippets, ref_snippets):
        np.testing.assert_allclose(got, want, atol=0.01)
    assert classes == ref_classes
    np.testing.assert_allclose(scene, ref_scene, atol=0.01)


def test_detected_without_format_flag(source, tmp_path):
    for case, (writer, W, fmt, _) in CASES.items():
        folder = writer(source, tmp_path / case, W)
        assert open_capture(folder).format == fmt


def test_colmap_variants_read_the_same_poses(source, tmp_path):
    ref = np.stack([f.cam_to_world for f in _frames(source)])
    for name, kw in {"flat": dict(sparse=False), "nopoints": dict(points=False),
                     "simple": dict(model="SIMPLE_PINHOLE")}.items():
        if name == "simple" and not np.isclose(_frames(source)[0].intrinsics[0, 0],
                                               _frames(source)[0].intrinsics[1, 1]):
            continue
        capture = open_capture(write_colmap(source, tmp_path / name, **kw), up="+z")
        got = np.stack([f.cam_to_world for f in capture.frames])
        np.testing.assert_allclose(got, ref, atol=1e-9)
        np.testing.assert_allclose(capture.frames[0].intrinsics, _frames(source)[0].intrinsics,
                                   atol=1e-9)
