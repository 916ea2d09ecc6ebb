"""Frame readers: a capture folder -> posed frames whose images load only when needed.

Every reader returns a :class:`Capture`: frames in capture order, each with its camera-to-world
pose in OpenCV camera axes (x right, y down, z forward), its 3x3 intrinsics for the stored image,
and a path to the image.  ``up`` is the world's up axis in the reader's convention.
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import ParqError


@dataclass
class Frame:
    """One posed frame.  cam_to_world (4, 4) float64 = T_world_camera; intrinsics (3, 3) for the
    image as stored."""

    name: str
    image_path: pathlib.Path
    cam_to_world: np.ndarray
    intrinsics: np.ndarray

    def load_image(self) -> np.ndarray:
        """RGB uint8 (H, W, 3), decoded with Pillow as the authors do; ParqError if unreadable."""
        return load_rgb(self.image_path)


@dataclass
class Capture:
    path: pathlib.Path
    format: str
    frames: list
    up: tuple = (0.0, 0.0, 1.0)
    notes: list = field(default_factory=list)  # things the reader skipped, for the user


def load_rgb(path) -> np.ndarray:
    path = pathlib.Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            rgb = im.convert("RGB")
    except FileNotFoundError:
        raise ParqError(f"{path}: image not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ParqError(f"{path}: not a readable image ({e})") from None
    return np.asarray(rgb)


def read_matrix(path, shape, what: str) -> np.ndarray:
    """A whitespace-separated text matrix; ParqError naming the file if it is not ``shape``
    (None: any number of values, returned flat)."""
    path = pathlib.Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ParqError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ParqError(f"{path}: {what} unreadable ({e})") from None
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise ParqError(f"{path}: {what} holds text that is not a number") from None
    if shape is None:
        return values
    if values.size != int(np.prod(shape)):
        raise ParqError(f"{path}: {what} has {values.size} numbers, expected "
                        f"{'x'.join(map(str, shape))}")
    return values.reshape(shape)


FORMATS = ("scannet",)


def detect_format(path: pathlib.Path) -> str:
    from . import scannet

    if scannet.looks_like(path):
        return "scannet"
    raise ParqError(f"{path}: no known capture layout found (expected a ScanNet export with "
                    "color/, pose/ and intrinsic/)")


def open_capture(path, format: str | None = None) -> Capture:
    """Read a capture folder's poses and intrinsics (images stay on disk)."""
    from . import scannet

    path = pathlib.Path(path)
    if not path.exists():
        raise ParqError(f"{path}: not found")
    if not path.is_dir():
        raise ParqError(f"{path}: not a folder")
    format = format or detect_format(path)
    readers = {"scannet": scannet.read}
    if format not in readers:
        raise ParqError(f"unknown format {format!r} (known: {', '.join(readers)})")
    capture = readers[format](path)
    if not capture.frames:
        raise ParqError(f"{path}: no frames found")
    return capture
