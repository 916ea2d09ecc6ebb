"""Every reader on hand-made captures whose geometry is known, and on broken ones."""
from __future__ import annotations

import json
import os
import pathlib
import pickle

import cv2
import numpy as np
import pytest
from PIL import Image

from parq_runtime import geometry
from parq_runtime.errors import ParqError
from parq_runtime.readers import FORMATS, detect_format, open_capture

from conftest import write_scannet

# A level camera in a z-up world looking along +y: x right = +x, y down = -z, z forward = +y.
LOOK_Y = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


def noise(path: pathlib.Path, size=(64, 48), seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)
    return path


def project_world(frame, point) -> np.ndarray:
    p = geometry.transform(geometry.invert(frame.cam_to_world), np.asarray(point, float))
    return (frame.intrinsics @ (p / p[2]))[:2]


# ----------------------------------------------------------------------------- ARKitScenes

def arkit_capture(folder, lines, frames=("100.000", "100.100"), size=(64, 48),
                  pincam="64 48 50 50 31.5 23.5"):
    for t in frames:
        noise(folder / "lowres_wide" / f"4242_{t}.png", size)
        (folder / "lowres_wide_intrinsics").mkdir(parents=True, exist_ok=True)
        (folder / "lowres_wide_intrinsics" / f"4242_{t}.pincam").write_text(pincam + "\n")
    (folder / "lowres_wide.traj").write_text("\n".join(lines) + "\n")
    return folder


def test_arkit_traj_is_world_to_camera_in_a_z_up_world(tmp_path):
    # R_camera_world = Rx(+90 deg): the camera looks along world +y, level; t = -R c
    c = np.array([1.0, 2.0, 1.5])
    t = -LOOK_Y.T @ c
    f = arkit_capture(tmp_path / "a", [
        # 3 ms off the frame's timestamp: matched
        f"100.003 {np.pi / 2!r} 0 0 {float(t[0])} {float(t[1])} {float(t[2])}",
        "100.1 0 0 0 0 0 0"])
    capture = open_capture(f)
    assert capture.format == "arkitscenes" and capture.up == (0, 0, 1.0)
    first = capture.frames[0]
    np.testing.assert_allclose(first.cam_to_world[:3, :3], LOOK_Y, atol=1e-12)
    np.testing.assert_allclose(first.cam_to_world[:3, 3], c, atol=1e-12)
    # a point 2 m ahead of the camera lands on the principal point
    np.testing.assert_allclose(project_world(first, c + [0, 2, 0]), [31.5, 23.5], atol=1e-9)
    assert first.size == (64, 48) and first.name == "100.000"
    assert first.load_image().shape == (48, 64, 3)


def test_arkit_frames_without_a_pose_nearby_are_skipped(tmp_path):
    f = arkit_capture(tmp_path / "a", ["100.0 0 0 0 0 0 0", "100.5 0 0 0 0 0 0"])
    capture = open_capture(f)
    assert [fr.name for fr in capture.frames] == ["100.000"]
    assert any("no pose" in n for n in capture.notes)


def test_arkit_scene_folder_with_frames_subfolder(tmp_path):
    arkit_capture(tmp_path / "41069042" / "41069042_frames", ["100.0 0 0 0 0 0 0",
                                                           "100.1 0 0 0 0 0 0"])
    capture = open_capture(tmp_path / "41069042")
    assert capture.format == "arkitscenes" and len(capture.frames) == 2


@pytest.mark.parametrize("lines, pincam, needle", [
    (["100.0 0 0 0 0 0", "100.1 0 0 0 0 0 0"], None, "expected 7 numbers"),
    (["100.0 0 0 nan 0 0 0", "100.1 0 0 0 0 0 0"], None, "NaN"),
    (["100.0 0 0 0 0 x 0", "100.1 0 0 0 0 0 0"], None, "not a number"),
    (["200.0 0 0 0 0 0 0"], None, "no pose within"),
    ([], None, "holds no poses"),
    (["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"], "64 48 50 50 31.5", "expected 6 numbers"),
    (["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"], "64 48 -50 50 31.5 23.5", "positive"),
    (["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"], "64 48 50 50 90 23.5", "outside"),
    (["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"], "64.5 48 50 50 31.5 23.5", "whole number"),
])
def test_arkit_bad_files(tmp_path, lines, pincam, needle):
    kw = {} if pincam is None else {"pincam": pincam}
    f = arkit_capture(tmp_path / "a", lines, **kw)
    with pytest.raises(ParqError, match=needle):
        open_capture(f)


def test_arkit_missing_and_extra_intrinsics(tmp_path):
    lines = ["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"]
    f = arkit_capture(tmp_path / "a", lines)
    (f / "lowres_wide_intrinsics" / "4242_100.100.pincam").unlink()
    with pytest.raises(ParqError, match="no intrinsics for 4242_100.100.png"):
        open_capture(f)
    f = arkit_capture(tmp_path / "b", lines)
    (f / "lowres_wide_intrinsics" / "4242_107.000.pincam").write_text("64 48 50 50 31.5 23.5")
    with pytest.raises(ParqError, match="no image for 1 intrinsics"):
        open_capture(f)
    f = arkit_capture(tmp_path / "c", lines)
    noise(f / "lowres_wide" / "999_100.200.png")
    with pytest.raises(ParqError, match="2 videos"):
        open_capture(f)


def test_image_size_against_stated_size(tmp_path):
    # pincam says 64x48, the image is 96x72: an error naming the image, when it loads
    f = arkit_capture(tmp_path / "a", ["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"],
                      size=(96, 72))
    capture = open_capture(f)
    with pytest.raises(ParqError, match=r"4242_100.000.png: image is 96x72 but its "
                                        r"intrinsics .*pincam\) state 64x48"):
        capture.frames[0].load_image()


def test_frames_of_different_sizes(tmp_path):
    # per-frame intrinsics (ARKit): allowed
    f = arkit_capture(tmp_path / "a", ["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"])
    noise(f / "lowres_wide" / "4242_100.100.png", (96, 72))
    (f / "lowres_wide_intrinsics" / "4242_100.100.pincam").write_text("96 72 75 75 47.5 35.5")
    capture = open_capture(f)
    assert [fr.load_image().shape for fr in capture.frames] == [(48, 64, 3), (72, 96, 3)]
    # one shared K without a size (ScanNet): the second size is an error naming both files
    s = write_scannet(tmp_path / "s", frames=3, size=(96, 72))
    noise(s / "color" / "2.png", (64, 48))
    capture = open_capture(s)
    capture.frames[0].load_image()
    with pytest.raises(ParqError, match=r"2.png: image is 64x48 but 0.png is 96x72"):
        capture.frames[2].load_image()


# ----------------------------------------------------------------------------- demo pickle

def demo_capture(folder, fragments, images=("00000", "00001")):
    for i in images:
        noise(folder / "images" / f"{i}.jpg")
    with open(folder / "fragments.pkl", "wb") as fh:
        pickle.dump(fragments, fh)
    return folder


def demo_fragment(ids=("00000", "00001"), pose=None):
    T = np.eye(4)
    T[:3, :3] = LOOK_Y
    T[:3, 3] = [0.5, 0.0, 1.5 + 1.5]       # PlanarRecon adds 1.5 m to z
    K = np.array([[50.0, 0, 31.5], [0, 50, 23.5], [0, 0, 1]])
    return {"scene": "demo", "fragment_id": 0, "image_ids": list(ids),
            "extrinsics": [T if pose is None else pose] * len(ids),
            "intrinsics": [K] * len(ids)}


def test_demo_pickle_camera_to_world_z_up(tmp_path):
    f = demo_capture(tmp_path / "d", [demo_fragment(), demo_fragment(["00001"])])
    capture = open_capture(f)
    assert capture.format == "demo" and capture.up == (0, 0, 1.0)
    assert [fr.name for fr in capture.frames] == ["00000", "00001"]   # 00001 used once
    np.testing.assert_allclose(project_world(capture.frames[0], [0.5, 2.0, 3.0]),
                               [31.5, 23.5], atol=1e-9)
    assert capture.frames[0].load_image().shape == (48, 64, 3)


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_demo_pickle_every_protocol(tmp_path, protocol):
    f = demo_capture(tmp_path / "d", [])
    data = [demo_fragment()]
    data[0]["fragment_id"] = np.int64(0)
    data[0]["scale"] = np.float64(1.0)
    (f / "fragments.pkl").write_bytes(pickle.dumps(data, protocol=protocol))
    assert len(open_capture(f).frames) == 2


def test_demo_pickle_written_by_old_numpy(tmp_path):
    f = demo_capture(tmp_path / "d", [])
    data = pickle.dumps([demo_fragment()], protocol=2)
    # numpy < 2 spells the module numpy.core.multiarray
    old = data.replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")
    assert old != data
    (f / "fragments.pkl").write_bytes(old)
    assert len(open_capture(f).frames) == 2


class Exploit:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_demo_pickle_never_runs_code(tmp_path):
    marker = tmp_path / "pwned"
    f = demo_capture(tmp_path / "d", [dict(demo_fragment(), scene=Exploit(marker))])
    assert b"system" in (f / "fragments.pkl").read_bytes()
    with pytest.raises(ParqError, match=r"refuses to load (posix|os)\.system"):
        open_capture(f)
    assert not marker.exists()
    # nor anything else that is not data
    (f / "fragments.pkl").write_bytes(pickle.dumps([demo_fragment(), pathlib.Path("x")]))
    with pytest.raises(ParqError, match="refuses to load pathlib"):
        open_capture(f)


@pytest.mark.parametrize("data, needle", [
    ({"a": 1}, "expected a list"),
    ([{"image_ids": ["00000"], "extrinsics": [np.eye(4)]}], "lacks intrinsics"),
    ([dict(demo_fragment(), image_ids=["00000"])], "must match one to one"),
    ([dict(demo_fragment(), extrinsics=[np.eye(3)] * 2)], "4x4"),
    ([dict(demo_fragment(), extrinsics=[np.diag([2.0, 1, 1, 1])] * 2)], "not a rotation"),
    ([dict(demo_fragment(), intrinsics=[np.eye(3) * [1, 1, 2]] * 2)], "not pinhole"),
    ([demo_fragment(["00000", "00009"])], "00009.jpg: image not found"),
    ([demo_fragment(["../x", "00000"])], "plain names"),
])
def test_demo_pickle_bad_content(tmp_path, data, needle):
    f = demo_capture(tmp_path / "d", data)
    with pytest.raises(ParqError, match=needle):
        open_capture(f)


def test_demo_pickle_garbage(tmp_path):
    f = demo_capture(tmp_path / "d", [])
    good = pickle.dumps([demo_fragment()])
    for bad in (b"", b"not a pickle", good[:len(good) // 2], b"\x80\x05K" + b"(" * 5000):
        (f / "fragments.pkl").write_bytes(bad)
        with pytest.raises(ParqError, match="fragments.pkl"):
            open_capture(f)


# ----------------------------------------------------------------------------- nerfstudio

def transforms(folder, meta, images=(("a.png", (64, 48)),)):
    for name, size in images:
        noise(folder / name, size)
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_nerfstudio_opengl_axes_and_half_pixel(tmp_path):
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]            # OpenGL camera at (1, 2, 3) looking along world -z
    f = transforms(tmp_path / "n", {"fl_x": 50, "fl_y": 60, "cx": 32, "cy": 24, "w": 64,
                                    "h": 48, "frames": [{"file_path": "a.png",
                                                         "transform_matrix": T.tolist()}]})
    capture = open_capture(f)
    assert capture.format == "nerfstudio" and capture.up_source == "estimated"
    frame = capture.frames[0]
    np.testing.assert_allclose(frame.cam_to_world, [[1, 0, 0, 1], [0, -1, 0, 2],
                                                    [0, 0, -1, 3], [0, 0, 0, 1]])
    np.testing.assert_allclose(frame.intrinsics, [[50, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
    # a point 2 m along -z (in front) and 1 m along +x projects to the right of the centre
    np.testing.assert_allclose(project_world(frame, [2, 2, 1]), [31.5 + 25, 23.5])


def test_nerfstudio_camera_angle_and_per_frame_intrinsics(tmp_path):
    T = np.eye(4).tolist()
    f = transforms(tmp_path / "n", {
        "camera_angle_x": 2 * np.arctan(0.5),     # fx = w / 2 / 0.5 = w
        "frames": [{"file_path": "./b", "transform_matrix": T},
                   {"file_path": "a.png", "transform_matrix": T, "fl_x": 10.0, "cx": 20,
                    "cy": 10, "w": 64, "h": 48}]},
        images=(("a.png", (64, 48)), ("b.png", (80, 60))))
    capture = open_capture(f, up="+z")
    a, b = capture.frames                        # sorted by file name: "./b" after "a.png"
    assert (a.name, b.name) == ("a.png", "./b")
    np.testing.assert_allclose(a.intrinsics, [[10, 0, 19.5], [0, 10, 9.5], [0, 0, 1]])
    np.testing.assert_allclose(b.intrinsics, [[80, 0, 39.5], [0, 80, 29.5], [0, 0, 1]])
    assert b.load_image().shape == (60, 80, 3)


@pytest.mark.parametrize("meta, needle", [
    ([], "JSON object"),
    ({"fl_x": 50}, "no frames list"),
    ({"fl_x": 50, "frames": []}, "empty"),
    ({"fl_x": 50, "frames": [{"file_path": "a.png"}]}, "transform_matrix"),
    ({"fl_x": 50, "frames": [{"file_path": "zz.png", "transform_matrix": np.eye(4).tolist()}]},
     "zz.png: image not found"),
    ({"fl_x": 50, "frames": [{"file_path": "a.png", "transform_matrix": [[1, 0], [0, 1]]}]},
     "4x4"),
    ({"fl_x": 50, "frames": [{"file_path": "a.png",
                              "transform_matrix": np.diag([2.0, 2, 2, 1]).tolist()}]},
     "not a rotation"),
    ({"fl_x": "50", "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]},
     "fl_x must be a number"),
    ({"cx": 3, "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]},
     "no focal length"),
    ({"fl_x": 50, "w": 64, "frames": [{"file_path": "a.png",
                                       "transform_matrix": np.eye(4).tolist()}]}, "only one"),
    ({"fl_x": 50, "camera_model": "EQUIRECTANGULAR",
      "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]},
     "not supported"),
    ({"fl_x": 50, "k4": 0.1, "frames": [{"file_path": "a.png",
                                         "transform_matrix": np.eye(4).tolist()}]}, "k4"),
])
def test_nerfstudio_bad_files(tmp_path, meta, needle):
    f = transforms(tmp_path / "n", meta)
    with pytest.raises(ParqError, match=needle):
        open_capture(f, up="+z")
    (f / "transforms.json").write_text("{broken")
    with pytest.raises(ParqError, match="not valid JSON"):
        open_capture(f, up="+z")


def test_nerfstudio_stated_size_must_match(tmp_path):
    f = transforms(tmp_path / "n", {"fl_x": 50, "w": 80, "h": 60, "frames": [
        {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]})
    frame = open_capture(f, up="+z").frames[0]
    with pytest.raises(ParqError, match="a.png: image is 64x48 but its intrinsics"):
        frame.load_image()


# ----------------------------------------------------------------------------- COLMAP

def colmap_model(folder, cameras, images, files=(("a.png", (64, 48)),)):
    (folder / "sparse" / "0").mkdir(parents=True)
    (folder / "sparse" / "0" / "cameras.txt").write_text(cameras)
    (folder / "sparse" / "0" / "images.txt").write_text(images)
    for name, size in files:
        noise(folder / "images" / name, size)
    return folder


def test_colmap_world_to_camera_quaternion(tmp_path):
    # q = Rx(+90 deg) = (cos 45, sin 45, 0, 0): R_camera_world = LOOK_Y^T, camera at c
    c = np.array([1.0, 2.0, 1.5])
    t = -LOOK_Y.T @ c
    s = np.sqrt(0.5)
    f = colmap_model(tmp_path / "c", "# comment\n1 PINHOLE 64 48 50 50 32 24\n",
                     f"# images\n7 {float(s)} {float(s)} 0 0 "
                     f"{float(t[0])} {float(t[1])} {float(t[2])} 1 a.png\n\n")
    capture = open_capture(f, up="+z")
    frame = capture.frames[0]
    np.testing.assert_allclose(frame.cam_to_world[:3, :3], LOOK_Y, atol=1e-12)
    np.testing.assert_allclose(frame.cam_to_world[:3, 3], c, atol=1e-12)
    np.testing.assert_allclose(frame.intrinsics[:2, 2], [31.5, 23.5])   # half-pixel shift
    assert frame.size == (64, 48)
    assert open_capture(f).up_source == "estimated"


def _dot_image(size, centre) -> np.ndarray:
    """A black image with a small bright blob centred at the (sub-pixel) point."""
    w, h = size
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    blob = np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * 1.5 ** 2))
    return np.repeat((255 * blob).astype(np.uint8)[..., None], 3, -1)


def _centroid(image) -> np.ndarray:
    g = image[..., 0].astype(np.float64)
    g[g < 40] = 0
    v, u = np.indices(g.shape)
    return np.array([(u * g).sum() / g.sum(), (v * g).sum() / g.sum()])


@pytest.mark.parametrize("model, params, f, dist", [
    ("SIMPLE_RADIAL", "90 80.5 60.5 -0.25", (90, 90), (-0.25, 0, 0, 0)),
    ("OPENCV", "90 85 80.5 60.5 -0.3 0.08 0.002 -0.001", (90, 85), (-0.3, 0.08, 0.002, -0.001)),
])
def test_colmap_distortion_is_undistorted(tmp_path, model, params, f, dist):
    size = (160, 120)
    K = np.array([[f[0], 0, 80.0], [0, f[1], 60.0], [0, 0, 1]])   # c = (80.5, 60.5) - 0.5
    ideal = np.array([130.0, 25.0])                       # where the pinhole puts the point
    ray = np.linalg.solve(K, [*ideal, 1.0])
    seen, _ = cv2.projectPoints(ray[None], np.zeros(3), np.zeros(3), K, np.array(dist))
    seen = seen.ravel()
    assert np.linalg.norm(seen - ideal) > 5                 # distortion moves it visibly
    folder = colmap_model(tmp_path / "c", f"1 {model} 160 120 {params}\n",
                          "1 1 0 0 0 0 0 0 1 a.png\n", files=())
    (folder / "images").mkdir()
    Image.fromarray(_dot_image(size, seen)).save(folder / "images" / "a.png")
    frame = open_capture(folder, up="+z").frames[0]
    np.testing.assert_allclose(frame.intrinsics, K)
    np.testing.assert_allclose(_centroid(frame.load_image()), ideal, atol=0.3)


@pytest.mark.parametrize("cameras, images, needle", [
    ("1 FOV 64 48 50 32 24 0.1\n", "1 1 0 0 0 0 0 0 1 a.png\n", "FOV is not supported"),
    ("1 PINHOLE 64 48 50 50 32\n", "1 1 0 0 0 0 0 0 1 a.png\n", "4 parameters, found 3"),
    ("1 PINHOLE 64 x 50 50 32 24\n", "1 1 0 0 0 0 0 0 1 a.png\n", "not a number"),
    ("1 PINHOLE 64 48 50 50 80 24\n", "1 1 0 0 0 0 0 0 1 a.png\n", "outside"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 2 0 0 0 0 0 0 1 a.png\n", "not a unit quaternion"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 nan 0 0 0 0 0 0 1 a.png\n", "NaN"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 0 5 a.png\n", "camera 5"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 0 1 b.png\n", "b.png: image not found"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 1 a.png\n", "expected IMAGE_ID"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "", "no registered images"),
    ("", "1 1 0 0 0 0 0 0 1 a.png\n", "no cameras"),
    ("1 PINHOLE 64 48 50 50 32 24\n1 PINHOLE 64 48 50 50 32 24\n",
     "1 1 0 0 0 0 0 0 1 a.png\n", "defined twice"),
    ("1 PINHOLE 64 48 50 50 32 24\n",
     "1 1 0 0 0 0 0 0 1 a.png\n\n2 1 0 0 0 0 0 0 1 a.png\n", "listed twice"),
    ("1 PINHOLE 64 48 50 50 32 24\n", "1 1 0 0 0 0 0 0 1 a.png\n1 2 3 4\n", "POINTS2D"),
])
def test_colmap_bad_files(tmp_path, cameras, images, needle):
    f = colmap_model(tmp_path / "c", cameras, images)
    with pytest.raises(ParqError, match=needle):
        open_capture(f, up="+z")


def test_colmap_binary_model_and_size_mismatch(tmp_path):
    b = tmp_path / "bin" / "sparse" / "0"
    b.mkdir(parents=True)
    (b / "cameras.bin").write_bytes(b"\0")
    (b / "images.bin").write_bytes(b"\0")
    with pytest.raises(ParqError, match="model_converter"):
        open_capture(tmp_path / "bin")
    f = colmap_model(tmp_path / "c", "1 PINHOLE 96 72 50 50 32 24\n", "1 1 0 0 0 0 0 0 1 a.png\n")
    frame = open_capture(f, up="+z").frames[0]
    with pytest.raises(ParqError, match=r"a.png: image is 64x48 but its intrinsics .*state "
                                        r"96x72"):
        frame.load_image()


# ----------------------------------------------------------------------------- all formats

def test_format_detection_and_forcing(tmp_path):
    s = write_scannet(tmp_path / "s", frames=2)
    assert detect_format(s) == "scannet"
    with pytest.raises(ParqError, match="COLMAP layout needs"):
        open_capture(s, "colmap")
    with pytest.raises(ParqError, match="unknown format"):
        open_capture(s, "kitti")
    assert set(FORMATS) == {"scannet", "arkitscenes", "demo", "nerfstudio", "colmap"}
    # two layouts in one folder: the first in FORMATS order, and a note
    colmap_model(s, "1 PINHOLE 96 72 80 80 48 36\n", "1 1 0 0 0 0 0 0 1 a.png\n")
    capture = open_capture(s)
    assert capture.format == "scannet"
    assert any("also looks like colmap" in n for n in capture.notes)


def test_up_choices(tmp_path):
    s = write_scannet(tmp_path / "s", frames=6)
    assert open_capture(s).up == (0, 0, 1.0)
    capture = open_capture(s, up="-y")
    assert capture.up == (0, -1.0, 0) and capture.up_source == "option"
    assert any("is --up right" in w for w in capture.warnings)
    capture = open_capture(s, up="auto")
    assert capture.up == (0, 0, 1.0) and capture.up_source == "estimated"
    with pytest.raises(ParqError, match="up axis"):
        open_capture(s, up="down")


def test_readers_do_not_read_images(tmp_path, monkeypatch):
    """Opening a capture touches poses and intrinsics only (images load per snippet)."""
    import parq_runtime.readers as readers

    calls = []
    real = readers.load_rgb
    monkeypatch.setattr(readers, "load_rgb", lambda p: calls.append(p) or real(p))
    f = arkit_capture(tmp_path / "a", ["100.0 0 0 0 0 0 0", "100.1 0 0 0 0 0 0"])
    capture = open_capture(f)
    assert calls == []
    capture.frames[1].load_image()
    assert len(calls) == 1


# ----------------------------------------------------------------------------- gravity

def walk(n=60, seed=0, roll_deg=3.0, tilt_deg=(10, 30), yaw_span=2 * np.pi, W=np.eye(4)):
    """A hand-held walk in a z-up world (then moved by W): a loop, looking inwards, pitched
    down, with roll jitter."""
    rng = np.random.default_rng(seed)
    a = np.linspace(0, yaw_span, n)
    poses = []
    for i in range(n):
        pos = [2 * np.cos(a[i]), 1.5 * np.sin(a[i]), 1.5 + 0.05 * rng.standard_normal()]
        yaw = a[i] + np.pi + np.radians(10) * rng.standard_normal()
        tilt = np.radians(rng.uniform(*tilt_deg))
        roll = np.radians(roll_deg) * rng.standard_normal()
        poses.append(W @ geometry.camera_pose(pos, yaw, tilt, roll))
    return np.stack(poses)


def tilted_world(degrees, axis=(1.0, 2.0, 0.5)):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(np.radians(degrees) * axis)
    W = np.eye(4)
    W[:3, :3] = R
    W[:3, 3] = [3, -2, 1]
    return W


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("degrees", [0, 37, 90, 160])
def test_gravity_recovers_up_of_a_tilted_world(seed, degrees):
    from parq_runtime.gravity import angle_deg, estimate

    W = tilted_world(degrees)
    est = estimate(walk(seed=seed, W=W), snap_degrees=0)
    assert angle_deg(est.raw, W[:3, 2]) < 2.0
    assert est.warnings == []
    assert est.roll_rms_deg < 5 and 10 < est.tilt_mean_deg < 30


def test_gravity_is_exact_without_roll_and_snaps_to_axes():
    from parq_runtime.gravity import angle_deg, estimate

    W = tilted_world(23)
    est = estimate(walk(roll_deg=0, W=W))
    assert angle_deg(est.up, W[:3, 2]) < 1e-6 and est.snapped is None
    # an ARKit-like y-up world, a little roll: snapped exactly to +y
    est = estimate(walk(roll_deg=2, W=tilted_world(-90, axis=(1, 0, 0))))
    assert est.snapped == "+y" and est.snap_deg < 2
    np.testing.assert_array_equal(est.up, [0, 1, 0])


def test_gravity_warns_when_poor():
    from parq_runtime.gravity import estimate

    # never turning: the x axes are all parallel; up falls back to the mean camera up
    straight = np.stack([geometry.camera_pose([0.1 * i, 0, 1.5], 0.0, np.radians(20))
                         for i in range(20)])
    est = estimate(straight)
    assert est.degenerate and any("never turn" in w for w in est.warnings)
    assert np.isfinite(est.up).all() and abs(np.linalg.norm(est.up) - 1) < 1e-12
    # held in portrait: x axes vertical
    portrait = walk(roll_deg=0)
    portrait[:, :3, :2] = np.stack([portrait[:, :3, 1], -portrait[:, :3, 0]], -1)
    est = estimate(portrait)
    assert any("out of any plane" in w or "far from the horizon" in w for w in est.warnings)
    assert any("only 1 camera" in w for w in estimate(straight[:1]).warnings)


@pytest.mark.parametrize("side", [40, 50])   # above the limit (Pillow warns), above twice it
def test_an_image_above_the_decompression_bomb_limit_is_refused_by_name(tmp_path, monkeypatch,
                                                                        side):
    import warnings

    from parq_runtime import readers

    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1000)   # 40x40 and 50x50 stand for 10k x 10k
    path = tmp_path / "huge.png"
    Image.new("RGB", (side, side)).save(path)

    class Frame:
        image_path = path

    with warnings.catch_warnings():
        warnings.simplefilter("error")          # nothing may leak out as a warning either
        with pytest.raises(ParqError, match="huge.png: image is larger than 0 megapixels"):
            readers.check_headers([Frame()])
