"""Class-typical furniture built from primitives, in the object frame.

Object frame (the detector's): x = the object's width axis, y = up, z = x cross y; the object
spans [-size/2, size/2] and stands on y = -size[1]/2.  "Front" is +z: a chair's backrest, a
sofa's back and a bookshelf's back panel are at -z; a cabinet's doors and a display's screen
face +z.  Every shape fills its box exactly (some primitive touches each of the six faces), so
the box written as ground truth is the tight bounding box of the geometry (``SceneObject``
recomputes it from the primitives; a test checks it equals the requested size).

Primitives are axis-aligned in the object frame: ``Primitive.kind`` is BOX (the box lo..hi)
or CYLINDER (the elliptic cylinder inscribed in lo..hi, its axis along object y).  Colours are
sRGB in [0, 1]; ``material`` picks a procedural texture (see render.py).
"""
from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np

CLASSES = ("chair", "table", "cabinet", "trash bin", "bookshelf", "display", "sofa",
           "bathtub", "other")
# Full extents (x, y = up, z) in metres: the class means of the authors' model card.
MEAN_SIZES = {
    "chair": (0.5507, 0.8494, 0.5786),
    "table": (1.2451, 0.6617, 0.7246),
    "cabinet": (0.9566, 0.9997, 0.5625),
    "trash bin": (0.3664, 0.4558, 0.2788),
    "bookshelf": (1.0513, 1.3472, 0.3374),
    "display": (0.6074, 0.4752, 0.1644),
    "sofa": (1.6882, 0.7664, 0.8935),
    "bathtub": (0.8531, 0.4393, 0.5161),
}
OTHER_SIZE_RANGE = (0.3, 1.0)
SIZE_FACTOR_RANGE = (0.8, 1.2)

BOX, CYLINDER = 0, 1
# Materials (procedural textures, see render.shade_objects).
PLAIN, WOOD, FABRIC, SCREEN, METAL = 0, 1, 2, 3, 4


@dataclass
class Primitive:
    kind: int
    lo: np.ndarray      # (3,) object frame
    hi: np.ndarray      # (3,)
    color: tuple        # sRGB in [0, 1]
    material: int = PLAIN
    emission: float = 0.0


def box_prim(lo, hi, color, material=PLAIN, emission=0.0) -> Primitive:
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    assert np.all(hi > lo), (lo, hi)
    return Primitive(BOX, lo, hi, tuple(float(c) for c in color), material, emission)


def cylinder_prim(lo, hi, color, material=PLAIN) -> Primitive:
    p = box_prim(lo, hi, color, material)
    p.kind = CYLINDER
    return p


def sample_size(rng: np.random.Generator, class_name: str) -> np.ndarray:
    if class_name == "other":
        return rng.uniform(*OTHER_SIZE_RANGE, size=3)
    return np.asarray(MEAN_SIZES[class_name]) * rng.uniform(*SIZE_FACTOR_RANGE, size=3)


# ----------------------------------------------------------------------------- colours

def vary(rng, rgb, hue=0.02, sat=0.15, val=0.12) -> tuple:
    """Per-instance variation of an sRGB colour in HSV."""
    h, s, v = colorsys.rgb_to_hsv(*rgb)
    h = (h + rng.uniform(-hue, hue)) % 1.0
    s = float(np.clip(s * rng.uniform(1 - sat, 1 + sat), 0, 1))
    v = float(np.clip(v * rng.uniform(1 - val, 1 + val), 0, 1))
    return colorsys.hsv_to_rgb(h, s, v)


def pick(rng, palette, **kw) -> tuple:
    return vary(rng, palette[int(rng.integers(len(palette)))], **kw)


def _hex(*codes):
    return tuple(tuple(int(c[i:i + 2], 16) / 255 for i in (0, 2, 4)) for c in codes)


WOODS = _hex("8b5a2b", "a0703c", "c39a6b", "5c3a1e", "d2b48c", "6f4e37")
DARK = _hex("1e1e1e", "2b2b2e", "3a3a3a")
METALS = _hex("9ea3a8", "c0c4c8", "6d7175")
WHITES = _hex("ece9e2", "f4f4f0", "dcdad2")
FABRICS = _hex("7a7f87", "b9ad96", "2e3f5c", "3f5a3a", "7b2d26", "5a4a42", "8c8c8c", "4b5d6b")
CHAIR_SEATS = _hex("a33a2c", "2f4b7c", "3c6e47", "606060", "202020", "c9b48a")
LAMINATES = _hex("ece9e2", "b8b2a6", "8f969c", "c8b08a", "6b4c30", "3c3c3c")
BINS = _hex("4d4d4d", "2a5db0", "3b8a4a", "d8d8d8", "8a8f94", "b0302a")
BOOKS = _hex("8e2323", "23468e", "2f7a3a", "c99a1e", "5a2d82", "d06a1f", "1f1f1f", "e0d6c0",
             "2d8a8a", "9c9c9c")
CERAMIC = _hex("f2f2ee", "ebe6da", "e4ebef")


# ----------------------------------------------------------------------------- shapes

def chair(rng, s):
    x, y, z = s / 2
    y0 = -y
    seat_top = y0 + s[1] * rng.uniform(0.48, 0.56)
    seat_t = rng.uniform(0.04, 0.07)
    leg = rng.uniform(0.035, 0.06)
    inset = rng.uniform(0.0, 0.025)
    back_t = rng.uniform(0.03, 0.06)
    group = int(rng.integers(3))
    frame = pick(rng, (WOODS, DARK, METALS)[group])
    frame_mat = (WOOD, PLAIN, METAL)[group]
    same = rng.random() < 0.4
    seat_c = vary(rng, frame, 0.01, 0.05, 0.05) if same else pick(rng, CHAIR_SEATS)
    seat_mat = frame_mat if same else FABRIC
    prims = [box_prim((-x, seat_top - seat_t, -z), (x, seat_top, z), seat_c, seat_mat)]
    round_legs = rng.random() < 0.35
    for sx in (-1, 1):
        for sz in (-1, 1):
            cx, cz = sx * (x - inset - leg / 2), sz * (z - inset - leg / 2)
            lo = (cx - leg / 2, y0, cz - leg / 2)
            hi = (cx + leg / 2, seat_top - seat_t, cz + leg / 2)
            prims.append((cylinder_prim if round_legs else box_prim)(lo, hi, frame, frame_mat))
    if rng.random() < 0.6:   # solid backrest
        prims.append(box_prim((-x, seat_top, -z), (x, y, -z + back_t), seat_c, seat_mat))
    else:                    # two posts and a rail
        rail = rng.uniform(0.08, 0.16)
        post = max(leg, 0.03)
        for sx in (-1, 1):
            lo = (min(sx * x, sx * (x - post)), seat_top, -z)
            hi = (max(sx * x, sx * (x - post)), y - rail, -z + back_t)
            prims.append(box_prim(lo, hi, frame, frame_mat))
        prims.append(box_prim((-x, y - rail, -z), (x, y, -z + back_t), seat_c, seat_mat))
    return prims


def table(rng, s):
    x, y, z = s / 2
    top_t = rng.uniform(0.03, 0.06)
    leg = rng.uniform(0.04, 0.08)
    inset = rng.uniform(0.02, 0.1)
    if rng.random() < 0.7:
        top_c, mat = pick(rng, WOODS), WOOD
    else:
        top_c, mat = pick(rng, WHITES + DARK), PLAIN
    leg_c = top_c if rng.random() < 0.6 else pick(rng, DARK + METALS)
    leg_mat = mat if leg_c == top_c else METAL
    prims = [box_prim((-x, y - top_t, -z), (x, y, z), top_c, mat)]
    round_legs = rng.random() < 0.3
    for sx in (-1, 1):
        for sz in (-1, 1):
            cx, cz = sx * (x - inset - leg / 2), sz * (z - inset - leg / 2)
            lo, hi = (cx - leg / 2, -y, cz - leg / 2), (cx + leg / 2, y - top_t, cz + leg / 2)
            prims.append((cylinder_prim if round_legs else box_prim)(lo, hi, leg_c, leg_mat))
    if rng.random() < 0.5:   # apron
        a = rng.uniform(0.06, 0.1)
        xi, zi = x - inset - leg, z - inset - leg
        t = 0.02
        prims.append(box_prim((-xi, y - top_t - a, zi - t), (xi, y - top_t, zi), top_c, mat))
        prims.append(box_prim((-xi, y - top_t - a, -zi), (xi, y - top_t, -zi + t), top_c, mat))
    return prims


def cabinet(rng, s):
    x, y, z = s / 2
    door_t = rng.uniform(0.015, 0.025)
    handle_t = rng.uniform(0.02, 0.03)
    zb = z - door_t - handle_t
    i = int(rng.integers(len(LAMINATES)))
    body = vary(rng, LAMINATES[i])
    mat = WOOD if i in (3, 4) else PLAIN
    door_c = vary(rng, body, 0.01, 0.08, 0.08)
    handle_c = pick(rng, METALS + DARK)
    plinth = rng.uniform(0.03, 0.08)
    gap = rng.uniform(0.004, 0.01)
    prims = [box_prim((-x, -y, -z), (x, y, zb), body, mat)]
    fy0, fy1 = -y + plinth, y - 0.02
    layout = rng.choice(["doors", "drawers", "mixed"])
    hl = rng.uniform(0.08, 0.2)   # handle length
    hw = 0.015
    fronts = []   # (x0, x1, y0, y1, vertical handle side or 0 for a centred horizontal one)
    if layout == "doors":
        n = 1 if s[0] < 0.6 or rng.random() < 0.3 else 2
        xs = np.linspace(-x + 0.01, x - 0.01, n + 1)
        for i in range(n):
            side = 1 if (n == 1 or i == 0) else -1
            fronts.append((xs[i], xs[i + 1], fy0, fy1, side))
    elif layout == "drawers":
        n = int(rng.integers(2, 5))
        ys = np.linspace(fy0, fy1, n + 1)
        fronts += [(-x + 0.01, x - 0.01, ys[i], ys[i + 1], 0) for i in range(n)]
    else:
        split = fy1 - (fy1 - fy0) * rng.uniform(0.2, 0.3)
        fronts.append((-x + 0.01, x - 0.01, split, fy1, 0))
        fronts.append((-x + 0.01, 0.0, fy0, split, 1))
        fronts.append((0.0, x - 0.01, fy0, split, -1))
    for x0, x1, y0, y1, side in fronts:
        x0, x1, y0, y1 = x0 + gap / 2, x1 - gap / 2, y0 + gap / 2, y1 - gap / 2
        prims.append(box_prim((x0, y0, zb), (x1, y1, zb + door_t), door_c, mat))
        if side == 0:
            cy, cx = (y0 + y1) / 2 + (y1 - y0) * 0.2, (x0 + x1) / 2
            lh = min(hl, (x1 - x0) * 0.6)
            lo, hi = (cx - lh / 2, cy - hw / 2, zb + door_t), (cx + lh / 2, cy + hw / 2, z)
        else:
            cx = x1 - 0.05 if side == 1 else x0 + 0.05
            cy = (y0 + y1) / 2 + (y1 - y0) * 0.15
            lh = min(hl, (y1 - y0) * 0.6)
            lo, hi = (cx - hw / 2, cy - lh / 2, zb + door_t), (cx + hw / 2, cy + lh / 2, z)
        prims.append(box_prim(lo, hi, handle_c, METAL))
    return prims


def trash_bin(rng, s):
    x, y, z = s / 2
    color = pick(rng, BINS)
    inside = tuple(c * 0.25 for c in color)
    rim_h = rng.uniform(0.02, 0.04)
    if rng.random() < 0.6:   # round (elliptic) bin with a rim and a dark opening
        k = rng.uniform(0.9, 0.95)
        prims = [cylinder_prim((-k * x, -y, -k * z), (k * x, y - 0.006, k * z), color),
                 cylinder_prim((-x, y - rim_h, -z), (x, y - 0.005, z), vary(rng, color, 0, 0, 0.1)),
                 cylinder_prim((-0.85 * x, y - 0.01, -0.85 * z), (0.85 * x, y, 0.85 * z), inside)]
    else:                    # a box bin stepping wider towards the top
        k0, k1 = rng.uniform(0.82, 0.9), rng.uniform(0.9, 0.96)
        mid = -y + s[1] * rng.uniform(0.4, 0.6)
        prims = [box_prim((-k0 * x, -y, -k0 * z), (k0 * x, mid, k0 * z), color),
                 box_prim((-k1 * x, mid, -k1 * z), (k1 * x, y - 0.006, k1 * z), color),
                 box_prim((-x, y - rim_h, -z), (x, y - 0.005, z), vary(rng, color, 0, 0, 0.1)),
                 box_prim((-0.85 * x, y - 0.01, -0.85 * z), (0.85 * x, y, 0.85 * z), inside)]
    return prims


def bookshelf(rng, s):
    x, y, z = s / 2
    painted = rng.random() < 0.3
    wood = pick(rng, WHITES[:1] + DARK[:1]) if painted else pick(rng, WOODS)
    mat = PLAIN if painted else WOOD
    st = rng.uniform(0.018, 0.035)     # board thickness
    plinth = rng.uniform(0.04, 0.08)
    back = 0.01
    prims = [box_prim((-x, -y, -z), (-x + st, y, z), wood, mat),
             box_prim((x - st, -y, -z), (x, y, z), wood, mat),
             box_prim((-x + st, y - st, -z), (x - st, y, z), wood, mat),
             box_prim((-x + st, -y, -z + 0.02), (x - st, -y + plinth, z), wood, mat),
             box_prim((-x + st, -y + plinth, -z), (x - st, y - st, -z + back),
                  vary(rng, wood, 0, 0.05, 0.15), mat)]
    n = int(np.clip(round(s[1] / rng.uniform(0.28, 0.4)), 2, 5))
    levels = np.linspace(-y + plinth, y - st, n + 1)   # compartment floors / ceilings
    for i in range(1, n):
        prims.append(box_prim((-x + st, levels[i] - st / 2, -z + back),
                          (x - st, levels[i] + st / 2, z), wood, mat))
    for i in range(n):
        floor = levels[i] + (st / 2 if i > 0 else 0.0)
        ceil = levels[i + 1] - (st / 2 if i + 1 < n else 0.0)
        room = ceil - floor
        if room < 0.08 or rng.random() < 0.12:
            continue
        u = -x + st + rng.uniform(0, 0.05)
        end = x - st - rng.uniform(0.0, (2 * x - 2 * st) * 0.6)
        count = 0
        while count < 9:
            w = rng.uniform(0.03, 0.09)
            if u + w > end:
                break
            h = room * rng.uniform(0.55, 0.92)
            d = (2 * z - back) * rng.uniform(0.6, 0.95)
            prims.append(box_prim((u, floor, -z + back), (u + w, floor + h, -z + back + d),
                              pick(rng, BOOKS, hue=0.02, sat=0.2, val=0.2), PLAIN))
            count += 1
            u += w + (rng.uniform(0.03, 0.12) if rng.random() < 0.15 else 0.002)
    return prims


def display(rng, s):
    x, y, z = s / 2
    frame = pick(rng, DARK + METALS[2:] + WHITES[:1], val=0.05)
    base_t = rng.uniform(0.012, 0.025)
    bw = s[0] * rng.uniform(0.3, 0.45) / 2
    panel_t = rng.uniform(0.02, 0.045)
    neck_w, neck_t = rng.uniform(0.04, 0.07), rng.uniform(0.015, 0.03)
    panel_h = min(s[0] * rng.uniform(0.55, 0.66), s[1] - 0.06)
    py0 = y - panel_h
    pz0 = -panel_t / 2 + rng.uniform(-0.01, 0.01)
    pz0 = min(max(pz0, -z + neck_t), z - panel_t - 0.003)
    bezel = rng.uniform(0.008, 0.02)
    on = rng.random() < 0.6
    screen_c = (0.02, 0.025, 0.03)
    emission = rng.uniform(0.25, 0.7) if on else 0.0
    return [
        box_prim((-bw, -y, -z), (bw, -y + base_t, z), frame, METAL),
        box_prim((-neck_w / 2, -y + base_t, pz0 - neck_t), (neck_w / 2, py0 + panel_h * 0.5, pz0),
             frame, METAL),
        box_prim((-x, py0, pz0), (x, y, pz0 + panel_t), frame, PLAIN),
        box_prim((-x + bezel, py0 + bezel * 1.5, pz0 + panel_t), (x - bezel, y - bezel,
             pz0 + panel_t + 0.003), screen_c, SCREEN, emission),
    ]


def sofa(rng, s):
    x, y, z = s / 2
    fabric = pick(rng, FABRICS)
    leather = rng.random() < 0.2
    mat = PLAIN if leather else FABRIC
    if leather:
        fabric = pick(rng, _hex("3b2418", "1c1c1c", "6b3a1f", "d8cdb8"))
    legs_c = pick(rng, WOODS + DARK)
    lh = rng.uniform(0.03, 0.1)
    aw = rng.uniform(0.1, 0.22)
    bt = rng.uniform(0.15, 0.25)
    seat = -y + min(rng.uniform(0.38, 0.48), s[1] * 0.62)
    ct = rng.uniform(0.08, 0.14)
    arm_top = -y + max(seat + y + 0.1, s[1] * rng.uniform(0.55, 0.75))
    prims = [box_prim((-x + aw, -y + lh, -z + bt), (x - aw, seat - ct, z), fabric, mat),
             box_prim((-x, -y + lh, -z), (x, y, -z + bt), fabric, mat),
             box_prim((-x, -y + lh, -z), (-x + aw, arm_top, z), fabric, mat),
             box_prim((x - aw, -y + lh, -z), (x, arm_top, z), fabric, mat)]
    n = 2 if s[0] < 1.6 or rng.random() < 0.5 else 3
    xs = np.linspace(-x + aw, x - aw, n + 1)
    cushion = vary(rng, fabric, 0.01, 0.05, 0.06)
    for i in range(n):
        prims.append(box_prim((xs[i] + 0.005, seat - ct, -z + bt), (xs[i + 1] - 0.005, seat,
                                                                  z - 0.01), cushion, mat))
    leg = rng.uniform(0.04, 0.06)
    for sx in (-1, 1):
        for sz in (-1, 1):
            cx, cz = sx * (x - 0.03 - leg / 2), sz * (z - 0.03 - leg / 2)
            prims.append(box_prim((cx - leg / 2, -y, cz - leg / 2), (cx + leg / 2, -y + lh,
                                                                  cz + leg / 2), legs_c, WOOD))
    return prims


def bathtub(rng, s):
    x, y, z = s / 2
    c = pick(rng, CERAMIC, val=0.04)
    wt = rng.uniform(0.04, 0.08)
    bt = rng.uniform(0.05, 0.1)
    return [box_prim((-x, -y, -z), (x, -y + bt, z), c),
            box_prim((-x, -y + bt, -z), (x, y, -z + wt), c),
            box_prim((-x, -y + bt, z - wt), (x, y, z), c),
            box_prim((-x, -y + bt, -z + wt), (-x + wt, y, z - wt), c),
            box_prim((x - wt, -y + bt, -z + wt), (x, y, z - wt), c)]


def other(rng, s):
    x, y, z = s / 2
    h, sat, v = rng.random(), rng.uniform(0.2, 0.8), rng.uniform(0.3, 0.9)
    color = colorsys.hsv_to_rgb(h, sat, v)
    mat = [PLAIN, WOOD, FABRIC][int(rng.integers(3))]
    kind = rng.random()
    if kind < 0.4:
        return [box_prim(-s / 2, s / 2, color, mat)]
    if kind < 0.7:
        return [cylinder_prim(-s / 2, s / 2, color, mat)]
    top = rng.uniform(0.03, 0.08)
    leg = rng.uniform(0.03, 0.06)
    prims = [box_prim((-x, y - top, -z), (x, y, z), color, mat)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            cx, cz = sx * (x - leg / 2), sz * (z - leg / 2)
            prims.append(box_prim((cx - leg / 2, -y, cz - leg / 2), (cx + leg / 2, y - top,
                                                                  cz + leg / 2), color, mat))
    return prims


BUILDERS = {"chair": chair, "table": table, "cabinet": cabinet, "trash bin": trash_bin,
            "bookshelf": bookshelf, "display": display, "sofa": sofa, "bathtub": bathtub,
            "other": other}


def build(rng, class_name: str, size) -> list:
    """Primitives (object frame) of one instance of ``class_name`` filling ``size``."""
    return BUILDERS[class_name](rng, np.asarray(size, dtype=np.float64))
