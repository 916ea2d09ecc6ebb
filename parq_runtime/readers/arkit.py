"""ARKitScenes raw layout (Apple's ARKitScenes dataset, "raw" and "3dod" downloads):

    lowres_wide/<video>_<timestamp>.png                  RGB frames (256x192 for the dataset)
    lowres_wide_intrinsics/<video>_<timestamp>.pincam    one line "w h fx fy cx cy"
    lowres_wide.traj                                     per line "timestamp rx ry rz tx ty tz"

The folder may also be the scene folder holding one ``<video>_frames/`` with these files (the
3dod download).

Conventions, as verified in the ARKitScenes repository (github.com/apple/ARKitScenes, DATA.md
and threedod/benchmark_scripts/utils/tenFpsDataLoader.py, rotation.py and rectify_im.py):

* a traj line holds an axis-angle rotation (radians; ``cv2.Rodrigues``) and a translation
  (metres) that together map **world to camera**: ``TrajStringToMatrix`` builds
  ``[R | t]`` and returns its inverse as the camera-to-world pose;
* camera axes are OpenCV's (x right, y down, z forward): ``generate_point`` back-projects pixel
  (u, v) with depth d through K as (u d, v d, d) and maps it to the world with that pose;
* the world is **z up** (gravity along -z): ``rectify_im.decide_pose`` calls an image upright
  when the camera's -y axis is closest to world +z, and ``upright_camera_relative_transform``
  takes heading in the x-y plane ("z-dim as height").  Checked numerically on the two traj
  lines quoted in rectify_im.py: they come out upside-down and rotated left, as its comments
  say, only under this reading;
* intrinsics: K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] used with integer pixel coordinates
  (pixel centres at integers, the runtime's convention), so K is taken as stored;
* frames are matched to poses by timestamp: the loader rounds the traj timestamps to 3
  decimals and takes the pose whose key equals the frame's timestamp, else one within 5 ms
  (no interpolation).  Here: the nearest traj timestamp within 5 ms; frames without one are
  skipped and counted in ``Capture.notes``.  The pincam of a frame is looked up by name, or
  1 ms either side as the loader does (nearest within 1.5 ms here).

ARKit itself is y-up; ARKitScenes' trajectories are not (see above).  A capture written in this
layout from an ARKit session's own y-up world needs ``--up +y``; parq-run warns when the
cameras contradict the up axis in use.  Frames are used as stored: ARKitScenes videos filmed in
portrait or upside down give sideways or upside-down images, unlike the upright ScanNet frames
PARQ was trained on (the dataset's rectify_im.py shows how to turn them).
"""
from __future__ import annotations

import pathlib
import re

import numpy as np

from .. import geometry
from ..errors import ParqError
from . import Capture, Frame, image_size, parse_floats, pinhole_matrix, read_text

UP = geometry.UP_Z
IMAGES, INTRINSICS, TRAJ = "lowres_wide", "lowres_wide_intrinsics", "lowres_wide.traj"
NAME = re.compile(r"^(.+)_(\d+(?:\.\d*)?)\.(png|jpg|jpeg)$", re.IGNORECASE)
PINCAM = re.compile(r"^(.+)_(\d+(?:\.\d*)?)\.pincam$")
POSE_TOLERANCE = 0.005       # seconds, as tenFpsDataLoader
PINCAM_TOLERANCE = 0.0015    # the loader tries the name and +-0.001 s


def _root(path: pathlib.Path) -> pathlib.Path | None:
    if (path / TRAJ).is_file() or (path / IMAGES).is_dir():
        return path
    try:
        inner = [p for p in path.iterdir() if p.name.endswith("_frames") and p.is_dir()]
    except OSError:
        return None
    if len(inner) == 1 and ((inner[0] / TRAJ).is_file() or (inner[0] / IMAGES).is_dir()):
        return inner[0]
    return None


def looks_like(path: pathlib.Path) -> bool:
    return _root(path) is not None


def _angle(r: np.ndarray) -> float:
    """|r| without overflow for large components (inf only if |r| itself is)."""
    m = float(np.max(np.abs(r)))
    return 0.0 if m == 0 else m * float(np.linalg.norm(r / m))


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis-angle vector (radians), as cv2.Rodrigues."""
    r = np.asarray(r, dtype=np.float64)
    theta = _angle(r)
    if theta < 1e-12:
        return np.eye(3) + np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    k = r / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * (K @ K)


def read_traj(path: pathlib.Path) -> tuple:
    """(timestamps (M,) sorted, cam_to_world (M, 4, 4)) from a .traj file."""
    stamps, poses = [], []
    text = read_text(path, "trajectory")
    for n, line in enumerate(text.splitlines(), 1):
        tokens = line.split()
        if not tokens:
            continue
        where = f"{path}:{n}"
        if len(tokens) != 7:
            raise ParqError(f"{where}: expected 7 numbers (timestamp rx ry rz tx ty tz), got "
                            f"{len(tokens)}")
        v = parse_floats(tokens, where, "trajectory line")
        if not np.all(np.isfinite(v)):
            raise ParqError(f"{where}: pose holds NaN or infinite values")
        if not np.isfinite(_angle(v[1:4])):
            raise ParqError(f"{where}: rotation angle is not finite")
        T_camera_world = np.eye(4)
        T_camera_world[:3, :3] = rodrigues(v[1:4])
        T_camera_world[:3, 3] = v[4:7]
        T = geometry.invert(T_camera_world)
        geometry.check_rigid(T, where)
        stamps.append(v[0])
        poses.append(T)
    if not stamps:
        raise ParqError(f"{path}: trajectory holds no poses")
    stamps = np.array(stamps)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], np.stack(poses)[order]


def read_pincam(path: pathlib.Path) -> tuple:
    """(K (3, 3), (w, h)) from a .pincam file."""
    tokens = read_text(path, "intrinsics").split()
    if len(tokens) != 6:
        raise ParqError(f"{path}: expected 6 numbers (w h fx fy cx cy), got {len(tokens)}")
    w, h, fx, fy, cx, cy = parse_floats(tokens, str(path), "intrinsics")
    size = image_size(w, h, str(path))
    K = pinhole_matrix(fx, fy, cx, cy, str(path))
    if not (0 < cx < size[0] and 0 < cy < size[1]):
        raise ParqError(f"{path}: principal point ({cx:g}, {cy:g}) lies outside the stated "
                        f"{size[0]}x{size[1]} image")
    return K, size


def _nearest(sorted_values: np.ndarray, value: float) -> int:
    i = int(np.searchsorted(sorted_values, value))
    candidates = [j for j in (i - 1, i) if 0 <= j < len(sorted_values)]
    return min(candidates, key=lambda j: abs(sorted_values[j] - value))


def _index(folder: pathlib.Path, pattern, what: str, notes: list) -> dict:
    """{timestamp: (video, path)} of the files in ``folder`` named <video>_<timestamp>.ext."""
    if not folder.is_dir():
        raise ParqError(f"{folder}: ARKitScenes layout needs this folder of {what}")
    found, other = {}, 0
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if not m:
            other += not p.name.startswith(".")
            continue
        t = float(m.group(2))
        if t in found:
            raise ParqError(f"{folder}: two {what} for timestamp {m.group(2)}: "
                            f"{found[t][1].name} and {p.name}")
        found[t] = (m.group(1), p)
    if other:
        notes.append(f"ignored {other} file(s) in {folder.name}/ not named "
                     "<video>_<timestamp>")
    return found


def read(path: pathlib.Path) -> Capture:
    root = _root(path)
    if root is None:
        raise ParqError(f"{path}: ARKitScenes layout needs {IMAGES}/, {INTRINSICS}/ and {TRAJ}")
    notes = []
    images = _index(root / IMAGES, NAME, "images", notes)
    pincams = _index(root / INTRINSICS, PINCAM, "intrinsics files", notes)
    if not images:
        raise ParqError(f"{root / IMAGES}: no frames named <video>_<timestamp>.png")
    videos = sorted({v for v, _ in images.values()})
    if len(videos) > 1:
        raise ParqError(f"{root / IMAGES}: frames of {len(videos)} videos ({', '.join(videos[:3])}"
                        "); one capture folder holds one video")
    stamps, poses = read_traj(root / TRAJ)
    pincam_times = np.array(sorted(pincams))
    used_pincams = set()
    frames, no_pose = [], 0
    for t in sorted(images):
        _, image = images[t]
        if not len(pincam_times):
            raise ParqError(f"{root / INTRINSICS}: no intrinsics files (<video>_<timestamp>."
                            "pincam)")
        j = _nearest(pincam_times, t)
        if abs(pincam_times[j] - t) > PINCAM_TOLERANCE:
            raise ParqError(f"{root / INTRINSICS}: no intrinsics for {image.name} (expected "
                            f"{image.stem}.pincam)")
        used_pincams.add(pincam_times[j])
        i = _nearest(stamps, t)
        if abs(stamps[i] - t) > POSE_TOLERANCE:
            no_pose += 1
            continue
        K, size = read_pincam(pincams[pincam_times[j]][1])
        frames.append(Frame(image.stem.split("_")[-1], image, poses[i].copy(), K, size=size,
                            source=str(pincams[pincam_times[j]][1])))
    unused = sorted(set(pincam_times) - used_pincams)
    if unused:
        raise ParqError(f"{root / IMAGES}: no image for {len(unused)} intrinsics file(s), first "
                        f"{pincams[unused[0]][1].name}")
    if not frames:
        raise ParqError(f"{root / TRAJ}: no pose within {POSE_TOLERANCE * 1000:.0f} ms of any of "
                        f"the {len(images)} frames' timestamps")
    if no_pose:
        notes.append(f"skipped {no_pose} frame(s) with no pose in {TRAJ} within "
                     f"{POSE_TOLERANCE * 1000:.0f} ms of their timestamp")
    return Capture(root, "arkitscenes", frames, UP, notes)
