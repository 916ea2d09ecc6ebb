"""The world's up axis: from the format's convention, the user, or estimated from the cameras.

PARQ needs gravity: every snippet is predicted in a gravity-aligned frame (see
geometry.pseudo_cameras).  ScanNet, ARKitScenes and the demo's fragments.pkl fix it (z up);
COLMAP has none and nerfstudio files have none they can be relied on, so there it is estimated.

Estimate (``--up auto``).  People and robots film with the camera's x axis (image right) close
to horizontal and the optical axis near the horizon, so

* up is the direction most orthogonal to every camera's x axis: the eigenvector of the smallest
  eigenvalue of the scatter ``S = mean(x x^T)`` of the x axes.  It is exact whenever the
  cameras do not roll, whatever they pitch, provided they turn (yaw) at all;
* its sign makes it point against the cameras' mean y axis (image down);
* when the x axes are all nearly parallel (a camera that never turns), S cannot tell up from
  the walking direction; then up is the mean camera up axis (-y) with its component along the
  x axes removed, which tilts by the cameras' mean pitch: that case is warned about.

Many worlds are built axis-aligned (ARKit's y up, ScanNet's and nerfstudio's z up, COLMAP's
first camera's -y), so an estimate within ``SNAP_DEGREES`` of a world axis is replaced by that
axis (the note says so and by how much); a random direction lands that close to one of the six
axes with a probability of about 1%.

Quality (warnings): the RMS and largest angle of the x axes above the estimated horizontal
plane (camera roll, or a camera held in portrait), how well the turning pins the estimate down
(an angle from the ratio of the two smallest eigenvalues), and the mean angle between the
camera up axes (-y) and the estimate (the optical axes are far from the horizon on average).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import ParqError

AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0),
        "-y": (0.0, -1.0, 0.0), "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
CHOICES = ("+z", "+y", "-z", "-y", "+x", "-x", "auto")
SNAP_DEGREES = 5.0
# x axes within about 0.6 degrees of one direction: the cameras do not turn.
DEGENERATE_TURN = 1e-4
WARN_ROLL_DEGREES = 10.0      # RMS angle of the x axes out of the horizontal plane
WARN_UNCERTAIN_DEGREES = 5.0  # atan(sqrt(lambda_min / lambda_mid))
WARN_TILT_DEGREES = 45.0      # mean angle between camera up (-y) and the estimate
# a given --up or convention that far from the estimate is probably wrong
DISAGREE_DEGREES = 30.0


@dataclass
class Estimate:
    """up (3,) unit vector (snapped when ``snapped``); raw: before snapping; cameras: how many;
    roll_rms_deg / roll_max_deg: angles of the camera x axes out of the horizontal plane of
    ``raw``; uncertainty_deg: how loosely the x axes pin ``raw`` down; tilt_mean_deg: mean angle
    between the camera up axes (-y) and ``raw``; degenerate: the cameras never turn;
    warnings: what makes the estimate poor (empty when it is good)."""

    up: np.ndarray
    raw: np.ndarray
    cameras: int
    roll_rms_deg: float
    roll_max_deg: float
    uncertainty_deg: float
    tilt_mean_deg: float
    degenerate: bool
    snapped: str | None = None
    snap_deg: float = 0.0
    warnings: list = field(default_factory=list)

    def summary(self) -> str:
        s = (f"from {self.cameras} camera{'s' if self.cameras != 1 else ''}: x axes "
             f"{self.roll_rms_deg:.1f} deg RMS ({self.roll_max_deg:.1f} max) from the horizontal "
             f"plane, camera up {self.tilt_mean_deg:.1f} deg from it on average")
        if self.snapped:
            s += f"; snapped to the world axis {self.snapped}, {self.snap_deg:.2f} deg away"
        return s


def axis_name(up) -> str:
    """'+z' for (0, 0, 1), else the rounded vector."""
    up = np.asarray(up, dtype=np.float64)
    for name, axis in AXES.items():
        if np.allclose(up, axis, atol=1e-12):
            return name
    return "(" + ", ".join(f"{v:.4f}" for v in up) + ")"


def parse_up(value):
    """None, "auto", an axis name or a 3-vector -> None, "auto" or a unit 3-tuple."""
    if value is None or (isinstance(value, str) and value == "auto"):
        return value
    if isinstance(value, str):
        if value.strip() in AXES:
            return AXES[value.strip()]
        raise ParqError(f"up axis {value!r}: use one of {', '.join(CHOICES)}")
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise ParqError(f"up axis {value!r}: expected a non-zero 3-vector")
    return tuple(float(c) for c in v / np.linalg.norm(v))


def _axes(cam_to_world) -> tuple:
    T = np.asarray(cam_to_world, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise ParqError(f"up estimate: expected (N, 4, 4) camera poses, got shape {T.shape}")
    if not np.all(np.isfinite(T[:, :3, :3])):
        raise ParqError("up estimate: camera poses hold NaN or infinite values")
    x, y = T[:, :3, 0], T[:, :3, 1]
    nx, ny = np.linalg.norm(x, axis=1), np.linalg.norm(y, axis=1)
    if np.any(nx < 1e-9) or np.any(ny < 1e-9):
        raise ParqError("up estimate: a camera pose has a zero rotation axis")
    return x / nx[:, None], y / ny[:, None]


def estimate(cam_to_world, snap_degrees: float = SNAP_DEGREES) -> Estimate:
    """Estimate the world's up axis from camera poses (N, 4, 4) T_world_camera, OpenCV camera
    axes.  See the module docstring."""
    x, y = _axes(cam_to_world)
    n = len(x)
    scatter = x.T @ x / n
    values, vectors = np.linalg.eigh(scatter)       # ascending
    values = np.clip(values, 0.0, None)
    down = y.mean(0)
    degenerate = values[1] < DEGENERATE_TURN
    if degenerate:
        main = vectors[:, 2]
        u = -(down - (down @ main) * main)
        if np.linalg.norm(u) < 1e-9:                # down axes cancel out: take any normal
            u = vectors[:, 0]
        u = u / np.linalg.norm(u)
        uncertainty = 90.0
    else:
        u = vectors[:, 0].copy()
        uncertainty = float(np.degrees(np.arctan(np.sqrt(values[0] / values[1]))))
    if u @ down > 0:
        u = -u
    elif u @ down == 0 and u[np.argmax(np.abs(u))] < 0:
        u = -u                                      # no hint at all: a deterministic sign
    roll = np.degrees(np.arcsin(np.clip(np.abs(x @ u), 0.0, 1.0)))
    tilt = np.degrees(np.arccos(np.clip(-(y @ u), -1.0, 1.0)))
    est = Estimate(u.copy(), u.copy(), n, float(np.sqrt(np.mean(roll ** 2))),
                   float(roll.max()), uncertainty, float(tilt.mean()), bool(degenerate))
    if n < 3:
        est.warnings.append(f"only {n} camera{'s' if n != 1 else ''}")
    if degenerate:
        est.warnings.append("the cameras never turn (their x axes are parallel): up is the mean "
                            "camera up axis, off by the cameras' mean pitch")
    elif est.uncertainty_deg > WARN_UNCERTAIN_DEGREES:
        est.warnings.append(f"the cameras turn too little for the roll they have (up uncertain "
                            f"by about {est.uncertainty_deg:.0f} deg)")
    if est.roll_rms_deg > WARN_ROLL_DEGREES:
        est.warnings.append(f"the camera x axes are {est.roll_rms_deg:.0f} deg RMS out of any "
                            "plane (rolled or portrait camera?)")
    if est.tilt_mean_deg > WARN_TILT_DEGREES:
        est.warnings.append(f"camera up axes are {est.tilt_mean_deg:.0f} deg from the estimate "
                            "on average (optical axes far from the horizon)")
    best = max(AXES, key=lambda k: float(np.dot(AXES[k], u)))
    angle = float(np.degrees(np.arccos(np.clip(np.dot(AXES[best], u), -1.0, 1.0))))
    if angle <= snap_degrees:
        est.up = np.array(AXES[best])
        est.snapped, est.snap_deg = best, angle
    return est


def angle_deg(a, b) -> float:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def resolve(capture, choice=None) -> None:
    """Set ``capture.up`` and ``capture.up_source``: ``choice`` None keeps the format's
    convention (estimates where ``capture.up`` is None), "auto" estimates, an axis (see
    :func:`parse_up`) is taken as given.  Appends the estimate to ``capture.notes`` and its
    problems, or a given axis that the cameras contradict, to ``capture.warnings``."""
    choice = parse_up(choice)
    poses = np.stack([f.cam_to_world for f in capture.frames])
    if choice == "auto" or (choice is None and capture.up is None):
        est = estimate(poses)
        capture.up, capture.up_source = tuple(float(v) for v in est.up), "estimated"
        capture.notes.append(f"up {axis_name(est.up)} estimated {est.summary()}")
        if est.warnings:
            capture.warnings.append("the up estimate is poor: " + "; ".join(est.warnings) +
                                    " (give the world's up axis with --up)")
        return
    if choice is not None:
        capture.up, capture.up_source = choice, "option"
    else:
        capture.up = parse_up(tuple(capture.up))
    est = estimate(poses)
    if not est.warnings and angle_deg(est.raw, capture.up) > DISAGREE_DEGREES:
        given = "--up" if capture.up_source == "option" else f"the {capture.format} convention"
        capture.warnings.append(
            f"up {axis_name(capture.up)} ({given}) is {angle_deg(est.raw, capture.up):.0f} deg "
            f"from the up the cameras suggest, {axis_name(est.up)}: is --up right?")
