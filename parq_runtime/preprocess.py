"""Image preparation exactly as the authors' data pipeline does it.

ScanNet colour frames (1296 x 968) are first padded with 2 black rows at the top and bottom to
1296 x 972 (4:3; cy += 2).  Every frame is then resized to the network size with
``PIL.Image.resize(..., BILINEAR)``, which antialiases when shrinking (a triangle filter whose
support grows with the scale factor), and stays uint8.  Intrinsic rows are scaled by
width_net / width and height_net / height.

Why Pillow and not OpenCV: the authors' numbers come from PIL's filter; measured on ScanNet-size
frames (1296 x 972 -> 320 x 240, ``benchmarks/preprocess_numerics.py``), cv2.INTER_AREA lands up
to tens of grey levels away from it and INTER_LINEAR (no antialiasing) further, while Pillow is
the reference itself: 0 difference, at about 2 ms a frame.

A model trained on frames rendered at its own size (``parq-train`` on ``parq-synth`` scenes)
saw no filter at all: a renderer's pixel is its centre ray, a point sample.  Its card says
``image.filter = "point"`` and frames of another size reach it point-sampled too: pixel (u, v)
of the network image is pixel (round(u * W / w), round(v * H / h)) of the frame, whose ray is
the one the scaled intrinsics give it (exactly, for whole-number ratios such as 320 -> 160).
Measured on the demo model (``benchmarks/resize_softness.py --seed 3000 5000 --scenes 120``):
240 held-out rooms rendered at 320x240 score F1@0.25 / F1@0.5 0.566 / 0.371 point-sampled to
160x120, level with the same rooms rendered at 160x120 (0.566 / 0.368), and 0.559 / 0.360
through Pillow's antialiasing filter, softer than anything that model trained on.  Point
sampling aliases when it shrinks a lot (a 1296-wide camera frame to 160); it is right for
models that were trained on unfiltered frames, and the authors' cards keep Pillow.
"""
from __future__ import annotations

import numpy as np
from PIL import Image

from .errors import ParqError

SCANNET_SIZE = (1296, 968)
SCANNET_PAD = 2  # rows added at the top and at the bottom
AUTHORS_FILTER = "pillow-bilinear"
FILTERS = (AUTHORS_FILTER, "point")  # how a frame is brought to the network size
PHASES = (0.0, 0.5)  # point-sampling grids, in network pixels: parq-run's, and half a pixel over


def prepare(image: np.ndarray, K: np.ndarray, size: tuple,
            image_filter: str = AUTHORS_FILTER, phase: float = 0.0) -> tuple:
    """RGB uint8 (H, W, 3) and its 3x3 intrinsics -> (uint8 (h, w, 3) at ``size`` = (w, h),
    scaled 3x3 intrinsics, float64); ``image_filter`` one of FILTERS (module doc); ``phase``
    one of PHASES: which point-sampling grid (:func:`grids`; only the ``point`` filter has a
    second, and only for frames at least twice the network size each way)."""
    if image_filter not in FILTERS:
        raise ParqError(f"unknown resize filter {image_filter!r} (one of "
                        f"{', '.join(FILTERS)})")
    if phase not in PHASES:
        raise ParqError(f"sampling phase {phase!r} must be one of {PHASES}")
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ParqError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} "
                        f"{image.shape}")
    K = np.array(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ParqError(f"intrinsics must be a finite 3x3 matrix with positive focal lengths, "
                        f"got {K.tolist()}")
    h, w = image.shape[:2]
    if not (0 < K[0, 2] < w and 0 < K[1, 2] < h):
        raise ParqError(f"principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the "
                        f"{w}x{h} image: the intrinsics do not fit it")
    if (w, h) == SCANNET_SIZE:
        image = np.pad(image, ((SCANNET_PAD, SCANNET_PAD), (0, 0), (0, 0)))
        K[1, 2] += SCANNET_PAD
        h += 2 * SCANNET_PAD
    if phase and grids((w, h), size, image_filter) < 2:
        raise ParqError(f"a {w}x{h} frame has one sampling grid for a {size[0]}x{size[1]} "
                        f"network with the {image_filter!r} filter, not a phase {phase} one")
    if (w, h) != tuple(size):
        if image_filter == "point":
            image = image[point_samples(h, size[1], phase)][:, point_samples(w, size[0], phase)]
        else:
            image = np.asarray(Image.fromarray(image).resize(tuple(size), Image.BILINEAR))
        K[0, :] /= w / size[0]
        K[1, :] /= h / size[1]
        K[:2, 2] -= phase
    return np.ascontiguousarray(image), K


def point_samples(n_in: int, n_out: int, phase: float = 0.0) -> np.ndarray:
    """(n_out,) indices of the input pixels along one axis that a point-sampling resize from
    ``n_in`` to ``n_out`` pixels takes: the nearest to (u + phase) * n_in / n_out, where the
    intrinsics scaled by n_out / n_in, their principal point less ``phase``, put output pixel
    u's ray."""
    return np.minimum(np.rint((np.arange(n_out) + phase) * (n_in / n_out)).astype(np.int64),
                      n_in - 1)


def grids(frame_size: tuple, size: tuple, image_filter: str) -> int:
    """How many of PHASES give a ``frame_size`` = (W, H) frame distinct point-sampling grids at
    the network ``size`` = (w, h): 2 with the ``point`` filter when W >= 2 w and H >= 2 h (a
    320x240 frame for 160x120: pixels (2u, 2v) and (2u + 1, 2v + 1), no pixel shared), else 1
    (a grid half a network pixel over would repeat the first one's pixels, and a filtered
    frame has no grid)."""
    (W, H), (w, h) = frame_size, size
    return 2 if image_filter == "point" and W >= 2 * w and H >= 2 * h else 1
