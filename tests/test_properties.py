"""Property-based tests: random and malformed input to the readers and the geometry either
succeeds with finite, rigid output or raises ParqError; never another exception.

Example counts are kept small (the suite stays fast); each example writes its capture into a
fresh temporary folder.
"""
from __future__ import annotations

import io
import json
import pathlib
import pickle
import tempfile

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from parq_runtime import geometry, gravity, keyframes, visualize
from parq_runtime.errors import ParqError
from parq_runtime.readers import open_capture

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])

_buf = io.BytesIO()
Image.fromarray(np.full((24, 32, 3), 128, np.uint8)).save(_buf, "PNG")
PNG = _buf.getvalue()          # 32 x 24

numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-10**6, 10**6),
    st.sampled_from([0.0, 1.0, -1.0, 0.5, 1e-12, 1e300, float("nan"), float("inf")]))
tokens = st.one_of(numbers.map(repr), st.sampled_from(["", "x", "nan", "-inf", "1e999", "0x10",
                                                       "1,2", "#", "PINHOLE", "a.png"]),
                   st.text(max_size=6))
lines = st.lists(tokens, max_size=12).map(" ".join)
texts = st.one_of(st.lists(lines, max_size=6).map("\n".join), st.text(max_size=200),
                  st.binary(max_size=64).map(lambda b: b.decode("latin1")))


rigid = st.tuples(st.floats(-np.pi, np.pi), st.floats(-1.4, 1.4), st.floats(-np.pi, np.pi),
                  st.lists(st.floats(-100, 100), min_size=3, max_size=3)).map(
    lambda a: geometry.camera_pose(a[3], a[0], a[1], a[2]))
pinhole = st.tuples(st.floats(0.5, 200), st.floats(0.5, 200), st.floats(-5, 40),
                    st.floats(-5, 30)).map(
    lambda v: np.array([[v[0], 0, v[2]], [0, v[1], v[3]], [0, 0, 1]]))


def matrix_text(m) -> st.SearchStrategy:
    return st.sampled_from(["{:.17g}", "{!r}", "{:.3f}", "{:e}"]).map(
        lambda fmt: "\n".join(" ".join(fmt.format(float(v)) for v in row) for row in m))


def unit_quaternion_or_not():
    return st.lists(st.floats(-1.5, 1.5), min_size=4, max_size=4)


def rigid_ok(T) -> bool:
    geometry.check_rigid(T, "test")
    return True


def check_capture(folder: pathlib.Path, fmt: str, up="+z", load=True):
    """open_capture either raises ParqError or gives finite rigid poses, positive focal
    lengths and a unit up axis; loading an image either works or raises ParqError."""
    try:
        capture = open_capture(folder, fmt, up)
    except ParqError:
        return None
    assert capture.frames
    for frame in capture.frames:
        assert frame.cam_to_world.shape == (4, 4) and rigid_ok(frame.cam_to_world)
        assert np.all(np.isfinite(frame.intrinsics))
        assert frame.intrinsics[0, 0] > 0 and frame.intrinsics[1, 1] > 0
    assert np.isclose(np.linalg.norm(capture.up), 1.0)
    if load:
        for frame in capture.frames[:2]:
            try:
                image = frame.load_image()
            except ParqError:
                continue
            assert image.dtype == np.uint8 and image.ndim == 3
    return capture


# ----------------------------------------------------------------------------- ScanNet

@SETTINGS
@given(pose=st.one_of(texts, st.lists(numbers, max_size=20).map(
           lambda v: " ".join(map(repr, v)))),
       intrinsic=st.one_of(texts, st.lists(numbers, min_size=9, max_size=16).map(
           lambda v: " ".join(map(repr, v)))),
       good_pose=rigid.flatmap(matrix_text), good_K=pinhole.flatmap(matrix_text))
def test_scannet_pose_and_intrinsics_text(pose, intrinsic, good_pose, good_K):
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        for sub in ("color", "pose", "intrinsic"):
            (f / sub).mkdir()
        (f / "color" / "0.png").write_bytes(PNG)
        (f / "color" / "1.png").write_bytes(PNG)
        (f / "pose" / "0.txt").write_text(" ".join(map(str, np.eye(4).ravel())))
        for P, K in ((pose, intrinsic), (good_pose, intrinsic), (pose, good_K),
                     (good_pose, good_K)):
            (f / "pose" / "1.txt").write_text(P)
            (f / "intrinsic" / "intrinsic_color.txt").write_text(K)
            check_capture(f, "scannet")


# ----------------------------------------------------------------------------- ARKitScenes

@SETTINGS
@given(traj=st.one_of(texts, st.lists(st.lists(numbers, min_size=7, max_size=7), max_size=4)
                      .map(lambda rows: "\n".join(" ".join(map(repr, r)) for r in rows))),
       pincam=st.one_of(texts, st.lists(numbers, min_size=6, max_size=6).map(
           lambda v: " ".join(map(repr, v)))))
def test_arkit_traj_and_pincam_text(traj, pincam):
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        (f / "lowres_wide").mkdir()
        (f / "lowres_wide_intrinsics").mkdir()
        (f / "lowres_wide" / "7_0.000.png").write_bytes(PNG)
        (f / "lowres_wide_intrinsics" / "7_0.000.pincam").write_text(pincam)
        (f / "lowres_wide.traj").write_text(traj)
        check_capture(f, "arkitscenes")


@SETTINGS
@given(rot=st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3),
       t=st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))
def test_arkit_any_axis_angle_is_rigid(rot, t):
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        (f / "lowres_wide").mkdir()
        (f / "lowres_wide_intrinsics").mkdir()
        (f / "lowres_wide" / "7_0.000.png").write_bytes(PNG)
        (f / "lowres_wide_intrinsics" / "7_0.000.pincam").write_text("32 24 30 30 15.5 11.5")
        (f / "lowres_wide.traj").write_text(" ".join(map(repr, [0.0, *rot, *t])))
        capture = check_capture(f, "arkitscenes", load=False)
        assert capture is not None


# ----------------------------------------------------------------------------- nerfstudio

json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9),
              st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=8)),
    lambda children: st.one_of(st.lists(children, max_size=5),
                               st.dictionaries(st.text(max_size=8), children, max_size=5)),
    max_leaves=20)
matrices = st.one_of(
    json_values,
    st.lists(st.lists(st.floats(-10, 10), min_size=4, max_size=4), min_size=3, max_size=4),
    st.just(np.eye(4).tolist()))
intrinsic_values = st.one_of(json_values, st.floats(-100, 100), st.integers(-5, 200))


@SETTINGS
@given(top=st.dictionaries(st.sampled_from(["fl_x", "fl_y", "cx", "cy", "w", "h",
                                            "camera_angle_x", "camera_model", "k1", "k4",
                                            "p1"]), intrinsic_values, max_size=6),
       frame=st.dictionaries(st.sampled_from(["file_path", "transform_matrix", "fl_x", "w",
                                              "h", "cx"]), intrinsic_values, max_size=4),
       matrix=matrices, path=st.sampled_from(["a.png", "./a", "b.png", "", "/nonexistent"]),
       junk=json_values)
def test_nerfstudio_transforms(top, frame, matrix, path, junk):
    gl = np.eye(4).tolist() if not isinstance(matrix, list) else matrix
    metas = [dict(top, frames=[dict(frame, file_path=path, transform_matrix=matrix)]),
             dict(top, frames=[frame]), junk,
             dict(top, fl_x=30.0, frames=[{"file_path": "a.png", "transform_matrix": gl}]),
             {"fl_x": 30, "cx": 16, "cy": 12, **{k: v for k, v in top.items() if k in "wh"},
              "frames": [{"file_path": "a.png", "transform_matrix": gl}]}]
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        (f / "a.png").write_bytes(PNG)
        for meta in metas:
            (f / "transforms.json").write_text(json.dumps(meta))
            check_capture(f, "nerfstudio")


# ----------------------------------------------------------------------------- COLMAP

camera_lines = st.one_of(
    lines,
    st.tuples(st.sampled_from(["1", "2", "x"]),
              st.sampled_from(["PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV",
                               "FULL_OPENCV", "OPENCV_FISHEYE", "FOV", "pinhole"]),
              st.sampled_from(["32", "24", "0", "-5", "32.5", "1e9"]),
              st.sampled_from(["24", "32", "0"]),
              st.lists(st.one_of(st.floats(-50, 50), numbers), max_size=12))
    .map(lambda c: " ".join([*c[:4], *map(repr, c[4])])))
image_lines = st.one_of(
    lines,
    st.tuples(st.integers(-2, 3), unit_quaternion_or_not(),
              st.lists(st.one_of(st.floats(-10, 10), numbers), min_size=3, max_size=3),
              st.sampled_from([1, 2]), st.sampled_from(["a.png", "b.png", "../a.png"]))
    .map(lambda c: " ".join([str(c[0]), *map(repr, c[1]), *map(repr, c[2]), str(c[3]),
                             c[4]])))


@SETTINGS
@given(cameras=st.lists(camera_lines, min_size=0, max_size=3),
       images=st.lists(st.one_of(image_lines, st.just(""),
                                 st.just("1.5 2.5 -1")), max_size=4),
       quaternion=unit_quaternion_or_not())
def test_colmap_text_model(cameras, images, quaternion):
    q = np.asarray(quaternion)
    good = (f"1 {' '.join(map(repr, (q / max(np.linalg.norm(q), 1e-9)).tolist()))} 0 0 1 1 "
            "a.png")
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        (f / "images").mkdir()
        (f / "images" / "a.png").write_bytes(PNG)
        for cams, imgs in ((cameras, images), (["1 PINHOLE 32 24 30 30 16 12"], images),
                           (cameras, [good, ""]), (["1 PINHOLE 32 24 30 30 16 12"], [good])):
            (f / "cameras.txt").write_text("\n".join(cams) + "\n")
            (f / "images.txt").write_text("\n".join(imgs) + "\n")
            check_capture(f, "colmap")


# ----------------------------------------------------------------------------- demo pickle

arrays = st.one_of(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=16, max_size=16)
    .map(lambda v: np.array(v).reshape(4, 4)),
    st.lists(st.floats(-100, 100), min_size=9, max_size=9).map(lambda v: np.array(v).reshape(3, 3)),
    st.just(np.eye(4)), st.just(np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])),
    st.just(np.zeros((2, 2), dtype=object)), st.just(np.arange(3)))
pickled = st.recursive(st.one_of(json_values, arrays),
                       lambda c: st.one_of(st.lists(c, max_size=4),
                                           st.dictionaries(st.sampled_from(
                                               ["image_ids", "extrinsics", "intrinsics",
                                                "scene"]), c, max_size=4)),
                       max_leaves=12)


@SETTINGS
@given(data=pickled, ids=st.lists(st.sampled_from(["00000", "00001", 0, None]), max_size=3),
       extr=st.lists(arrays, max_size=3), intr=st.lists(arrays, max_size=3),
       raw=st.binary(max_size=80), pose=st.one_of(rigid, arrays), K=st.one_of(pinhole, arrays),
       protocol=st.integers(0, 5))
def test_demo_pickle(data, ids, extr, intr, raw, pose, K, protocol):
    one = [{"image_ids": ["00000"], "extrinsics": [pose], "intrinsics": [K]}]
    with tempfile.TemporaryDirectory() as d:
        f = pathlib.Path(d)
        (f / "images").mkdir()
        (f / "images" / "00000.jpg").write_bytes(PNG)
        for blob in (pickle.dumps(data),
                     pickle.dumps([{"image_ids": ids, "extrinsics": extr, "intrinsics": intr}]),
                     raw, pickle.dumps(data)[:len(raw)], pickle.dumps(one, protocol=protocol)):
            (f / "fragments.pkl").write_bytes(blob)
            check_capture(f, "demo")


# ----------------------------------------------------------------------------- geometry

poses = st.one_of(
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=16,
             max_size=16).map(lambda v: np.array(v, dtype=np.float64).reshape(4, 4)),
    st.tuples(st.floats(-np.pi, np.pi), st.floats(-np.pi / 2, np.pi / 2),
              st.floats(-np.pi, np.pi),
              st.lists(st.floats(-100, 100), min_size=3, max_size=3))
    .map(lambda a: geometry.camera_pose(a[3], a[0], a[1], a[2])),
    st.sampled_from([np.eye(4), np.diag([1.0, -1, -1, 1]),
                     geometry.camera_pose([0, 0, 1], 0.3, np.pi / 2),      # straight down
                     geometry.camera_pose([0, 0, 1], 0.3, -np.pi / 2),     # straight up
                     np.zeros((4, 4))]))


@SETTINGS
@given(ps=st.lists(poses, min_size=1, max_size=6), up=st.sampled_from(list(gravity.AXES)))
def test_geometry_on_random_poses(ps, up):
    T = np.stack(ps)
    try:
        geometry.check_rigid(T, "poses")
    except ParqError:
        return
    for fn in (lambda: geometry.pseudo_cameras(T, gravity.AXES[up]),
               lambda: geometry.snippet_frame(T, gravity.AXES[up])[None]):
        try:
            out = fn()
        except ParqError:
            continue
        assert np.all(np.isfinite(out))
        geometry.check_rigid(out, "pseudo cameras")
    try:
        est = gravity.estimate(T)
    except ParqError:
        pass
    else:
        assert np.all(np.isfinite(est.up)) and np.isclose(np.linalg.norm(est.up), 1.0)
        assert all(isinstance(w, str) for w in est.warnings)
    keys = keyframes.select(list(T), 15.0, 0.1)
    assert keys and keys[0] == 0 and keys == sorted(set(keys))
    inverse = geometry.invert(T)
    np.testing.assert_allclose(inverse @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-6)


@SETTINGS
@given(pose=poses, center=st.lists(st.floats(-20, 20), min_size=3, max_size=3),
       size=st.lists(st.floats(0, 10), min_size=3, max_size=3),
       near=st.sampled_from([0.05, 1e-6, 1.0]))
def test_box_projection_is_finite_and_inside(pose, center, size, near):
    try:
        geometry.check_rigid(pose, "pose")
    except ParqError:
        return
    corners = geometry.box_corners(np.array(center), np.array(size), np.eye(3))
    K = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    for _, p, q in visualize.box_segments(corners, pose, K, (32, 24), near):
        for pt in (p, q):
            assert np.all(np.isfinite(pt))
            assert -1e-6 <= pt[0] <= 31 + 1e-6 and -1e-6 <= pt[1] <= 23 + 1e-6
