"""The authors' demo layout: ``fragments.pkl`` + ``images/<id>.jpg``, as written by PlanarRecon's
(and NeuralRecon's, which it derives from) ``tools/process_arkit_data.py`` from an ARKit
recording made with ios_logger:

    fragments.pkl   a pickled list of dicts, one per fragment of keyframes:
                    {"scene": str, "fragment_id": int, "image_ids": [str, ...],
                     "extrinsics": [4x4 camera-to-world, ...], "intrinsics": [3x3, ...]}
    images/<id>.jpg the frames (ids are zero-padded frame numbers, "00042"); .jpeg and .png
                    are accepted too

Conventions, as verified in github.com/neu-vi/PlanarRecon (tools/process_arkit_data.py,
tools/kp_reproject.py, datasets/demo.py) and github.com/zju3dv/NeuralRecon (the same tools):

* extrinsics are **camera-to-world** with **OpenCV camera axes**: ``load_camera_pose`` turns
  ARKit's camera (x right, y up, z back) into OpenCV's by right-multiplying diag(1, -1, -1);
* the world is **z up**: the same function left-multiplies rotation and translation by a
  +90 degree rotation about x, which takes ARKit's y-up world to z up; the tool then adds
  1.5 m to every camera's z ("moving down the X-Y plane ... to meet the training settings in
  ScanNet").  Boxes therefore come out in that shifted z-up frame;
* intrinsics are the ARKit ones scaled to the 640x480 images (rows divided by 3), used with
  integer pixel coordinates, as stored.

Frames are the fragments' image ids in order; an id listed by two fragments is used once (its
two poses must agree).  The pickle is read with a restricted unpickler (:class:`SafeUnpickler`)
that can only rebuild numpy arrays, numpy scalars and plain containers: any other global in the
file (a function, a class) is refused with a ParqError naming it, so no code in the file runs.
"""
from __future__ import annotations

import importlib
import io
import pathlib
import pickle

import numpy as np

from .. import geometry
from ..errors import ParqError
from . import Capture, Frame, pinhole_matrix

UP = geometry.UP_Z
PICKLE = "fragments.pkl"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".JPG", ".PNG")
MAX_BYTES = 512 << 20


def _latin1_encode(text, encoding="latin1"):
    # Python 2-compatible pickles (protocol < 3) spell bytes as _codecs.encode(str, "latin1").
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError("_codecs.encode is allowed only for latin1 text")
    return text.encode("latin1")


def _numpy_global(modules, name):
    for module in modules:
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            continue
    raise pickle.UnpicklingError(f"this numpy has no {name}")


_MULTIARRAY = ("numpy._core.multiarray", "numpy.core.multiarray")
_NUMERIC = ("numpy._core.numeric", "numpy.core.numeric")
ALLOWED = {
    # numpy arrays: ndarray.__reduce__ (protocols 0-4) and __reduce_ex__(5)
    ("numpy.core.multiarray", "_reconstruct"): lambda: _numpy_global(_MULTIARRAY, "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"): lambda: _numpy_global(_MULTIARRAY, "_reconstruct"),
    ("numpy.core.numeric", "_frombuffer"): lambda: _numpy_global(_NUMERIC, "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"): lambda: _numpy_global(_NUMERIC, "_frombuffer"),
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy", "dtype"): lambda: np.dtype,
    # numpy scalars (np.float64(1.0) pickles as scalar(dtype, bytes))
    ("numpy.core.multiarray", "scalar"): lambda: _numpy_global(_MULTIARRAY, "scalar"),
    ("numpy._core.multiarray", "scalar"): lambda: _numpy_global(_MULTIARRAY, "scalar"),
    ("_codecs", "encode"): lambda: _latin1_encode,
    **{("builtins", n): (lambda n=n: getattr(__import__("builtins"), n))
       for n in ("list", "dict", "tuple", "set", "frozenset", "int", "float", "complex", "str",
                 "bytes", "bytearray", "bool")},
    **{("__builtin__", n): (lambda n=n: getattr(__import__("builtins"), n))
       for n in ("list", "dict", "tuple", "set", "frozenset", "int", "float", "complex", "str",
                 "bool")},
}


class SafeUnpickler(pickle.Unpickler):
    """An unpickler whose ``find_class`` (the only way a pickle reaches code) hands out only
    the globals in ALLOWED; anything else raises :class:`ParqError` naming it."""

    def __init__(self, file, where: str):
        super().__init__(file, encoding="latin1")
        self.where = where

    def find_class(self, module, name):
        factory = ALLOWED.get((module, name))
        if factory is None:
            raise ParqError(f"{self.where}: refuses to load {module}.{name} (the pickle may only "
                            "hold numpy arrays, numbers, strings, lists and dicts; it would run "
                            "code otherwise)")
        return factory()

    def persistent_load(self, pid):
        raise ParqError(f"{self.where}: holds a persistent reference; not a fragments file")


def safe_load(path) -> object:
    """Unpickle ``path`` with :class:`SafeUnpickler`; ParqError for anything that goes wrong."""
    path = pathlib.Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ParqError(f"{path}: not found") from None
    except OSError as e:
        raise ParqError(f"{path}: unreadable ({e})") from None
    if len(data) > MAX_BYTES:
        raise ParqError(f"{path}: {len(data) >> 20} MiB is too large for a fragments file")
    try:
        return SafeUnpickler(io.BytesIO(data), str(path)).load()
    except ParqError:
        raise
    except RecursionError:
        raise ParqError(f"{path}: not a readable pickle (nested too deeply)") from None
    except Exception as e:  # a malformed pickle can raise almost anything while it is decoded
        raise ParqError(f"{path}: not a readable pickle ({type(e).__name__}: "
                        f"{str(e)[:120]})") from None


def looks_like(path: pathlib.Path) -> bool:
    return (path / PICKLE).is_file()


def _matrices(value, shape, where: str, what: str) -> np.ndarray:
    """A list of matrices (or a stacked array) of ``shape`` as (n, *shape) float64."""
    try:
        if isinstance(value, np.ndarray):
            if value.dtype == object:
                raise ValueError("object array")
            items = list(value) if value.ndim == len(shape) + 1 else [value]
        elif isinstance(value, (list, tuple)):
            items = list(value)
        else:
            raise ValueError(f"a {type(value).__name__}")
        out = []
        for m in items:
            if isinstance(m, (bool, str, bytes, dict)) or (isinstance(m, np.ndarray) and
                                                           m.dtype.kind not in "iuf"):
                raise ValueError("not numbers")
            a = np.array(m, dtype=np.float64)
            if a.shape != shape:
                raise ValueError(f"shape {a.shape}")
            out.append(a)
    except (ValueError, TypeError, OverflowError) as e:
        raise ParqError(f"{where}: {what} must be a list of {shape[0]}x{shape[1]} number "
                        f"matrices ({e})") from None
    return np.stack(out) if out else np.zeros((0, *shape))


def _image(folder: pathlib.Path, image_id: str) -> pathlib.Path:
    for suffix in IMAGE_SUFFIXES:
        p = folder / f"{image_id}{suffix}"
        if p.is_file():
            return p
    raise ParqError(f"{folder / (image_id + '.jpg')}: image not found (listed in {PICKLE})")


def read(path: pathlib.Path) -> Capture:
    pkl = path / PICKLE
    data = safe_load(pkl)
    if isinstance(data, dict) and "image_ids" in data:
        data = [data]
    if not isinstance(data, list):
        raise ParqError(f"{pkl}: expected a list of fragments (dicts), found a "
                        f"{type(data).__name__}")
    if not (path / "images").is_dir():
        raise ParqError(f"{path}: the demo layout needs an images/ folder beside {PICKLE}")
    frames, seen = [], {}
    for n, fragment in enumerate(data):
        where = f"{pkl}: fragment {n}"
        if not isinstance(fragment, dict):
            raise ParqError(f"{where}: expected a dict, found a {type(fragment).__name__}")
        missing = [k for k in ("image_ids", "extrinsics", "intrinsics") if k not in fragment]
        if missing:
            raise ParqError(f"{where}: lacks {', '.join(missing)}")
        ids = fragment["image_ids"]
        if isinstance(ids, np.ndarray):
            ids = ids.tolist()
        if not isinstance(ids, (list, tuple)) or not all(
                isinstance(i, (str, int, np.integer)) and not isinstance(i, bool) for i in ids):
            raise ParqError(f"{where}: image_ids must be a list of strings")
        ids = [str(i) for i in ids]
        if any(("/" in i or "\\" in i or i in ("", ".", "..")) for i in ids):
            raise ParqError(f"{where}: image ids must be plain names, not paths")
        poses = _matrices(fragment["extrinsics"], (4, 4), where, "extrinsics")
        Ks = _matrices(fragment["intrinsics"], (3, 3), where, "intrinsics")
        if not len(ids) == len(poses) == len(Ks):
            raise ParqError(f"{where}: {len(ids)} image ids, {len(poses)} extrinsics and "
                            f"{len(Ks)} intrinsics; they must match one to one")
        for image_id, T, K in zip(ids, poses, Ks):
            frame_where = f"{where}, image {image_id}"
            geometry.check_rigid(T, frame_where)
            if np.any(K[2] != (0, 0, 1)) or K[0, 1] != 0 or np.any(K[1:, 0] != 0):
                raise ParqError(f"{frame_where}: not pinhole intrinsics "
                                f"{np.round(K, 3).tolist()}")
            K = pinhole_matrix(K[0, 0], K[1, 1], K[0, 2], K[1, 2], frame_where)
            if image_id in seen:
                if not np.allclose(seen[image_id].cam_to_world, T, atol=1e-6):
                    raise ParqError(f"{frame_where}: listed again with another pose")
                continue
            frame = Frame(image_id, _image(path / "images", image_id), T, K,
                          source=f"{pkl} fragment {n}")
            seen[image_id] = frame
            frames.append(frame)
    return Capture(path, "demo", frames, UP)
