"""The floor's height, found in the images by a one-parameter plane sweep.

Indoor furniture stands on the floor, so a box of a floor-standing class has its center half
its height above it.  Along a camera's viewing ray, which points down at furniture from eye
height, that fixes the depth the network is least sure of (fusion's ``ray`` mode explains the
error it leaves).  Snapping to the floor needs the floor's height in the world frame, which a
posed capture does not state.  This module finds it from the frames themselves.

Sweep.  For a candidate floor height ``h`` along the up axis, a pixel of frame i whose ray
points down meets the plane ``up . X = h`` at one world point; projected into frame j it should
show the same floor texture.  The cost of ``h`` is the mean truncated absolute difference of
grey levels over textured pixels (Sobel gradient above ``GRADIENT``), over pairs of frames with
a useful baseline (``MIN_BASELINE`` to ``MAX_BASELINE`` apart, optical axes within
``MAX_ANGLE``).  Pixels on furniture or walls mismatch at every ``h`` and the truncation caps
what they add, so a textured floor shows as a sharp dip.  Tabletops and seats make dips too.

Candidates.  Every local minimum of the cost that lies below the cost ``FLANK`` under and over
it by at least ``PROMINENCE`` of its own value is a candidate, refined on a finer grid.  The
sweep alone cannot tell a floor from a tabletop, or say that a plain floor made no dip.  So
the scene's fused boxes give a coarse guess first (the median bottom of its floor-class boxes:
fusion.SceneFusion.floor_guess); the sweep runs within ``TOLERANCE`` of it, and
:func:`choose` takes the candidate nearest it, or none (then no box is pulled).

Measured with the demo on its 120 held-out scenes (parq-synth, floor at z = 0;
``python benchmarks/floor.py --scenes 120``, benchmarks/results/floor.md): a floor is found in
100, with a median error of 6 mm (90% within 3.3 cm, 11 over 3 cm, the worst 12 cm), in a
median 0.19 s a capture on 2 cores (160x120 frames).  In the other 20 (6 of the 22 carpets, 9
of 48 plank floors, 5 of 50 tiled) no dip lay near the guess, and no box was pulled.  What it
gives the demo: docs/demo-experiments.md, "The floor, found in the images".

Why 12 pairs (``PAIRS``).  More pairs find no more floors.  On the 160 validation scenes, each
swept near one saved guess (the median bottom of an exploratory fusion's boxes: scene NMS 0.05,
seven floor classes):

* 12, 24 and 48 pairs find a floor in 141, 141 and 139 scenes;
* of those, 19, 15 and 13 are more than 3 cm off;
* a sweep takes 0.12, 0.25 and 0.48 s.

The validation F1@0.25 / F1@0.5 through the card's fusion (its own guesses, near which those
sweeps' candidates are chosen) moves by at most 0.002: 0.573 / 0.402, 0.573 / 0.400 and 0.574 /
0.402.  The true floor in all 160 scenes would give 0.579 / 0.415.  On the held-out scenes with
saved guesses of the same kind, 24 pairs find 105 floors against 12 pairs' 103 (100 above:
parq-run's own guesses), again 11 of them more than 3 cm off.  (Exploratory scripts over saved
detections.)
"""
from __future__ import annotations

import cv2
import numpy as np

MIN_BASELINE, MAX_BASELINE = 0.3, 1.2     # metres between a pair's cameras
MAX_ANGLE = 30.0                          # degrees between a pair's optical axes
PAIRS = 12                                # pairs used, spread over the capture
FRAMES = 48                               # frames considered, spread over the capture
GRADIENT = 4.0                            # grey levels per pixel: a textured pixel
PIXELS = 8000                             # textured pixels of a frame used, at most
TRUNCATE = 6.0                            # grey levels: the most one pixel adds to a cost
MIN_DOWN = 0.15                           # a ray must point this far down (cosine with -up)
BELOW_CAMERA = (0.4, 2.6)                 # metres below the median camera: the sweep's range
COARSE, FINE = 0.02, 0.0025               # metres between candidates
FLANK = 0.06                              # metres either side of a dip it must be below
PROMINENCE = 0.002                        # of the cost at the dip
TOLERANCE = 0.15                          # metres from the guess a candidate may be


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 grey levels of an RGB uint8 image, lightly smoothed."""
    g = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return cv2.GaussianBlur(g, (3, 3), 0.7)


def pairs(T_world_camera: np.ndarray, most: int = PAIRS) -> list:
    """(i, j) frame pairs with a useful baseline and overlapping views, at most ``most``,
    spread evenly over all such pairs in capture order."""
    centers = T_world_camera[:, :3, 3]
    axes = T_world_camera[:, :3, 2]
    found = []
    for i in range(len(T_world_camera)):
        baseline = np.linalg.norm(centers[i + 1:] - centers[i], axis=1)
        angle = np.degrees(np.arccos(np.clip(axes[i + 1:] @ axes[i], -1.0, 1.0)))
        ok = (baseline >= MIN_BASELINE) & (baseline <= MAX_BASELINE) & (angle <= MAX_ANGLE)
        found += [(i, i + 1 + int(k)) for k in np.flatnonzero(ok)]
    if len(found) > most:
        found = [found[k] for k in np.linspace(0, len(found) - 1, most).round().astype(int)]
    return found


class _Pair:
    """Frame i's textured, downward pixels as world rays, and frame j to compare them in."""

    def __init__(self, grey_i, grey_j, K_i, K_j, T_world_i, T_world_j, up):
        h, w = grey_i.shape
        gx = cv2.Sobel(grey_i, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(grey_i, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        v, u = np.nonzero(np.hypot(gx, gy) > GRADIENT)
        if len(u) > PIXELS:                 # evenly thinned: the cost is a mean
            keep = np.linspace(0, len(u) - 1, PIXELS).round().astype(int)
            v, u = v[keep], u[keep]
        pixels = np.stack([u, v, np.ones_like(u)]).astype(np.float64)      # (3, N)
        rays_world = T_world_i[:3, :3] @ (np.linalg.inv(K_i) @ pixels)
        rays_world /= np.linalg.norm(rays_world, axis=0)
        down = -(up @ rays_world)
        keep = down > MIN_DOWN
        self.rays_world, self.down = rays_world[:, keep], down[keep]
        self.values_i = grey_i[v[keep], u[keep]]
        self.origin_world = T_world_i[:3, 3]
        self.height_i = float(up @ self.origin_world)
        self.R_j_world = T_world_j[:3, :3].T
        self.t_j = -self.R_j_world @ T_world_j[:3, 3]
        self.K_j, self.grey_j, self.size = K_j, grey_j, (w, h)

    def cost(self, height: float) -> float:
        """Mean truncated grey-level difference at floor height ``height`` (NaN if fewer than
        50 pixels land in frame j)."""
        distance = (self.height_i - height) / self.down
        points_world = self.origin_world[:, None] + self.rays_world * distance
        points_j = self.R_j_world @ points_world + self.t_j[:, None]
        z = points_j[2]
        ok = z > 0.1
        uv = (self.K_j @ points_j)[:2] / np.where(ok, z, 1.0)
        w, h = self.size
        ok &= (uv[0] >= 0) & (uv[0] <= w - 1) & (uv[1] >= 0) & (uv[1] <= h - 1)
        if ok.sum() < 50:
            return float("nan")
        seen = cv2.remap(self.grey_j, uv[0, ok].astype(np.float32)[None],
                         uv[1, ok].astype(np.float32)[None], cv2.INTER_LINEAR)[0]
        return float(np.minimum(np.abs(self.values_i[ok] - seen), TRUNCATE).mean())


def _costs(prepared: list, heights: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        table = np.array([[p.cost(h) for h in heights] for p in prepared])
        counted = np.isfinite(table).sum(0)
        return np.where(counted > 0, np.nansum(table, 0) / np.maximum(counted, 1), np.nan)


def candidates(frames: list, up, near: float | None = None) -> list:
    """Heights (world metres along ``up``) of the floor-like planes the frames agree on,
    best first: [(height, prominence)], prominence the dip's depth below its flanks as a
    fraction of its cost.  ``frames``: readers.Frame objects of one capture (at most
    ``FRAMES`` are read); ``near``: sweep only within ``TOLERANCE`` of this height (what
    :func:`choose` can take; 5 times faster than the whole range below the cameras)."""
    up = np.asarray(up, dtype=np.float64)
    if len(frames) > FRAMES:
        frames = [frames[k] for k in np.linspace(0, len(frames) - 1, FRAMES).round().astype(int)]
    T_world_camera = np.stack([f.cam_to_world for f in frames])
    chosen = pairs(T_world_camera)
    if not chosen:
        return []
    greys = {i: grey(frames[i].load_image()) for i in sorted({k for p in chosen for k in p})}
    prepared = [_Pair(greys[i], greys[j], frames[i].intrinsics, frames[j].intrinsics,
                      T_world_camera[i], T_world_camera[j], up) for i, j in chosen]
    if near is None:
        camera = float(np.median(T_world_camera[:, :3, 3] @ up))
        heights = camera - np.arange(BELOW_CAMERA[0], BELOW_CAMERA[1] + 1e-9, COARSE)
    else:
        reach = TOLERANCE + FLANK + COARSE
        heights = near + reach - np.arange(0.0, 2 * reach + 1e-9, COARSE)
    cost = _costs(prepared, heights)
    flank = int(round(FLANK / COARSE))
    found = []
    for k in range(flank, len(heights) - flank):
        window = cost[k - flank:k + flank + 1]
        if not np.isfinite(window).all() or cost[k] > window.min() or cost[k] <= 0:
            continue
        prominence = (min(cost[k - flank], cost[k + flank]) - cost[k]) / cost[k]
        if prominence >= PROMINENCE:
            found.append((_refine(prepared, float(heights[k])), float(prominence)))
    return sorted(found, key=lambda c: -c[1])


def _refine(prepared: list, height: float) -> float:
    """The minimum of the cost on a finer grid around ``height``, with a parabola's vertex."""
    heights = height + np.arange(-COARSE * 1.5, COARSE * 1.5 + 1e-9, FINE)
    cost = _costs(prepared, heights)
    if not np.isfinite(cost).any():
        return float(height)
    k = int(np.nanargmin(cost))
    best = float(heights[k])
    if 0 < k < len(cost) - 1 and np.isfinite(cost[k - 1:k + 2]).all():
        a, b, c = cost[k - 1:k + 2]
        curvature = a - 2 * b + c
        if curvature > 0:
            best += float(0.5 * (a - c) / curvature * FINE)
    return best


def locate(guess: float | None, sweep) -> tuple:
    """(the floor height, the candidates it was chosen from) for a coarse ``guess`` (the fused
    boxes', fusion.SceneFusion.floor_guess): ``sweep(guess)`` gives the candidates near it
    (:func:`candidates` with ``near``), :func:`choose` picks one.  (None, []) without a
    guess.  parq-run and parq_train.tune both find a scene's floor with it."""
    if guess is None:
        return None, []
    found = sweep(guess)
    return choose(found, guess), found


def choose(found: list, guess: float | None, tolerance: float = TOLERANCE) -> float | None:
    """The candidate height nearest ``guess`` within ``tolerance`` (None: none, or no guess)."""
    if guess is None:
        return None
    near = [(abs(h - guess), h) for h, _ in found if abs(h - guess) <= tolerance]
    return min(near)[1] if near else None
