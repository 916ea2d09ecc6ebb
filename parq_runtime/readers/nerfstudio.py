"""nerfstudio / instant-ngp ``transforms.json``:

    {"camera_model": "OPENCV", "fl_x": .., "fl_y": .., "cx": .., "cy": .., "w": .., "h": ..,
     "k1": .., "k2": .., "k3": .., "k4": .., "p1": .., "p2": ..,      (all optional)
     "frames": [{"file_path": "images/frame_00001.png", "transform_matrix": 4x4, ...}, ...]}

Conventions, as documented by nerfstudio (docs.nerf.studio, "Data conventions") and read in its
code (nerfstudio/data/dataparsers/nerfstudio_dataparser.py, cameras/cameras.py,
cameras/camera_utils.py, process_data/colmap_utils.py and record3d_utils.py):

* ``transform_matrix`` is **camera-to-world** in **OpenGL camera axes** (x right, y up, z
  back, looking along -z); it becomes OpenCV's (x right, y down, z forward) by negating its
  y and z columns;
* intrinsics may sit at the top level or in each frame (a frame's value wins): ``fl_x``,
  ``fl_y`` (default fl_x), ``cx``, ``cy`` (default w/2, h/2), ``w``, ``h``; or, as in the
  Blender scenes and instant-ngp, ``camera_angle_x`` (and optionally ``camera_angle_y``): the
  horizontal field of view in radians, fx = w / 2 / tan(camera_angle_x / 2).  Without ``w h``
  the size is read from the first image's header;
* pixel coordinates: nerfstudio casts the ray of pixel (i, j) through (i + 0.5, j + 0.5), i.e.
  its cx, cy put pixel centres at half-integers; the runtime puts them at integers, so
  cx, cy are moved by -0.5;
* ``camera_model``: OPENCV (k1, k2, k3, p1, p2; nerfstudio's k4 has no OpenCV equivalent and
  is refused) or OPENCV_FISHEYE (k1..k4) are undistorted with OpenCV to a pinhole with the same
  K before detection; other models (EQUIRECTANGULAR, ...) are refused;
* ``file_path`` is relative to the json's folder; a path without a suffix (the Blender scenes'
  "./train/r_0") gets .png; frames are sorted by file name, as nerfstudio's parser does;
* the world: nerfstudio's docs say z up, and its COLMAP conversion permutes COLMAP's axes so
  that the first camera's -y becomes +z; Record3D and Polycam exports keep ARKit's y-up world;
  instant-ngp's colmap2nerf turns the mean camera up to +z; nerfstudio's own parser re-orients
  every scene from the cameras (orientation_method "up").  No convention holds, so ``up`` is
  estimated from the cameras by default (``--up auto``, snapped to a world axis when within
  5 degrees); give ``--up`` when it is known.  Scale: PARQ predicts metric boxes;
  ARKit-based exports are metric, COLMAP-based ones (and colmap2nerf's rescaled ones) are not.
"""
from __future__ import annotations

import json
import math
import os
import pathlib

import numpy as np
from PIL import Image

from .. import geometry
from ..errors import ParqError
from . import (Capture, Frame, SizeGroup, image_size, natural_key, pinhole_matrix,
               unique_names)
from .undistort import Undistorter

UP = None        # estimated (see the module docstring)
FILE = "transforms.json"
MODELS = {"OPENCV": "opencv", "OPENCV_FISHEYE": "fisheye", "PINHOLE": "opencv",
          "SIMPLE_PINHOLE": "opencv", "PERSPECTIVE": "opencv"}
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
                  "k1", "k2", "k3", "k4", "p1", "p2", "camera_model", "distortion_params")
MAX_BYTES = 256 << 20


def looks_like(path: pathlib.Path) -> bool:
    return (path / FILE).is_file()


def _number(value, where: str, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ParqError(f"{where}: {name} must be a number, got {json.dumps(value)[:40]}")
    value = float(value)
    if not math.isfinite(value):
        raise ParqError(f"{where}: {name} is not finite")
    return value


def _pose(value, where: str) -> np.ndarray:
    ok = isinstance(value, list) and len(value) in (3, 4) and all(
        isinstance(row, list) and len(row) == 4 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in row)
        for row in value)
    if not ok:
        raise ParqError(f"{where}: transform_matrix must be a 4x4 (or 3x4) list of numbers")
    T = np.eye(4)
    T[:len(value)] = np.array(value, dtype=np.float64)
    geometry.check_rigid(T, f"{where}: transform_matrix")
    T[:3, 1:3] *= -1.0                     # OpenGL camera axes -> OpenCV
    return T


def _image_path(folder: pathlib.Path, value, where: str) -> pathlib.Path:
    if not isinstance(value, str) or not value.strip():
        raise ParqError(f"{where}: file_path must be a non-empty string")
    p = pathlib.Path(value)
    p = p if p.is_absolute() else folder / p
    if p.is_file():
        return p
    if not p.suffix:
        for suffix in (".png", ".jpg", ".jpeg"):
            if p.with_name(p.name + suffix).is_file():
                return p.with_name(p.name + suffix)
    raise ParqError(f"{p}: image not found (listed in {FILE}, {where})")


def _header_size(path: pathlib.Path) -> tuple:
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise ParqError(f"{path}: image not found") from None
    except Exception as e:  # Pillow raises many types for a bad header
        raise ParqError(f"{path}: not a readable image ({e})") from None


class _Camera:
    """Intrinsics of one distinct parameter set (shared by the frames that use it)."""

    def __init__(self, params: dict, where: str, first_image: pathlib.Path):
        get = params.get
        self.where = where
        w, h = get("w"), get("h")
        if (w is None) != (h is None):
            raise ParqError(f"{where}: gives only one of w and h")
        self.stated = w is not None
        if self.stated:
            self.size = image_size(_number(w, where, "w"), _number(h, where, "h"), where)
        else:
            self.size = None
        fx = self._focal(params, "x", 0, first_image)
        if fx is None:
            raise ParqError(f"{where}: no focal length (fl_x or camera_angle_x)")
        fy = self._focal(params, "y", 1, first_image)
        if fy is None:
            fy = fx
        cx = (_number(get("cx"), where, "cx") if get("cx") is not None
              else self._need_size(first_image)[0] / 2)
        cy = (_number(get("cy"), where, "cy") if get("cy") is not None
              else self._need_size(first_image)[1] / 2)
        # nerfstudio: pixel centres at +0.5; the runtime: at integers
        self.K = pinhole_matrix(fx, fy, cx - 0.5, cy - 0.5, where)
        model = get("camera_model", "OPENCV")
        if not isinstance(model, str) or model.upper() not in MODELS:
            raise ParqError(f"{where}: camera_model {model!r} is not supported (use OPENCV or "
                            "OPENCV_FISHEYE)")
        kind = MODELS[model.upper()]
        if get("distortion_params") is not None:
            d = get("distortion_params")
            if not isinstance(d, list) or len(d) != 6:
                raise ParqError(f"{where}: distortion_params must be 6 numbers "
                                "(k1 k2 k3 k4 p1 p2)")
            k1, k2, k3, k4, p1, p2 = (_number(v, where, "distortion_params") for v in d)
        else:
            k1, k2, k3, k4, p1, p2 = (_number(get(k, 0.0), where, k)
                                      for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
        self.undistort = None
        if kind == "fisheye":
            coefficients = (k1, k2, k3, k4)
        else:
            if k4 != 0:
                raise ParqError(f"{where}: k4 = {k4:g} for a perspective camera (an r^8 term) "
                                "has no OpenCV equivalent")
            coefficients = (k1, k2, p1, p2, k3)
        if kind == "fisheye" or any(coefficients):
            size = self._need_size(first_image)
            self.undistort = Undistorter(self.K, coefficients, size, kind, where)

    def _focal(self, params: dict, axis: str, dim: int, first_image) -> float | None:
        """fl_<axis>, or from the field of view camera_angle_<axis> (radians) and the image's
        size along ``dim``: size / 2 / tan(angle / 2); None when neither is given."""
        focal, fov = params.get(f"fl_{axis}"), params.get(f"camera_angle_{axis}")
        if focal is not None:
            return _number(focal, self.where, f"fl_{axis}")
        if fov is None:
            return None
        angle = _number(fov, self.where, f"camera_angle_{axis}")
        if not 0 < angle < math.pi:
            raise ParqError(f"{self.where}: camera_angle_{axis} {angle:g} rad is not a field of "
                            "view between 0 and pi")
        return self._need_size(first_image)[dim] / 2 / math.tan(angle / 2)

    def _need_size(self, first_image: pathlib.Path) -> tuple:
        if self.size is None:
            self.size = _header_size(first_image)
        return self.size


def read(path: pathlib.Path) -> Capture:
    file = path / FILE
    try:
        if file.stat().st_size > MAX_BYTES:
            raise ParqError(f"{file}: too large for a transforms file")
        meta = json.loads(file.read_text())
    except FileNotFoundError:
        raise ParqError(f"{file}: not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ParqError(f"{file}: unreadable ({e})") from None
    except (json.JSONDecodeError, RecursionError) as e:
        raise ParqError(f"{file}: not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ParqError(f"{file}: expected a JSON object with a frames list")
    entries = meta.get("frames")
    if not isinstance(entries, list):
        raise ParqError(f"{file}: no frames list")
    if not entries:
        raise ParqError(f"{file}: the frames list is empty")
    top = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    items = []
    for n, entry in enumerate(entries):
        where = f"{file}: frame {n}"
        if not isinstance(entry, dict):
            raise ParqError(f"{where}: expected an object")
        if "file_path" not in entry or "transform_matrix" not in entry:
            raise ParqError(f"{where}: needs file_path and transform_matrix")
        image = _image_path(path, entry["file_path"], where)
        items.append((natural_key(os.path.normpath(str(entry["file_path"]))), n, entry, image))
    items.sort(key=lambda item: item[:2])
    cameras, frames, source = {}, [], str(file)
    for _, n, entry, image in items:
        where = f"{file}: frame {n}"
        own = {k: entry[k] for k in INTRINSIC_KEYS if k in entry}
        params = {**top, **own}
        key = json.dumps(params, sort_keys=True, default=str)
        if key not in cameras:
            camera = _Camera(params, where if own else str(file), image)
            group = None if camera.stated else SizeGroup(f"{file}, which states no w h")
            cameras[key] = (camera, group)
        camera, group = cameras[key]
        T = _pose(entry["transform_matrix"], where)
        frames.append(Frame(str(entry["file_path"]), image, T, camera.K.copy(),
                            size=camera.size if camera.stated else None,
                            source=source, undistort=camera.undistort, size_group=group))
    unique_names(frames, file)
    return Capture(path, "nerfstudio", frames, UP)
