"""Scene layout: room, furniture, lights, textures and the hand-held camera path.

Everything random comes from numpy ``Generator(PCG64)`` streams seeded with
``SeedSequence([seed, index], spawn_key=(stream,))``, one stream per concern (layout, camera,
style, lighting, and one per frame for sensor noise), so scene ``index`` of ``seed`` is
reproducible alone, on any machine, and changing e.g. the frame count does not move the
furniture.  The image size only scales the intrinsics: the same seed at 160x120 and 320x240
is the same scene seen through the same lens.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from parq_runtime import geometry
from parq_runtime.errors import ParqError

from . import render, shapes

GENERATOR_VERSION = 1
STREAM_LAYOUT, STREAM_CAMERA, STREAM_STYLE, STREAM_LIGHT, STREAM_NOISE = range(5)

ROOM_XY = (3.5, 7.0)
ROOM_Z = (2.5, 3.0)
EYE = (1.3, 1.7)
TILT_DEG = (10.0, 30.0)
ROLL_DEG = 3.0
CAMERA_CLEARANCE = 0.35     # bird's-eye distance from the camera path to any object
OBJECT_GAP = 0.05           # bird's-eye gap between objects
WALL_GAP = 0.03
MIN_OBJECTS = 4


def rng_for(seed: int, index: int, stream: int, *extra: int) -> np.random.Generator:
    ss = np.random.SeedSequence([int(seed), int(index)], spawn_key=(stream, *extra))
    return np.random.Generator(np.random.PCG64(ss))


def upright_rotation(yaw: float) -> np.ndarray:
    """R_world_object of an upright object with heading yaw: x = (cos, sin, 0), y = up,
    z = x cross y."""
    c, s = np.cos(yaw), np.sin(yaw)
    x = np.array([c, s, 0.0])
    y = np.array([0.0, 0.0, 1.0])
    return np.stack([x, y, np.cross(x, y)], -1)


@dataclass
class SceneObject:
    """One piece of furniture: its ground-truth box (world frame) and its primitives in the
    box frame (the box spans [-size/2, size/2], y up)."""

    class_name: str
    label: int
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray
    primitives: list

    @property
    def yaw(self) -> float:
        return float(geometry.yaw(self.rotation))

    @classmethod
    def place(cls, class_name: str, primitives: list, floor_point, yaw: float,
              base_height: float = 0.0) -> "SceneObject":
        """Stand primitives (built around the origin, y up) with their lowest point at
        ``base_height`` above ``floor_point`` (x, y), heading ``yaw``; the box is the tight
        bounding box of the primitives."""
        lo = np.min([p.lo for p in primitives], 0)
        hi = np.max([p.hi for p in primitives], 0)
        mid = (lo + hi) / 2
        prims = [shapes.Primitive(p.kind, p.lo - mid, p.hi - mid, p.color, p.material,
                                  p.emission) for p in primitives]
        R = upright_rotation(yaw)
        center = np.array([floor_point[0], floor_point[1], 0.0]) + R @ np.array(
            [mid[0], 0.0, mid[2]])
        center[2] = base_height + (hi[1] - lo[1]) / 2
        return cls(class_name, shapes.CLASSES.index(class_name), center, hi - lo, R, prims)

    def footprint(self) -> np.ndarray:
        """Bird's-eye corners (4, 2) of the box."""
        return geometry.box_corners(self.center, self.size, self.rotation)[[0, 1, 5, 4], :2]

    def to_json(self) -> dict:
        return {"class": self.class_name, "label": int(self.label),
                "center": [float(v) for v in self.center],
                "size": [float(v) for v in self.size],
                "rotation": [[float(v) + 0.0 for v in row] for row in self.rotation],
                "yaw": self.yaw}


@dataclass
class Scene:
    seed: int
    index: int
    size: tuple                 # (W, H)
    camera: np.ndarray          # (fx, fy, cx, cy)
    room: np.ndarray            # (Lx, Ly, Lz); the room is [0, Lx] x [0, Ly] x [0, Lz]
    objects: list
    poses: np.ndarray           # (F, 4, 4) T_world_camera
    style: dict                 # room textures
    lights: list
    ambient: np.ndarray         # linear RGB
    exposure: float
    sensor_noise: float
    screen_color: np.ndarray
    lattice: np.ndarray         # value-noise lattice for the textures
    meta: dict = field(default_factory=dict)
    _compiled: object = field(default=None, init=False, repr=False, compare=False)

    @property
    def K(self) -> np.ndarray:
        fx, fy, cx, cy = self.camera
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    def compiled(self) -> render.Compiled:
        if self._compiled is None:
            self._compiled = render.compile_objects(self.objects)
        return self._compiled

    def render(self, frame: int, noise: bool = True) -> render.View:
        rng = rng_for(self.seed, self.index, STREAM_NOISE, frame) if noise else None
        return render.render(self, self.poses[frame], noise_rng=rng)

    def boxes_json(self) -> dict:
        return {"format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1],
                "boxes": [o.to_json() for o in self.objects]}


# ----------------------------------------------------------------------------- camera path

def camera_path(rng, room, frames: int):
    """A smooth closed loop around the room's centre (an ellipse whose radius wobbles with the
    angle) walked at a constant step: positions (F, 3), yaw, tilt, roll (F,), the loop itself
    (M, 2) for the layout (it does not depend on F) and provenance."""
    Lx, Ly, _ = room
    centre = np.array([Lx, Ly]) / 2 + rng.uniform(-0.1, 0.1, 2)
    margin = rng.uniform(0.6, 0.9, 2)
    radii = np.maximum(np.array([Lx, Ly]) / 2 - margin, 0.75)
    lobes = int(rng.integers(2, 4))
    wobble, lobe_phase = rng.uniform(0, 0.08), rng.uniform(0, 2 * np.pi)
    theta = np.linspace(0, 2 * np.pi, 4097)
    radial = 1.0 + wobble * np.sin(lobes * theta + lobe_phase)
    loop = centre + radii * radial[:, None] * np.stack([np.cos(theta), np.sin(theta)], -1)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=-1))])
    perimeter = arc[-1]
    step = min(rng.uniform(0.06, 0.12), 0.16 * radii.min())
    direction = rng.choice([-1.0, 1.0])
    s = (rng.uniform(0, perimeter) + direction * step * np.arange(frames)) % perimeter
    xy = np.stack([np.interp(s, arc, loop[:, 0]), np.interp(s, arc, loop[:, 1])], -1)
    u = step * np.arange(frames)           # metres walked

    def wave(amplitude, period):
        return amplitude * np.sin(2 * np.pi * u / period + rng.uniform(0, 2 * np.pi))

    eye = rng.uniform(EYE[0] + 0.05, EYE[1] - 0.05) + wave(0.04, rng.uniform(1.5, 3.0))
    target = centre + np.stack([wave(rng.uniform(0, 0.5), rng.uniform(3, 6)),
                                wave(rng.uniform(0, 0.5), rng.uniform(3, 6))], -1)
    to = target - xy
    yaw = np.arctan2(to[:, 1], to[:, 0]) + wave(np.radians(rng.uniform(0, 25)),
                                               rng.uniform(3, 6))
    tilt = np.radians(np.clip(rng.uniform(15, 24) + wave(5.0, rng.uniform(2, 4)), *TILT_DEG))
    roll = np.radians(np.clip(wave(rng.uniform(0.5, 2.5), rng.uniform(1.5, 3))
                              + wave(0.5, rng.uniform(0.4, 0.8)), -ROLL_DEG, ROLL_DEG))
    position = np.concatenate([xy, eye[:, None]], -1)
    meta = {"centre": centre.tolist(), "radii": radii.tolist(), "lobes": lobes,
            "wobble": float(wobble), "step": float(step), "direction": float(direction)}
    walk = {"loop": loop, "arc": arc, "s": s, "centre": centre}
    return position, yaw, tilt, roll, walk, meta


AIM_DISTANCE = 1.8      # metres: furniture about this far away pulls the heading most
AIM_SMOOTH = 0.4        # metres of loop: the Gaussian that smooths the pull


def aim_offsets(walk: dict, objects: list) -> np.ndarray:
    """Heading corrections (F,) radians that turn the camera from the room's centre towards
    the furniture near it.  Computed along the whole closed loop (so frame i's correction does
    not depend on the frame count), smoothed along it, and read at each frame's arc position."""
    loop, arc, centre = walk["loop"][:-1:8], walk["arc"][:-1:8], walk["centre"]
    perimeter = walk["arc"][-1]
    inward = centre - loop
    inward /= np.linalg.norm(inward, axis=-1, keepdims=True)
    pull = 0.7 * inward
    for obj in objects:
        to = obj.center[:2] - loop
        d = np.linalg.norm(to, axis=-1)
        u = to / np.maximum(d, 1e-9)[:, None]
        ahead = 0.5 * (1 + np.einsum("ni,ni->n", u, inward))
        w = np.exp(-((d - AIM_DISTANCE) / 1.0) ** 2) * ahead
        pull += w[:, None] * u
    offset = np.arctan2(pull[:, 1], pull[:, 0]) - np.arctan2(inward[:, 1], inward[:, 0])
    # circular Gaussian smoothing along the loop, of unit vectors (angles wrap)
    dist = np.abs(arc[:, None] - arc[None, :])
    dist = np.minimum(dist, perimeter - dist)
    smoothed = np.angle(np.einsum("ij,j->i", np.exp(-0.5 * (dist / AIM_SMOOTH) ** 2),
                                  np.exp(1j * offset)))
    return np.interp(walk["s"], arc, smoothed, period=perimeter)


# ----------------------------------------------------------------------------- layout

def _sat_overlap(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """Whether two convex quads (4, 2) come closer than ``gap`` (separating-axis test)."""
    for poly in (a, b):
        for i in range(4):
            e = poly[(i + 1) % 4] - poly[i]
            n = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            pa, pb = a @ n, b @ n
            if pa.max() + gap < pb.min() or pb.max() + gap < pa.min():
                return False
    return True


def _point_quad_distance(points: np.ndarray, obj: SceneObject) -> np.ndarray:
    """Bird's-eye distances (n,) from points (n, 2) to an object's footprint."""
    x = obj.rotation[:2, 0] / np.linalg.norm(obj.rotation[:2, 0])
    z = np.array([x[1], -x[0]])
    rel = points - obj.center[:2]
    local = np.stack([rel @ x, rel @ z], -1)
    half = obj.size[[0, 2]] / 2
    out = np.maximum(np.abs(local) - half, 0)
    return np.linalg.norm(out, axis=-1)


CLASS_WEIGHTS = np.array([2.0, 1.5, 1.2, 1.2, 1.0, 1.0, 1.0, 0.6, 1.0])


def layout(rng, room, loop_xy) -> list:
    """4-10 objects on the floor (a display may stand on a table), no bird's-eye overlaps,
    at least CAMERA_CLEARANCE from the camera loop, inside the walls, mostly in the open
    middle of the room where the camera looks.  Classes are drawn first and placed largest
    first, so big furniture is not crowded out by small things."""
    Lx, Ly, _ = room
    n_max = int(np.clip(round(Lx * Ly / 2.5), 6, 10))
    target = int(rng.integers(4, n_max + 1))
    probs = CLASS_WEIGHTS / CLASS_WEIGHTS.sum()
    wanted = [shapes.CLASSES[int(i)] for i in rng.choice(len(probs), target, p=probs)]
    while len(wanted) < 16:     # spares, used when a wanted class does not fit
        wanted.append(str(rng.choice(["chair", "trash bin", "other", "chair"])))
    area = {c: np.prod(np.asarray(shapes.MEAN_SIZES.get(c, (0.65, 0.65, 0.65)))[[0, 2]])
            for c in shapes.CLASSES}
    first = sorted(wanted[:target], key=lambda c: -area[c])
    floor_objects: list = []
    stacked: list = []          # (display, table)
    lo, hi = loop_xy.min(0), loop_xy.max(0)
    for cls in first + wanted[target:]:
        if len(floor_objects) + len(stacked) >= target:
            break
        for _ in range(60):
            obj, table = _try_place(rng, cls, room, loop_xy, lo, hi, floor_objects, stacked)
            if obj is not None:
                (stacked.append((obj, table)) if table is not None
                 else floor_objects.append(obj))
                break
    # boxes.json order: floor objects as placed, each table followed by what stands on it
    ordered = []
    for o in floor_objects:
        ordered.append(o)
        ordered += [d for d, t in stacked if t is o]
    return ordered


def _try_place(rng, cls, room, loop_xy, lo, hi, floor_objects, stacked):
    Lx, Ly, _ = room
    size = shapes.sample_size(rng, cls)
    prims = shapes.build(rng, cls, size)
    yaw = rng.uniform(-np.pi, np.pi)
    tables = [o for o in floor_objects if o.class_name == "table"]
    if cls == "display" and tables and rng.random() < 0.8:
        table = tables[int(rng.integers(len(tables)))]
        obj = _on_table(rng, prims, table)
        if obj is None or any(_sat_overlap(obj.footprint(), d.footprint(), 0.02)
                              for d, t in stacked if t is table):
            return None, None
        return obj, table
    if rng.random() < 0.75:
        xy = (lo + hi) / 2 + rng.uniform(-0.5, 0.5, 2) * (hi - lo)
    else:
        xy = rng.uniform([0, 0], [Lx, Ly])
    obj = SceneObject.place(cls, prims, xy, yaw)
    fp = obj.footprint()
    if (fp.min() < WALL_GAP or fp[:, 0].max() > Lx - WALL_GAP
            or fp[:, 1].max() > Ly - WALL_GAP):
        return None, None
    if _point_quad_distance(loop_xy, obj).min() < CAMERA_CLEARANCE:
        return None, None
    if any(_sat_overlap(fp, o.footprint(), OBJECT_GAP) for o in floor_objects):
        return None, None
    return obj, None


def _on_table(rng, prims, table: SceneObject):
    """The display standing on the table top, facing the table's +z or -z, fully on it."""
    yaw = table.yaw + (0.0 if rng.random() < 0.5 else np.pi) + rng.uniform(-0.3, 0.3)
    half_t = table.size[[0, 2]] / 2
    top = table.center[2] + table.size[1] / 2
    for _ in range(10):
        local = rng.uniform(-1, 1, 2) * np.maximum(half_t - 0.3, 0.0)
        xy = (table.center[:2] + local[0] * table.rotation[:2, 0]
              + local[1] * table.rotation[:2, 2])
        obj = SceneObject.place("display", prims, xy, yaw, base_height=top)
        rel = obj.footprint() - table.center[:2]
        if (np.all(np.abs(rel @ table.rotation[:2, 0]) <= half_t[0] - 0.02)
                and np.all(np.abs(rel @ table.rotation[:2, 2]) <= half_t[1] - 0.02)):
            return obj
    return None


# ----------------------------------------------------------------------------- style, light

def _kelvin_rgb(kelvin: float) -> np.ndarray:
    """Approximate linear RGB of black-body light (Tanner Helland's fit), max channel 1."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = (99.4708025861 * np.log(t) - 161.1195681661 if t <= 66
         else 288.1221695283 * (t - 60) ** -0.0755148492)
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * np.log(t - 10)
                               - 305.0447927307)
    rgb = np.clip(np.array([r, g, b]) / 255.0, 0, 1) ** 2.2
    return rgb / rgb.max()


def room_style(rng) -> dict:
    from .shapes import _hex, pick, vary
    floor_kind = str(rng.choice(["planks", "tiles", "carpet"], p=[0.45, 0.35, 0.2]))
    woods = _hex("b58a5a", "9c6b3e", "d4b48c", "6e4a2c", "c9a27a")
    tiles = _hex("e8e4dc", "b9b4aa", "8c8c8c", "d9cbb0", "3d3d3d", "a7b7c2")
    carpets = _hex("7d7468", "5a6470", "8a7a5a", "4a4a52", "9a8f80", "6b4f4f")
    paints = _hex("f0ece2", "e6e1d3", "d7dde2", "e8dcc8", "cfd8c8", "f2e6d8", "dcdcdc")
    accents = _hex("7a93a8", "a87a6a", "8aa07a", "c8b07a", "6a6a7a")
    if floor_kind == "planks":
        c = pick(rng, woods)
        floor = {"kind": "planks", "color": c, "color2": vary(rng, c, 0.02, 0.2, 0.25),
                 "plank_width": float(rng.uniform(0.1, 0.22)),
                 "plank_length": float(rng.uniform(0.8, 1.8))}
    elif floor_kind == "tiles":
        c = pick(rng, tiles)
        floor = {"kind": "tiles", "color": c, "color2": pick(rng, tiles),
                 "tile": float(rng.uniform(0.25, 0.6)), "grout": float(rng.uniform(0.004, 0.012)),
                 "checker": bool(rng.random() < 0.4),
                 "grout_color": vary(rng, (0.75, 0.74, 0.7), 0, 0, 0.3)}
    else:
        c = pick(rng, carpets)
        floor = {"kind": "carpet", "color": c, "color2": c}
    floor["axis"] = int(rng.integers(2))
    paint = pick(rng, paints, val=0.05)
    walls = {"kind": str(rng.choice(["paint", "stripes", "wainscot"], p=[0.5, 0.25, 0.25])),
             "color": paint, "color2": vary(rng, pick(rng, paints + accents), 0.03, 0.2, 0.15),
             "accent": pick(rng, accents + paints),
             "accent_faces": [int(f) for f in rng.choice(4, int(rng.random() < 0.3),
                                                          replace=False)],
             "stripe": float(rng.uniform(0.05, 0.2)),
             "wainscot": float(rng.uniform(0.8, 1.1)),
             "baseboard": float(rng.uniform(0.06, 0.12)),
             "baseboard_color": pick(rng, _hex("f4f4f0", "6e4a2c", "3a3a3a", "c8c0b0"))}
    ceiling = vary(rng, (0.95, 0.95, 0.93), 0.02, 0.3, 0.03)
    return {"floor": floor, "walls": walls, "ceiling": ceiling}


def lighting(rng, room) -> dict:
    Lx, Ly, Lz = room
    kelvin = float(rng.uniform(2700, 6500))
    ambient_level = float(rng.uniform(0.2, 0.4))
    lights = []
    lamp_k = float(np.clip(kelvin + rng.uniform(-500, 500), 2500, 7000))
    lights.append({"type": "point",
                   "position": [float(rng.uniform(0.3, 0.7) * Lx),
                                float(rng.uniform(0.3, 0.7) * Ly),
                                float(Lz - rng.uniform(0.1, 0.4))],
                   "kelvin": lamp_k, "intensity": float(rng.uniform(0.7, 1.3)),
                   "falloff": float(rng.uniform(2.0, 3.5))})
    if rng.random() < 0.6:
        az = rng.uniform(-np.pi, np.pi)
        el = np.radians(rng.uniform(25, 55))
        direction = [float(-np.cos(el) * np.cos(az)), float(-np.cos(el) * np.sin(az)),
                     float(-np.sin(el))]
        lights.append({"type": "directional", "direction": direction,
                       "kelvin": float(rng.uniform(4500, 7000)),
                       "intensity": float(rng.uniform(0.2, 0.5))})
    for light in lights:
        light["color"] = (_kelvin_rgb(light["kelvin"]) * light["intensity"]).tolist()
    return {"kelvin_ambient": kelvin, "ambient_level": ambient_level,
            "ambient": (_kelvin_rgb(kelvin) * ambient_level).tolist(), "lights": lights,
            "exposure": float(rng.uniform(0.9, 1.2)),
            "sensor_noise": float(rng.uniform(0.5, 2.0) / 255),
            "screen_color": (_kelvin_rgb(float(rng.uniform(5500, 9000))) * 0.9).tolist()}


# ----------------------------------------------------------------------------- the scene

def build_scene(seed: int, index: int = 0, frames: int = 60, size=(320, 240)) -> Scene:
    """The scene ``index`` of ``seed`` (geometry, lights, poses; nothing rendered)."""
    check_args(seed=seed, index=index, frames=frames, size=size)
    w, h = int(size[0]), int(size[1])
    lay = rng_for(seed, index, STREAM_LAYOUT)
    room = np.array([lay.uniform(*ROOM_XY), lay.uniform(*ROOM_XY), lay.uniform(*ROOM_Z)])
    cam_rng = rng_for(seed, index, STREAM_CAMERA)
    f_rel = cam_rng.uniform(0.9, 1.1)
    c_off = cam_rng.uniform(-0.01, 0.01, 2)
    camera = np.array([f_rel * w, f_rel * w, (w - 1) / 2 + c_off[0] * w,
                       (h - 1) / 2 + c_off[1] * h])
    # the layout keeps clear of the whole loop, so it does not depend on the frame count
    position, yaw, tilt, roll, walk, path_meta = camera_path(cam_rng, room, frames)
    loop = walk["loop"][::4]
    objects: list = []
    for attempt in range(50):   # a crowded small room may need another draw to fit 4
        placed = layout(rng_for(seed, index, STREAM_LAYOUT, 1 + attempt), room, loop)
        if len(placed) > len(objects):
            objects = placed
        if len(objects) >= MIN_OBJECTS:
            break
    yaw = yaw + aim_offsets(walk, objects)
    poses = np.stack([geometry.camera_pose(position[i], yaw[i], tilt[i], roll[i])
                      for i in range(frames)])
    style = room_style(rng_for(seed, index, STREAM_STYLE))
    style_rng = rng_for(seed, index, STREAM_STYLE, 1)
    lattice = style_rng.random((256, 256))
    light = lighting(rng_for(seed, index, STREAM_LIGHT), room)
    meta = {"path": path_meta, "lighting": light}
    return Scene(seed=int(seed), index=int(index), size=(w, h), camera=camera, room=room,
                 objects=objects, poses=poses, style=style,
                 lights=light["lights"], ambient=np.array(light["ambient"]),
                 exposure=light["exposure"], sensor_noise=light["sensor_noise"],
                 screen_color=np.array(light["screen_color"]), lattice=lattice, meta=meta)


MIN_SIZE, MAX_SIZE = 16, 4096


def check_args(seed=0, index=0, frames=1, size=(320, 240), scenes=1) -> None:
    def integer(v, name):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise ParqError(f"{name} must be an integer, got {v!r}")
        return int(v)
    if integer(seed, "seed") < 0:
        raise ParqError(f"seed must be >= 0, got {seed}")
    if integer(index, "scene index") < 0:
        raise ParqError(f"scene index must be >= 0, got {index}")
    if integer(frames, "frames") < 1:
        raise ParqError(f"frames must be >= 1, got {frames}")
    if integer(scenes, "scenes") < 1:
        raise ParqError(f"scenes must be >= 1, got {scenes}")
    try:
        w, h = size
    except (TypeError, ValueError):
        raise ParqError(f"size must be (width, height), got {size!r}") from None
    for v, name in ((w, "width"), (h, "height")):
        if not MIN_SIZE <= integer(v, name) <= MAX_SIZE:
            raise ParqError(f"{name} must be between {MIN_SIZE} and {MAX_SIZE} pixels, got {v}")
