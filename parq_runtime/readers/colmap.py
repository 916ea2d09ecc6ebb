"""COLMAP text model: ``cameras.txt`` + ``images.txt`` in the folder, in ``sparse/0/`` or in
``sparse/``; the images in ``images/`` (or beside the model files).

    cameras.txt   CAMERA_ID MODEL WIDTH HEIGHT PARAMS...
    images.txt    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME
                  POINTS2D (X Y POINT3D_ID ...; may be empty; ignored)

Conventions, as documented by COLMAP (colmap.github.io, "Output Format" and "Camera Models",
and the database format's note on image coordinates) and used by nerfstudio's converter
(process_data/colmap_utils.py):

* the quaternion (QW QX QY QZ, Hamilton, scalar first) and T map **world to camera**
  (x_cam = R x_world + t); the camera centre is -R^T t.  The pose used here is the inverse;
* camera axes are OpenCV's (x right, y down, z forward);
* image coordinates put the upper-left image *corner* at (0, 0), so the centre of the first
  pixel is (0.5, 0.5); the runtime puts pixel centres at integers, so cx, cy are moved by -0.5;
* camera models: SIMPLE_PINHOLE (f cx cy) and PINHOLE (fx fy cx cy) are used directly;
  SIMPLE_RADIAL (f cx cy k), RADIAL (f cx cy k1 k2), OPENCV (fx fy cx cy k1 k2 p1 p2),
  FULL_OPENCV (fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6) and OPENCV_FISHEYE (fx fy cx cy k1 k2 k3 k4)
  are undistorted with OpenCV, whose models these are, to a pinhole with the same K before
  detection; other models (FOV, the *_FISHEYE variants, ...) are refused: run COLMAP's
  image_undistorter first.  WIDTH HEIGHT state the image size; an image of another size is an
  error;
* binary models (cameras.bin, images.bin) are refused with the command that converts them
  (``colmap model_converter --output_type TXT``);
* the world has no gravity and no scale: ``up`` is estimated from the cameras
  (``--up auto``, see parq_runtime.gravity), and the model must be metric for PARQ's boxes to
  mean anything (COLMAP's scale is arbitrary unless the model was aligned, e.g. with
  ``colmap model_aligner``).

Frames are sorted by image name (natural order: frame2 before frame10), the video's order when
frames are named by number.  Images in the images folder that the model does not list (not
registered) are counted in ``Capture.notes``.
"""
from __future__ import annotations

import pathlib

import numpy as np

from .. import geometry
from ..errors import ParqError
from . import (Capture, Frame, image_size, natural_key, parse_floats, pinhole_matrix,
               unique_names)
from .undistort import Undistorter

UP = None        # no gravity: estimated
# model: (parameter count, how to build (fx, fy, cx, cy, coefficients, kind))
MODELS = {
    "SIMPLE_PINHOLE": (3, lambda p: (p[0], p[0], p[1], p[2], (), "opencv")),
    "PINHOLE": (4, lambda p: (p[0], p[1], p[2], p[3], (), "opencv")),
    "SIMPLE_RADIAL": (4, lambda p: (p[0], p[0], p[1], p[2], (p[3], 0, 0, 0), "opencv")),
    "RADIAL": (5, lambda p: (p[0], p[0], p[1], p[2], (p[3], p[4], 0, 0), "opencv")),
    "OPENCV": (8, lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:8]), "opencv")),
    "FULL_OPENCV": (12, lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:12]), "opencv")),
    "OPENCV_FISHEYE": (8, lambda p: (p[0], p[1], p[2], p[3], tuple(p[4:8]), "fisheye")),
}
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


def _model_dir(path: pathlib.Path, suffix: str) -> pathlib.Path | None:
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if (folder / f"cameras{suffix}").is_file() and (folder / f"images{suffix}").is_file():
            return folder
    return None


def looks_like(path: pathlib.Path) -> bool:
    return _model_dir(path, ".txt") is not None or _model_dir(path, ".bin") is not None


def _lines(path: pathlib.Path, what: str):
    """(line number, text) of a text file, streamed; ParqError if unreadable."""
    try:
        with open(path, encoding="utf-8") as f:
            for n, line in enumerate(f, 1):
                yield n, line.rstrip("\r\n")
    except FileNotFoundError:
        raise ParqError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ParqError(f"{path}: {what} unreadable ({e})") from None


def _int(token: str, where: str, name: str) -> int:
    try:
        return int(token)
    except ValueError:
        raise ParqError(f"{where}: {name} {token[:20]!r} is not an integer") from None


def read_cameras(path: pathlib.Path) -> dict:
    """{camera id: (K (3, 3) in the runtime's pixel convention, (w, h), Undistorter or None)}."""
    cameras = {}
    for n, line in _lines(path, "cameras"):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{path}:{n}"
        if len(tokens) < 4:
            raise ParqError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        cid = _int(tokens[0], where, "CAMERA_ID")
        model = tokens[1].upper()
        if model not in MODELS:
            raise ParqError(f"{where}: camera model {tokens[1]} is not supported (supported: "
                            f"{', '.join(MODELS)}); undistort the images with COLMAP's "
                            "image_undistorter first")
        w, h = parse_floats(tokens[2:4], where, "WIDTH HEIGHT")
        size = image_size(w, h, where)
        count, build = MODELS[model]
        if len(tokens) - 4 != count:
            raise ParqError(f"{where}: {model} has {count} parameters, found {len(tokens) - 4}")
        params = parse_floats(tokens[4:], where, "camera parameters")
        if not np.all(np.isfinite(params)):
            raise ParqError(f"{where}: camera parameters hold NaN or infinite values")
        fx, fy, cx, cy, coefficients, kind = build(params)
        # COLMAP: first pixel centre at (0.5, 0.5); the runtime: at (0, 0)
        K = pinhole_matrix(fx, fy, cx - 0.5, cy - 0.5, where)
        if not (0 < K[0, 2] < size[0] and 0 < K[1, 2] < size[1]):
            raise ParqError(f"{where}: principal point ({cx:g}, {cy:g}) lies outside the "
                            f"stated {size[0]}x{size[1]} image")
        undistort = None
        if kind == "fisheye" or any(coefficients):
            undistort = Undistorter(K, coefficients, size, kind, where)
        if cid in cameras:
            raise ParqError(f"{where}: camera {cid} is defined twice")
        cameras[cid] = (K, size, undistort)
    if not cameras:
        raise ParqError(f"{path}: no cameras")
    return cameras


def quaternion_matrix(q: np.ndarray, where: str) -> np.ndarray:
    """Rotation of a Hamilton quaternion (w, x, y, z); ParqError unless it is a unit one
    (to 1e-3, then normalised)."""
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or abs(norm - 1.0) > 1e-3:
        raise ParqError(f"{where}: quaternion {np.round(q, 6).tolist()} is not a unit "
                        f"quaternion (norm {norm:.6g}); the pose is not a rotation")
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _image_line(tokens) -> bool:
    """An image line: exactly 10 tokens, integer ids, 7 numbers.  A POINTS2D line has 3k tokens,
    never 10, so the two cannot be confused even when the POINTS2D lines are left out."""
    if len(tokens) != 10:
        return False
    try:
        int(tokens[0]), int(tokens[8])
        [float(t) for t in tokens[1:8]]
    except ValueError:
        return False
    return True


def read_images(path: pathlib.Path) -> list:
    """[(name, T_world_camera (4, 4), camera id, where)] in file order."""
    images, expect_points = [], False
    for n, line in _lines(path, "images"):
        if line.lstrip().startswith("#"):
            continue
        tokens = line.split()
        where = f"{path}:{n}"
        if _image_line(tokens):
            values = parse_floats(tokens[1:8], where, "pose")
            if not np.all(np.isfinite(values)):
                raise ParqError(f"{where}: pose holds NaN or infinite values")
            T_camera_world = np.eye(4)
            T_camera_world[:3, :3] = quaternion_matrix(values[:4], where)
            T_camera_world[:3, 3] = values[4:7]
            T = geometry.invert(T_camera_world)
            geometry.check_rigid(T, where)
            images.append((tokens[9], T, int(tokens[8]), where))
            expect_points = True
        elif expect_points:
            expect_points = False             # the POINTS2D line of the image above
            if len(tokens) % 3:
                raise ParqError(f"{where}: neither an image line (IMAGE_ID QW QX QY QZ TX TY "
                                "TZ CAMERA_ID NAME) nor a POINTS2D line (X Y POINT3D_ID ...)")
        elif tokens:
            raise ParqError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, "
                            f"found {len(tokens)} fields")
    return images


def read(path: pathlib.Path) -> Capture:
    model = _model_dir(path, ".txt")
    if model is None:
        binary = _model_dir(path, ".bin")
        if binary is not None:
            raise ParqError(f"{binary}: a binary COLMAP model; convert it to text with "
                            f"`colmap model_converter --input_path {binary} --output_path "
                            f"{binary} --output_type TXT`")
        raise ParqError(f"{path}: COLMAP layout needs cameras.txt and images.txt (here, in "
                        "sparse/0/ or in sparse/)")
    cameras = read_cameras(model / "cameras.txt")
    entries = read_images(model / "images.txt")
    if not entries:
        raise ParqError(f"{model / 'images.txt'}: no registered images")
    image_dir = path / "images" if (path / "images").is_dir() else path
    frames, sources = [], {cid: f"{model / 'cameras.txt'} camera {cid}" for cid in cameras}
    for name, T, cid, where in sorted(entries, key=lambda e: natural_key(e[0])):
        if cid not in cameras:
            raise ParqError(f"{where}: image {name} uses camera {cid}, which cameras.txt does "
                            "not define")
        image = image_dir / name
        if not image.is_file():
            raise ParqError(f"{image}: image not found (listed in {model / 'images.txt'})")
        K, size, undistort = cameras[cid]
        frames.append(Frame(name, image, T, K.copy(), size=size,
                            source=sources[cid],
                            undistort=undistort))
    unique_names(frames, model / "images.txt")
    capture = Capture(path, "colmap", frames, UP)
    listed = {f.name for f in frames}
    if image_dir != path and all("/" not in n for n in listed):
        try:
            extra = sum(1 for p in image_dir.iterdir()
                        if p.suffix.lower() in IMAGE_SUFFIXES and p.name not in listed)
        except OSError:
            extra = 0
        if extra:
            capture.notes.append(f"{extra} image(s) in {image_dir.name}/ are not in the model "
                                 "(not registered) and are not used")
    return capture
