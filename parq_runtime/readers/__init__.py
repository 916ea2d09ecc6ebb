"""Frame readers: a capture folder -> posed frames whose images load only when needed.

Every reader returns a :class:`Capture`: frames in capture order, each with its camera-to-world
pose in OpenCV camera axes (x right, y down, z forward), its 3x3 intrinsics for the image as
:meth:`Frame.load_image` returns it (pixel centres at integer coordinates, the runtime's
convention), and a path to the image.  ``up`` is the world's up axis.

Formats (one module each, conventions in each module's docstring and in docs/readers.md):

    scannet      color/ + pose/ + intrinsic/          z-up world
    arkitscenes  lowres_wide/ + *.pincam + .traj       z-up world
    demo         fragments.pkl + images/               z-up world (PlanarRecon/NeuralRecon tool)
    nerfstudio   transforms.json                       no fixed up: estimated (--up auto)
    colmap       cameras.txt + images.txt              no gravity: estimated (--up auto)

Images are never read while a capture is opened (only poses and intrinsics are), so a long
video costs a few hundred bytes per frame; :meth:`Frame.load_image` reads, checks and (for
distorted cameras) undistorts one image when the detector needs it.

Image sizes: the runtime resizes every frame to the network size, so frames of different sizes
are fine *when their intrinsics are per frame* (ARKitScenes, nerfstudio, COLMAP, demo).  Where
a format states a size (pincam ``w h``, transforms.json ``w h``, cameras.txt ``WIDTH HEIGHT``)
an image of another size is an error, and where one set of intrinsics without a size serves all
frames (ScanNet's intrinsic_color.txt) every frame must have the size of the first one loaded.
"""
from __future__ import annotations

import importlib
import math
import pathlib
import re
import warnings
from dataclasses import dataclass, field

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..errors import ParqError

FORMATS = ("scannet", "arkitscenes", "demo", "nerfstudio", "colmap")
_MODULES = {"scannet": "scannet", "arkitscenes": "arkit", "demo": "demo_pkl",
            "nerfstudio": "nerfstudio", "colmap": "colmap"}


class SizeGroup:
    """Frames sharing one set of intrinsics that states no image size: the first image loaded
    fixes the size, and an image of another size is an error (one K cannot fit both)."""

    def __init__(self, source: str):
        self.source = source
        self.size = None
        self.first = None

    def check(self, path, size: tuple) -> None:
        if self.size is None:
            self.size, self.first = size, path
        elif size != self.size:
            first = pathlib.Path(self.first).name
            raise ParqError(f"{path}: image is {size[0]}x{size[1]} but {first} is "
                            f"{self.size[0]}x{self.size[1]}; the frames share one set of "
                            f"intrinsics ({self.source}), which cannot fit both sizes")


@dataclass(slots=True)
class Frame:
    """One posed frame.  cam_to_world (4, 4) float64 = T_world_camera (OpenCV camera axes);
    intrinsics (3, 3) for the image that :meth:`load_image` returns.

    size: (w, h) the format states for this image (None: not stated); source: the file the
    intrinsics come from (for messages); undistort: a callable applied to the decoded image
    (distorted COLMAP / nerfstudio cameras); size_group: frames sharing intrinsics that state no
    size (:class:`SizeGroup`)."""

    name: str
    image_path: pathlib.Path
    cam_to_world: np.ndarray
    intrinsics: np.ndarray
    size: tuple | None = None
    source: str = ""
    undistort: object = None
    size_group: SizeGroup | None = None

    def load_image(self) -> np.ndarray:
        """RGB uint8 (H, W, 3), decoded with Pillow as the authors do, checked against the
        intrinsics and undistorted where the camera has distortion; ParqError naming the file
        if it is unreadable or does not fit."""
        image = load_rgb(self.image_path)
        check_fits(self, image.shape[1], image.shape[0])
        if self.undistort is not None:
            image = self.undistort(image)
        return image


def check_headers(frames) -> None:
    """Read every frame's image header (not its pixels) and check its size against the
    intrinsics, so that a missing, unreadable or mis-sized image stops a run before it starts
    rather than hours into it.  Pixel data that is corrupt past the header is found when the
    image is decoded.  An image above Pillow's decompression-bomb limit (89 megapixels, more
    than any camera frame) is refused here, where Pillow would only have warned."""
    for frame in frames:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", Image.DecompressionBombWarning)
                with Image.open(frame.image_path) as im:
                    w, h = im.size
        except FileNotFoundError:
            raise ParqError(f"{frame.image_path}: image not found") from None
        except (Image.DecompressionBombWarning, Image.DecompressionBombError):
            raise ParqError(f"{frame.image_path}: image is larger than "
                            f"{Image.MAX_IMAGE_PIXELS / 1e6:.0f} megapixels, not a camera "
                            "frame") from None
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError, TypeError) as e:
            raise ParqError(f"{frame.image_path}: not a readable image ({e})") from None
        check_fits(frame, w, h)


@dataclass
class Capture:
    """path, format name, frames in capture order, ``up`` = the world's up axis (unit 3-tuple),
    ``up_source``: "format" (the format's convention), "option" (given by the user) or
    "estimated" (from the cameras, :mod:`parq_runtime.gravity`); notes: things the reader did
    that the user should know (skipped frames, the up estimate); warnings: things that are
    probably wrong."""

    path: pathlib.Path
    format: str
    frames: list
    up: tuple | None = (0.0, 0.0, 1.0)
    notes: list = field(default_factory=list)
    up_source: str = "format"
    warnings: list = field(default_factory=list)


def load_rgb(path) -> np.ndarray:
    path = pathlib.Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            rgb = im.convert("RGB")
    except FileNotFoundError:
        raise ParqError(f"{path}: image not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, TypeError,
            Image.DecompressionBombError) as e:
        raise ParqError(f"{path}: not a readable image ({e})") from None
    return np.asarray(rgb)


def check_fits(frame: Frame, w: int, h: int) -> None:
    """ParqError naming the image unless (w, h) matches the stated size and the principal point
    lies inside the image."""
    where = f" ({frame.source})" if frame.source else ""
    if frame.size is not None and (w, h) != tuple(frame.size):
        raise ParqError(f"{frame.image_path}: image is {w}x{h} but its intrinsics{where} state "
                        f"{frame.size[0]}x{frame.size[1]}")
    if frame.size_group is not None:
        frame.size_group.check(frame.image_path, (w, h))
    cx, cy = frame.intrinsics[0, 2], frame.intrinsics[1, 2]
    if not (0 < cx < w and 0 < cy < h):
        raise ParqError(f"{frame.image_path}: principal point ({cx:.1f}, {cy:.1f}) of its "
                        f"intrinsics{where} lies outside the {w}x{h} image: the intrinsics do "
                        "not fit it")


def read_text(path, what: str) -> str:
    path = pathlib.Path(path)
    try:
        return path.read_text()
    except FileNotFoundError:
        raise ParqError(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise ParqError(f"{path}: {what} is a folder, expected a file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ParqError(f"{path}: {what} unreadable ({e})") from None


def parse_floats(tokens, where: str, what: str) -> np.ndarray:
    """Floats from text tokens; ParqError naming ``where`` if one is not a number."""
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        bad = next(t for t in tokens if not _is_float(t))
        raise ParqError(f"{where}: {what} holds {bad[:20]!r}, which is not a number") from None


def _is_float(token) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def read_matrix(path, shape, what: str) -> np.ndarray:
    """A whitespace-separated text matrix; ParqError naming the file if it is not ``shape``
    (None: any number of values, returned flat)."""
    path = pathlib.Path(path)
    text = read_text(path, what)
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


def pinhole_matrix(fx, fy, cx, cy, where: str) -> np.ndarray:
    """3x3 K; ParqError naming ``where`` unless the values are finite and fx, fy > 0."""
    values = np.array([fx, fy, cx, cy], dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise ParqError(f"{where}: intrinsics hold NaN or infinite values")
    if fx <= 0 or fy <= 0:
        raise ParqError(f"{where}: focal lengths must be positive, got fx = {fx:g}, "
                        f"fy = {fy:g}")
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def image_size(value_w, value_h, where: str) -> tuple:
    """(w, h) as positive integers from numbers that must be whole; ParqError otherwise."""
    out = []
    for v, name in ((value_w, "width"), (value_h, "height")):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise ParqError(f"{where}: image {name} {v!r} is not a number")
        if not math.isfinite(v) or v != int(v) or not 1 <= v <= 100_000:
            raise ParqError(f"{where}: image {name} {float(v):g} is not a whole number of "
                            "pixels (1 to 100000)")
        out.append(int(v))
    return tuple(out)


def natural_key(text: str):
    """Sort key that orders frame2 before frame10."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", text)]


def unique_names(frames: list, where) -> None:
    seen = {}
    for f in frames:
        if f.name in seen:
            raise ParqError(f"{where}: frame {f.name!r} is listed twice")
        seen[f.name] = f


def _module(name: str):
    return importlib.import_module(f".{_MODULES[name]}", __name__)


def detect_format(path: pathlib.Path, notes: list | None = None) -> str:
    """The first format (in FORMATS order) whose files are in ``path``; others that also match
    are mentioned in ``notes``."""
    path = pathlib.Path(path)
    matches = [name for name in FORMATS if _module(name).looks_like(path)]
    if not matches:
        raise ParqError(f"{path}: no known capture layout found (expected a ScanNet export "
                        "with color/, pose/ and intrinsic/; ARKitScenes lowres_wide/ with "
                        "lowres_wide.traj; the demo's fragments.pkl with images/; a "
                        "nerfstudio transforms.json; or a COLMAP text model, cameras.txt and "
                        "images.txt, here or in sparse/0/)")
    if len(matches) > 1 and notes is not None:
        notes.append(f"the folder also looks like {', '.join(matches[1:])}; read as "
                     f"{matches[0]} (choose with --format)")
    return matches[0]


def open_capture(path, format: str | None = None, up=None) -> Capture:
    """Read a capture folder's poses and intrinsics (images stay on disk).

    format: one of FORMATS, or None to detect it; up: None for the format's convention (an
    estimate where it has none), "auto" to estimate it from the cameras, or an axis ("+z",
    "-y", ... or a 3-vector); see :func:`parq_runtime.gravity.resolve`."""
    from .. import gravity

    path = pathlib.Path(path)
    if not path.exists():
        raise ParqError(f"{path}: not found")
    if not path.is_dir():
        raise ParqError(f"{path}: not a folder")
    notes = []
    if format is None:
        format = detect_format(path, notes)
    elif format not in FORMATS:
        raise ParqError(f"unknown format {format!r} (known: {', '.join(FORMATS)})")
    capture = _module(format).read(path)
    capture.notes[:0] = notes
    if not capture.frames:
        raise ParqError(f"{path}: no frames found")
    gravity.resolve(capture, up)
    return capture
