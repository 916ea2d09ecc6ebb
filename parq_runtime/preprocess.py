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
"""
from __future__ import annotations

import numpy as np
from PIL import Image

from .errors import ParqError

SCANNET_SIZE = (1296, 968)
SCANNET_PAD = 2  # rows added at the top and at the bottom


def prepare(image: np.ndarray, K: np.ndarray, size: tuple) -> tuple:
    """RGB uint8 (H, W, 3) and its 3x3 intrinsics -> (uint8 (h, w, 3) at ``size`` = (w, h),
    scaled 3x3 intrinsics, float64)."""
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
    if (w, h) != tuple(size):
        image = np.asarray(Image.fromarray(image).resize(tuple(size), Image.BILINEAR))
        K[0, :] /= w / size[0]
        K[1, :] /= h / size[1]
    return np.ascontiguousarray(image), K
