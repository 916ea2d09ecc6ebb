"""Lens undistortion with OpenCV, for COLMAP and nerfstudio cameras with distortion.

An :class:`Undistorter` maps a distorted image to the pinhole image with the *same* K (OpenCV's
``initUndistortRectifyMap`` with newCameraMatrix = K, then ``remap``, bilinear, black outside),
so the frame's intrinsics stay K.  The maps (fixed-point, 6 bytes a pixel) are built on first
use and kept in a small cache shared by every frame with the same camera, so a capture whose
frames each have their own distortion does not keep one pair of maps per frame.

Models (OpenCV's coefficient order):
    radial-tangential ("opencv"): (k1, k2, p1, p2[, k3[, k4, k5, k6]]), cv2.undistort's model;
    fisheye ("fisheye"): (k1, k2, k3, k4), the equidistant model of cv2.fisheye.
"""
from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np

from ..errors import ParqError

CACHE_SIZE = 4
_CACHE: OrderedDict = OrderedDict()


class Undistorter:
    def __init__(self, K: np.ndarray, coefficients, size: tuple, model: str = "opencv",
                 where: str = ""):
        self.K = np.asarray(K, dtype=np.float64)
        self.coefficients = np.asarray(coefficients, dtype=np.float64).ravel()
        self.size = tuple(int(v) for v in size)
        self.model = model
        self.where = where
        if model not in ("opencv", "fisheye"):
            raise ParqError(f"{where}: unknown distortion model {model!r}")
        if not np.all(np.isfinite(self.coefficients)):
            raise ParqError(f"{where}: distortion coefficients hold NaN or infinite values")
        if model == "fisheye" and self.coefficients.size != 4:
            raise ParqError(f"{where}: a fisheye camera needs 4 coefficients, got "
                            f"{self.coefficients.size}")
        if model == "opencv" and self.coefficients.size not in (4, 5, 8):
            raise ParqError(f"{where}: expected 4, 5 or 8 distortion coefficients, got "
                            f"{self.coefficients.size}")

    @property
    def identity(self) -> bool:
        return not np.any(self.coefficients)

    def maps(self):
        key = (self.model, self.K.tobytes(), self.coefficients.tobytes(), self.size)
        if key in _CACHE:
            _CACHE.move_to_end(key)
            return _CACHE[key]
        try:
            if self.model == "fisheye":
                maps = cv2.fisheye.initUndistortRectifyMap(
                    self.K, self.coefficients.reshape(4, 1), np.eye(3), self.K, self.size,
                    cv2.CV_16SC2)
            else:
                maps = cv2.initUndistortRectifyMap(self.K, self.coefficients, None, self.K,
                                                   self.size, cv2.CV_16SC2)
        except cv2.error as e:
            first = str(e).strip().splitlines()[-1] if str(e).strip() else "cv2 error"
            raise ParqError(f"{self.where}: OpenCV cannot undistort with these parameters "
                            f"({first})") from None
        _CACHE[key] = maps
        while len(_CACHE) > CACHE_SIZE:
            _CACHE.popitem(last=False)
        return maps

    def __call__(self, image: np.ndarray) -> np.ndarray:
        h, w = image.shape[:2]
        if (w, h) != self.size:
            raise ParqError(f"{self.where}: image is {w}x{h}, the camera is "
                            f"{self.size[0]}x{self.size[1]}")
        if self.identity:
            return image
        m1, m2 = self.maps()
        return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
