"""Boxes drawn on the frames (``parq-run --vis DIR``).

For every snippet, each of its keyframes is written as a PNG with

* the snippet's detections: solid lines in the class colour (ply.class_color), labelled with
  class and score;
* the fused scene boxes: dashed white lines;

and ``index.json`` lists the images.  Box edges are clipped against the near plane z = NEAR in
the camera frame *before* projecting (a corner behind the camera has no meaningful projection:
dividing by a negative z flips it), then against the image rectangle, and drawn with OpenCV.
Images are read one at a time (as the detector reads them), so memory stays flat.

The folder is written whole or not at all: images go to a hidden temporary folder beside it,
renamed into place at the end.  An existing folder is replaced only if it is an earlier
``--vis`` output (it holds our index.json) or empty.
"""
from __future__ import annotations

import json
import os
import pathlib
import re

import cv2
import numpy as np

from . import files, geometry
from .errors import ParqError
from .ply import class_color

NEAR = 0.05
SCHEMA = "parq-onnx/vis"
SCENE_COLOR = (255, 255, 255)


def clip_near(a: np.ndarray, b: np.ndarray, near: float = NEAR):
    """The part of segment a-b (camera frame, (3,)) with z >= near, or None."""
    za, zb = a[2], b[2]
    if za < near and zb < near:
        return None
    if za >= near and zb >= near:
        return a, b
    t = (near - za) / (zb - za)
    p = a + t * (b - a)
    p[2] = near
    return (p, b) if za < near else (a, p)


def clip_rect(p, q, w: int, h: int):
    """Liang-Barsky: the part of 2D segment p-q inside [0, w - 1] x [0, h - 1], or None."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    d = q - p
    t0, t1 = 0.0, 1.0
    for pi, di, lo, hi in ((p[0], d[0], 0.0, w - 1.0), (p[1], d[1], 0.0, h - 1.0)):
        for num, den in ((pi - lo, -di), (hi - pi, di)):
            if den == 0:
                if num < 0:
                    return None
                continue
            t = num / den
            if den < 0:
                t0 = max(t0, t)
            else:
                t1 = min(t1, t)
            if t0 > t1:
                return None
    return p + t0 * d, p + t1 * d


def project(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) of camera-frame points with z > 0 (pixel centres at
    integers)."""
    z = points_camera[..., 2:3]
    return points_camera[..., :2] / z * np.diag(K)[:2] + K[:2, 2]


def box_segments(corners_world, T_world_camera, K, size, near: float = NEAR) -> list:
    """The visible 2D segments of a box's 12 edges: [(edge index, p (2,), q (2,))], clipped to
    z >= near and to the image ``size`` = (w, h)."""
    T_camera_world = geometry.invert(np.asarray(T_world_camera, dtype=np.float64))
    corners = geometry.transform(T_camera_world, np.asarray(corners_world, dtype=np.float64))
    out = []
    for e, (i, j) in enumerate(geometry.BOX_EDGES):
        seg = clip_near(corners[i].copy(), corners[j].copy(), near)
        if seg is None:
            continue
        p, q = project(np.stack(seg), K)
        seg2 = clip_rect(p, q, *size)
        if seg2 is not None:
            out.append((e, seg2[0], seg2[1]))
    return out


def _point(p) -> tuple:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _dashed(image, p, q, color, thickness, dash: float):
    length = float(np.linalg.norm(q - p))
    if length < 1:
        return
    steps = max(1, int(length // dash))
    for k in range(0, steps, 2):
        a = p + (q - p) * (k / steps)
        b = p + (q - p) * (min(k + 1, steps) / steps)
        cv2.line(image, _point(a), _point(b), color, thickness, cv2.LINE_AA)


def draw(image: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, boxes: list,
         scene_boxes: list = (), header: str | None = None) -> np.ndarray:
    """A copy of RGB ``image`` with ``boxes`` (solid, class colour, labelled) and
    ``scene_boxes`` (dashed white) drawn on it."""
    out = np.ascontiguousarray(image).copy()
    h, w = out.shape[:2]
    thick = max(1, round(min(w, h) / 240))
    font = max(0.3, min(w, h) / 700)
    labels = []
    for box in boxes:
        segments = box_segments(box.corners, T_world_camera, K, (w, h))
        color = class_color(box.label)
        for _, p, q in segments:
            cv2.line(out, _point(p), _point(q), color, thick + 1, cv2.LINE_AA)
        if segments:
            top = min((s for seg in segments for s in seg[1:]), key=lambda s: s[1])
            labels.append((f"{box.class_name} {box.score:.2f}", top, color))
    for box in scene_boxes:
        for _, p, q in box_segments(box.corners, T_world_camera, K, (w, h)):
            _dashed(out, p, q, SCENE_COLOR, thick, dash=max(4.0, min(w, h) / 60))
    for text, (x, y), color in labels:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font, 1)
        x = int(min(max(x, 0), max(w - tw - 2, 0)))
        y = int(min(max(y - 3, th + 2), h - 2))
        cv2.rectangle(out, (x, y - th - 2), (x + tw + 2, y + base - 1), (0, 0, 0), -1)
        cv2.putText(out, text, (x + 1, y - 1), cv2.FONT_HERSHEY_SIMPLEX, font, color, 1,
                    cv2.LINE_AA)
    if header:
        (tw, th), base = cv2.getTextSize(header, cv2.FONT_HERSHEY_SIMPLEX, font, 1)
        cv2.rectangle(out, (0, 0), (min(tw + 4, w), th + base + 4), (0, 0, 0), -1)
        cv2.putText(out, header, (2, th + 2), cv2.FONT_HERSHEY_SIMPLEX, font,
                    (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _is_ours(folder: pathlib.Path) -> bool:
    try:
        return json.loads((folder / "index.json").read_text()).get("schema") == SCHEMA
    except (OSError, ValueError, AttributeError):
        return False


def check_output(folder) -> pathlib.Path:
    """Fail early, before any work, if ``folder`` cannot become the --vis output."""
    folder = pathlib.Path(folder)
    parent = folder.absolute().parent
    if folder.exists():
        if not folder.is_dir():
            raise ParqError(f"{folder}: exists and is not a folder")
        if any(folder.iterdir()) and not _is_ours(folder):
            raise ParqError(f"{folder}: exists and is not an earlier --vis output (no "
                            "index.json of ours); choose another folder or empty it")
    if not parent.is_dir():
        raise ParqError(f"{parent}: folder does not exist")
    if not os.access(parent, os.W_OK):
        raise ParqError(f"{parent}: not writable")
    return folder


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._")[:80] or "frame"


def write(result, folder) -> int:
    """Draw every keyframe of every snippet of a :class:`~parq_runtime.scene.SceneResult` into
    ``folder`` (atomically); returns the number of images."""
    folder = check_output(folder)
    frames = {f.name: f for f in result.capture.frames}
    scene_boxes = list(result.fusion.boxes) if result.fusion is not None else []
    index = []
    with files.atomic_folder(folder, "the visualisation") as tmp:
        for snippet in result.snippets:
            for j, name in enumerate(snippet.frames):
                frame = frames[name]
                image = frame.load_image()
                header = (f"snippet {snippet.index} view {j}: {len(snippet.boxes)} boxes, "
                          f"scene {len(scene_boxes)} (dashed)")
                drawn = draw(image, frame.intrinsics, frame.cam_to_world, snippet.boxes,
                             scene_boxes, header)
                file = f"snippet{snippet.index:04d}_view{j}_{_safe(name)}.png"
                ok, data = cv2.imencode(".png", drawn[..., ::-1])
                if not ok:
                    raise ParqError(f"{folder / file}: OpenCV could not encode the image")
                (tmp / file).write_bytes(data.tobytes())
                index.append({"file": file, "snippet": snippet.index, "view": j,
                              "frame": name, "boxes": len(snippet.boxes)})
        (tmp / "index.json").write_text(json.dumps(
            {"schema": SCHEMA, "version": 1, "capture": str(result.capture.path),
             "scene_boxes": len(scene_boxes), "images": index}, indent=1) + "\n")
    return len(index)
