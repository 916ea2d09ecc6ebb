"""ScanNet export layout (what ScanNet's SensReader writes), z-up world:

    color/<i>.jpg|.png   or the authors' color/frame-%06d.color.jpg
    pose/<i>.txt         or pose/frame-%06d.pose.txt: camera-to-world 4x4, OpenCV axes
    intrinsic/intrinsic_color.txt: 4x4 (or 3x3) for the colour images

ScanNet marks frames where tracking was lost with poses full of -inf; those frames are skipped
(the authors' preprocessing skips them too) and counted in ``Capture.notes``.  Any other bad
pose (NaN, a matrix that is not rigid) is an error naming the file.

Pixel convention: ScanNet's intrinsics put pixel centres at integer coordinates (the authors'
and SensReader's use), the runtime's convention, so K is used as stored.  One intrinsics file
serves every frame and states no image size: all colour frames must have the size of the first
one loaded (checked as images load; a frame of another size is an error naming it).
"""
from __future__ import annotations

import pathlib
import re

import numpy as np

from .. import geometry
from ..errors import ParqError
from . import Capture, Frame, SizeGroup, read_matrix

COLOR = re.compile(r"^(?:frame-)?(\d+)(?:\.color)?\.(jpg|jpeg|png)$", re.IGNORECASE)
POSE = re.compile(r"^(?:frame-)?(\d+)(?:\.pose)?\.txt$")


UP = geometry.UP_Z


def looks_like(path: pathlib.Path) -> bool:
    return (path / "color").is_dir() and (path / "pose").is_dir()


def _index(folder: pathlib.Path, pattern, what: str) -> dict:
    found = {}
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if not m:
            continue
        i = int(m.group(1))
        if i in found:
            raise ParqError(f"{folder}: two {what} files for frame {i}: {found[i].name} and "
                            f"{p.name}")
        found[i] = p
    return found


def read(path: pathlib.Path) -> Capture:
    for sub in ("color", "pose", "intrinsic"):
        if not (path / sub).is_dir():
            raise ParqError(f"{path}: ScanNet layout needs a {sub}/ folder")
    intrinsic = path / "intrinsic" / "intrinsic_color.txt"
    if not intrinsic.is_file():
        raise ParqError(f"{intrinsic}: not found")
    values = read_matrix(intrinsic, None, "intrinsics")
    if values.size not in (9, 16):
        raise ParqError(f"{intrinsic}: expected a 3x3 or 4x4 matrix, found {values.size} "
                        "numbers")
    K = values.reshape(3, 3) if values.size == 9 else values.reshape(4, 4)[:3, :3]
    # the runtime reads fx, fy, cx, cy: anything else must be the pinhole's zeros
    if (not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0
            or np.any(K[2] != (0, 0, 1)) or K[1, 0] != 0 or abs(K[0, 1]) > 1e-6 * K[0, 0]):
        raise ParqError(f"{intrinsic}: not pinhole intrinsics (need fx, fy > 0, no skew and "
                        f"last row 0 0 1; got {np.round(K, 4).tolist()})")
    colors = _index(path / "color", COLOR, "colour")
    poses = _index(path / "pose", POSE, "pose")
    if not colors:
        raise ParqError(f"{path / 'color'}: no colour frames (<i>.jpg, <i>.png or "
                        "frame-%06d.color.jpg)")
    no_pose = sorted(set(colors) - set(poses))
    no_color = sorted(set(poses) - set(colors))
    if no_pose:
        raise ParqError(f"{path / 'pose'}: no pose for {len(no_pose)} colour frame(s), "
                        f"first {colors[no_pose[0]].name}")
    if no_color:
        raise ParqError(f"{path / 'color'}: no colour frame for {len(no_color)} pose(s), "
                        f"first {poses[no_color[0]].name}")
    frames, lost = [], 0
    source = str(intrinsic)
    group = SizeGroup(source)
    for i in sorted(colors):
        T = read_matrix(poses[i], (4, 4), "pose")
        if np.all(np.isneginf(T[:3])):     # ScanNet's mark of a lost frame; +inf is an error
            lost += 1
            continue
        geometry.check_rigid(T, str(poses[i]))
        frames.append(Frame(str(i), colors[i], T, K.copy(), source=source,
                            size_group=group))
    capture = Capture(path, "scannet", frames, geometry.UP_Z)
    if lost:
        capture.notes.append(f"skipped {lost} frame(s) whose pose is marked invalid (-inf)")
    return capture
