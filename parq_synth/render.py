"""Exact ray casting of a synthetic room, vectorised numpy (float64).

Camera model (the runtime's): pinhole (fx, fy, cx, cy), pixel (u, v) centred at integer
coordinates, camera-frame ray direction ((u - cx) / fx, (v - cy) / fy, 1).  Because that
direction has z = 1, the ray parameter t of a hit *is* its camera-frame depth z.

Primary rays: the room is the inside of the box [0, Lx] x [0, Ly] x [0, Lz] (every ray leaves
it); each object is first culled by the screen rectangle of its projected box corners (all
pixels when a corner is behind the camera), then by a slab test against its oriented box, and
only the rays that pass are tested against its primitives, all primitives at once: slab tests
for boxes, the analytic elliptic-cylinder / slab intersection for cylinders.  The nearest hit
wins (a z-buffer); objects are visited front to back so later ones are culled by the buffer.

Shading: Lambertian, ambient + point / directional lights with hard shadows (shadow rays are
cast against the objects, not the room), procedural textures (render.TEXTURES), gamma 2.2,
optional Gaussian sensor noise.  No antialiasing: every pixel is its centre ray.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import shapes

EPS = 1e-7          # smallest hit distance along a ray (metres for unit directions)
SHADOW_OFFSET = 2e-4
ROOM_FACES = ("wall x=0", "wall x=Lx", "wall y=0", "wall y=Ly", "floor", "ceiling")


def _mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b for a long array of short vectors, without BLAS: its threads only contend for
    the cores on tiny inner dimensions like these (and make timings depend on the load)."""
    return np.einsum("...j,j->...", a, b) if b.ndim == 1 else np.einsum("...j,jk->...k", a, b)


def _safe_inv(d: np.ndarray) -> np.ndarray:
    tiny = 1e-300
    return 1.0 / np.where(np.abs(d) < tiny, np.where(d < 0, -tiny, tiny), d)


@dataclass
class Compiled:
    """Every object's primitives as arrays.  Per object j: R[j] = R_world_object, c[j] the box
    centre, half[j] its half extents, corners[j] (8, 3) world; boxes[j] = (lo, hi, gid) and
    cyls[j] = (center, semi, gid) in the object frame.  Per global primitive id g: kind,
    obj, center, half (object frame), albedo (linear RGB), material, emission."""

    R: np.ndarray
    c: np.ndarray
    half: np.ndarray
    corners: np.ndarray
    boxes: list
    cyls: list
    kind: np.ndarray
    obj: np.ndarray
    center: np.ndarray
    phalf: np.ndarray
    albedo: np.ndarray
    material: np.ndarray
    emission: np.ndarray


def srgb_to_linear(c):
    return np.asarray(c, dtype=np.float64) ** 2.2


def compile_objects(objects) -> Compiled:
    from parq_runtime.geometry import box_corners
    O = len(objects)
    R = np.array([o.rotation for o in objects]).reshape(O, 3, 3)
    c = np.array([o.center for o in objects]).reshape(O, 3)
    half = np.array([o.size for o in objects]).reshape(O, 3) / 2
    prims = [(j, p) for j, o in enumerate(objects) for p in o.primitives]
    boxes, cyls = [], []
    g = 0
    for j, o in enumerate(objects):
        ids = np.arange(g, g + len(o.primitives))
        g += len(o.primitives)
        kinds = np.array([p.kind for p in o.primitives], dtype=np.int64)
        lo = np.array([p.lo for p in o.primitives]).reshape(-1, 3)
        hi = np.array([p.hi for p in o.primitives]).reshape(-1, 3)
        b, y = kinds == shapes.BOX, kinds == shapes.CYLINDER
        boxes.append((lo[b], hi[b], ids[b]))
        cyls.append(((lo[y] + hi[y]) / 2, (hi[y] - lo[y]) / 2, ids[y]))
    lo = np.array([p.lo for _, p in prims]).reshape(-1, 3)
    hi = np.array([p.hi for _, p in prims]).reshape(-1, 3)
    return Compiled(
        R=R, c=c, half=half, corners=box_corners(c, 2 * half, R).reshape(O, 8, 3),
        boxes=boxes, cyls=cyls,
        kind=np.array([p.kind for _, p in prims], dtype=np.int64),
        obj=np.array([j for j, _ in prims], dtype=np.int64),
        center=(lo + hi) / 2, phalf=(hi - lo) / 2,
        albedo=srgb_to_linear(np.array([p.color for _, p in prims]).reshape(-1, 3)),
        material=np.array([p.material for _, p in prims], dtype=np.int64),
        emission=np.array([p.emission for _, p in prims], dtype=np.float64))


def camera_rays(camera, size) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions ((u - cx) / fx, (v - cy) / fy, 1)."""
    fx, fy, cx, cy = np.asarray(camera, dtype=np.float64)
    w, h = size
    d = np.empty((h, w, 3))
    d[..., 0] = ((np.arange(w) - cx) / fx)[None, :]
    d[..., 1] = ((np.arange(h) - cy) / fy)[:, None]
    d[..., 2] = 1.0
    return d


# ----------------------------------------------------------------------------- intersection

def room_hit(origin, d, room) -> tuple:
    """Exit distance t (n,) and face index (n,) (ROOM_FACES) of rays from inside the room."""
    L = np.asarray(room, dtype=np.float64)
    inv = _safe_inv(d)
    bound = np.where(d > 0, L, 0.0)
    t_axis = (bound - origin) * inv
    t_axis = np.where(np.abs(d) < 1e-300, np.inf, t_axis)
    k = np.argmin(t_axis, -1)
    t = np.take_along_axis(t_axis, k[..., None], -1)[..., 0]
    positive = np.take_along_axis(d, k[..., None], -1)[..., 0] > 0
    return t, 2 * k + positive


def _slab(o, inv, lo, hi):
    """Entry and exit t of rays o + t d (inv = 1/d) through axis-aligned boxes lo..hi; every
    argument is a list of three per-axis arrays broadcastable together."""
    tn = tf = None
    for k in range(3):
        a = (lo[k] - o[k]) * inv[k]
        b = (hi[k] - o[k]) * inv[k]
        mn, mx = np.minimum(a, b), np.maximum(a, b)
        tn = mn if tn is None else np.maximum(tn, mn)
        tf = mx if tf is None else np.minimum(tf, mx)
    return tn, tf


def _boxes_single_origin(o, inv, lo, hi):
    """Nearest entry t (m, P) of rays o + t d (o (3,), inv = 1/d (m, 3)) into boxes lo..hi
    (P, 3); inf where missed."""
    tn, tf = _slab([o[k] for k in range(3)], [inv[:, k, None] for k in range(3)],
                   [lo[None, :, k] for k in range(3)], [hi[None, :, k] for k in range(3)])
    return np.where((tf >= tn) & (tn > EPS), tn, np.inf)


def _cylinders_single_origin(o, d, inv, center, semi):
    """Nearest entry t (m, Q) into elliptic cylinders (axis y) inscribed in center +- semi."""
    ox = (o[0] - center[:, 0]) / semi[:, 0]
    oz = (o[2] - center[:, 2]) / semi[:, 2]
    dx = d[:, None, 0] / semi[None, :, 0]
    dz = d[:, None, 2] / semi[None, :, 2]
    return _cylinder_core(ox[None], oz[None], dx, dz,
                          (center[:, 1] - semi[:, 1] - o[1])[None] * inv[:, None, 1],
                          (center[:, 1] + semi[:, 1] - o[1])[None] * inv[:, None, 1])


def _cylinder_core(ox, oz, dx, dz, ty1, ty2):
    a = dx * dx + dz * dz
    hb = ox * dx + oz * dz
    c = ox * ox + oz * oz - 1.0
    disc = hb * hb - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    parallel = a < 1e-24
    with np.errstate(divide="ignore", invalid="ignore"):
        ts0 = np.where(parallel, np.where(c <= 0, -np.inf, np.inf), (-hb - sq) / a)
        ts1 = np.where(parallel, np.where(c <= 0, np.inf, -np.inf), (-hb + sq) / a)
    tn = np.maximum(ts0, np.minimum(ty1, ty2))
    tf = np.minimum(ts1, np.maximum(ty1, ty2))
    return np.where((disc >= 0) & (tf >= tn) & (tn > EPS), tn, np.inf)


def _nearest(parts):
    """parts: list of (t (m, P), gid (P,)) -> (t (m,), gid (m,)) of the nearest hit."""
    best_t, best_g = None, None
    for t, gid in parts:
        if t.shape[1] == 0:
            continue
        k = np.argmin(t, 1)
        tk = t[np.arange(len(t)), k]
        if best_t is None:
            best_t, best_g = tk, gid[k]
        else:
            closer = tk < best_t
            best_t = np.where(closer, tk, best_t)
            best_g = np.where(closer, gid[k], best_g)
    return best_t, best_g


def _screen_rect(corners_cam, camera, size):
    """Pixel rectangle (v0, v1, u0, u1), end exclusive, that holds every pixel whose centre ray
    can hit a convex body with these camera-frame corners; None if it cannot be seen."""
    w, h = size
    z = corners_cam[:, 2]
    if np.all(z <= 0):
        return None
    if np.any(z < 1e-3):
        return 0, h, 0, w
    fx, fy, cx, cy = camera
    u = corners_cam[:, 0] / z * fx + cx
    v = corners_cam[:, 1] / z * fy + cy
    u0, u1 = max(0, int(np.floor(u.min()))), min(w, int(np.floor(u.max())) + 2)
    v0, v1 = max(0, int(np.floor(v.min()))), min(h, int(np.floor(v.max())) + 2)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def cast_primary(comp: Compiled, room, T_world_camera, camera, size, rays_cam=None):
    """Nearest hits of every pixel's centre ray: depth (H, W) (camera z, metres) and hit id
    (H, W) int64: the global primitive id (>= 0) or -1 - room face index."""
    w, h = size
    R_wc, origin = T_world_camera[:3, :3], T_world_camera[:3, 3]
    if rays_cam is None:
        rays_cam = camera_rays(camera, size)
    d_world = _mm(rays_cam, R_wc.T)
    t_room, face = room_hit(origin, d_world, room)
    zbuf = t_room
    gbuf = -1 - face
    if len(comp.c) == 0:
        return zbuf, gbuf
    corners_cam = (comp.corners - origin) @ R_wc
    order = np.argsort(np.linalg.norm(comp.c - origin, axis=-1), kind="stable")
    for j in order:
        rect = _screen_rect(corners_cam[j], camera, size)
        if rect is None:
            continue
        v0, v1, u0, u1 = rect
        Rj = comp.R[j]
        dl = _mm(rays_cam[v0:v1, u0:u1], (Rj.T @ R_wc).T)
        inv = _safe_inv(dl)
        ol = (origin - comp.c[j]) @ Rj
        hj = comp.half[j]
        tn, tf = _slab(ol, [inv[..., k] for k in range(3)], -hj, hj)
        zs = zbuf[v0:v1, u0:u1]
        cand = (tf >= tn) & (tf > EPS) & (tn < zs)
        if not cand.any():
            continue
        rows, cols = np.nonzero(cand)
        dl, inv = dl[rows, cols], inv[rows, cols]
        lo, hi, gb = comp.boxes[j]
        cc, cs, gc = comp.cyls[j]
        parts = []
        if len(gb):
            parts.append((_boxes_single_origin(ol, inv, lo, hi), gb))
        if len(gc):
            parts.append((_cylinders_single_origin(ol, dl, inv, cc, cs), gc))
        t, g = _nearest(parts)
        upd = t < zs[rows, cols]
        rows, cols = rows[upd] + v0, cols[upd] + u0
        zbuf[rows, cols] = t[upd]
        gbuf[rows, cols] = g[upd]
    return zbuf, gbuf


def occluded(comp: Compiled, points, dirs, t_max, light_position=None) -> np.ndarray:
    """Whether segments points + t dirs, EPS < t < t_max (n,) (dirs unit, (n, 3) or (3,)) hit
    any object primitive.  With ``light_position`` (a point light: every segment ends there)
    or a single direction (a directional light), objects are first culled per point with their
    bounding spheres; exact tests follow."""
    n = len(points)
    occ = np.zeros(n, dtype=bool)
    if n == 0 or len(comp.c) == 0:
        return occ
    single_dir = np.ndim(dirs) == 1
    dirs = np.broadcast_to(dirs, points.shape)
    t_max = np.broadcast_to(t_max, (n,))
    radius = np.linalg.norm(comp.half, axis=-1)
    if light_position is not None:
        # the point is in the shadow cone of the sphere seen from the light
        L = np.asarray(light_position, dtype=np.float64)
        to_c = comp.c - L                                   # (O, 3)
        dc = np.linalg.norm(to_c, axis=-1)
        rel = points - L                                    # (n, 3)
        dp = np.linalg.norm(rel, axis=-1)
        cosang = _mm(rel, to_c.T) / np.maximum(dp[:, None] * dc[None], 1e-12)
        inside = dc <= radius
        cos_cone = np.sqrt(np.maximum(1 - (radius / np.maximum(dc, 1e-12)) ** 2, 0))
        maybe = ((cosang >= cos_cone[None] - 1e-9) & (dp[:, None] >= dc[None] - radius[None])
                 ) | inside[None]
    elif single_dir:
        l = dirs[0]
        along = _mm(points, l)                              # (n,)
        c_along = comp.c @ l                                # (O,)
        pc = _mm(points, comp.c.T)                          # (n, O)
        dist2 = ((points * points).sum(-1)[:, None] - 2 * pc + (comp.c * comp.c).sum(-1)[None]
                 - (along[:, None] - c_along[None]) ** 2)
        maybe = (dist2 <= radius[None] ** 2 + 1e-9) & (c_along[None] - along[:, None]
                                                         >= -radius[None])
    else:
        maybe = np.ones((n, len(comp.c)), dtype=bool)
    for j in range(len(comp.c)):
        idx = np.nonzero(maybe[:, j] & ~occ)[0]
        if len(idx) == 0:
            continue
        Rj, hj = comp.R[j], comp.half[j]
        ol = _mm(points[idx] - comp.c[j], Rj)
        dl = _mm(dirs[idx], Rj)
        inv = _safe_inv(dl)
        tm = t_max[idx]
        tn, tf = _slab([ol[:, k] for k in range(3)], [inv[:, k] for k in range(3)], -hj, hj)
        cand = (tf >= tn) & (tf > EPS) & (tn < tm)
        if not cand.any():
            continue
        idx, ol, dl, inv, tm = idx[cand], ol[cand], dl[cand], inv[cand], tm[cand]
        hit = np.zeros(len(idx), dtype=bool)
        lo, hi, gb = comp.boxes[j]
        if len(gb):
            tn, tf = _slab([ol[:, None, k] for k in range(3)], [inv[:, None, k] for k in range(3)],
                           [lo[None, :, k] for k in range(3)], [hi[None, :, k] for k in range(3)])
            hit |= np.any((tf >= tn) & (tn > EPS) & (tn < tm[:, None]), 1)
        cc, cs, gc = comp.cyls[j]
        if len(gc):
            ox = (ol[:, None, 0] - cc[None, :, 0]) / cs[None, :, 0]
            oz = (ol[:, None, 2] - cc[None, :, 2]) / cs[None, :, 2]
            dx = dl[:, None, 0] / cs[None, :, 0]
            dz = dl[:, None, 2] / cs[None, :, 2]
            ty1 = (cc[None, :, 1] - cs[None, :, 1] - ol[:, None, 1]) * inv[:, None, 1]
            ty2 = (cc[None, :, 1] + cs[None, :, 1] - ol[:, None, 1]) * inv[:, None, 1]
            t = _cylinder_core(ox, oz, dx, dz, ty1, ty2)
            hit |= np.any(t < tm[:, None], 1)
        occ[idx[hit]] = True
    return occ


# ----------------------------------------------------------------------------- normals

def object_normals(comp: Compiled, gid, p_world):
    """World normals (n, 3) and object-frame points (n, 3) of hits on primitives gid (n,)."""
    j = comp.obj[gid]
    R = comp.R[j]
    p_obj = np.einsum("nji,nj->ni", R, p_world - comp.c[j])
    q = (p_obj - comp.center[gid]) / comp.phalf[gid]
    n_obj = np.zeros_like(q)
    axis = np.argmax(np.abs(q), -1)
    rows = np.arange(len(q))
    n_obj[rows, axis] = np.sign(q[rows, axis])
    cyl = comp.kind[gid] == shapes.CYLINDER
    if cyl.any():
        qc = q[cyl]
        r = np.hypot(qc[:, 0], qc[:, 2])
        side = np.abs(r - 1) < np.abs(np.abs(qc[:, 1]) - 1)
        semi = comp.phalf[gid[cyl]]
        grad = np.stack([qc[:, 0] / semi[:, 0], np.zeros(len(qc)), qc[:, 2] / semi[:, 2]], -1)
        grad /= np.maximum(np.linalg.norm(grad, axis=-1, keepdims=True), 1e-12)
        cap = np.zeros_like(qc)
        cap[:, 1] = np.sign(qc[:, 1])
        n_obj[cyl] = np.where(side[:, None], grad, cap)
    return np.einsum("nij,nj->ni", R, n_obj), p_obj


ROOM_NORMALS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                        dtype=np.float64)


# ----------------------------------------------------------------------------- textures

def noise2(lattice, u, v):
    """Smooth value noise in [0, 1] from a periodic random lattice (N, N)."""
    N = lattice.shape[0]
    fu, fv = np.floor(u), np.floor(v)
    a, b = u - fu, v - fv
    a = a * a * (3 - 2 * a)
    b = b * b * (3 - 2 * b)
    i0 = fu.astype(np.int64) % N
    j0 = fv.astype(np.int64) % N
    i1, j1 = (i0 + 1) % N, (j0 + 1) % N
    top = lattice[i0, j0] * (1 - a) + lattice[i1, j0] * a
    bot = lattice[i0, j1] * (1 - a) + lattice[i1, j1] * a
    return top * (1 - b) + bot * b


def cell_value(lattice, i, j):
    """A random value in [0, 1) for integer cells (i, j)."""
    N = lattice.shape[0]
    return lattice[np.asarray(i, dtype=np.int64) % N, (np.asarray(j, dtype=np.int64) * 7 + 3) % N]


def _wood(lat, along, across, phase):
    warp = noise2(lat, along * 0.8 + phase * 31, across * 6 + phase * 17)
    rings = np.sin((across * 40 + warp * 5 + phase * 13) * 2) * 0.5 + 0.5
    fine = noise2(lat, along * 3 + phase * 5, across * 150)
    return 0.78 + 0.2 * rings ** 3 + 0.12 * fine


def _face_coords(p, normal_axis):
    """The two in-plane coordinates (n,), (n,) of points p (n, 3) on faces normal to axis."""
    a = np.where(normal_axis == 0, p[:, 1], p[:, 0])
    b = np.where(normal_axis == 2, p[:, 1], p[:, 2])
    return a, b


def object_albedo(comp: Compiled, lat, gid, p_obj, n_obj_axis):
    alb = comp.albedo[gid].copy()
    mat = comp.material[gid]
    phase = (gid * 0.6180339887) % 1.0
    rel = p_obj - comp.center[gid]
    a, b = _face_coords(rel, n_obj_axis)
    f = np.ones(len(gid))
    m = mat == shapes.WOOD
    if m.any():
        # grain runs along the primitive's longest axis
        ph = comp.phalf[gid[m]]
        long_axis = np.argmax(ph, -1)
        r = rel[m]
        along = r[np.arange(len(r)), long_axis]
        across = r.sum(-1) - along
        f[m] = _wood(lat, along, across, phase[m])
    m = mat == shapes.FABRIC
    if m.any():
        f[m] = 0.85 + 0.2 * noise2(lat, a[m] * 60 + phase[m] * 50, b[m] * 60) \
            + 0.1 * noise2(lat, a[m] * 7, b[m] * 7 + phase[m] * 50)
    m = (mat == shapes.PLAIN) | (mat == shapes.METAL)
    if m.any():
        f[m] = 0.94 + 0.1 * noise2(lat, a[m] * 9 + phase[m] * 40, b[m] * 9)
    return alb * f[:, None]


def room_albedo(room_style, lat, face, p):
    """Linear albedo (n, 3) of room pixels with faces (n,) at world points p (n, 3)."""
    out = np.empty((len(face), 3))
    floor = face == 4
    if floor.any():
        out[floor] = _floor(room_style["floor"], lat, p[floor])
    ceil = face == 5
    if ceil.any():
        q = p[ceil]
        out[ceil] = srgb_to_linear(room_style["ceiling"]) * (
            0.95 + 0.06 * noise2(lat, q[:, 0] * 4, q[:, 1] * 4))[:, None]
    wall = face < 4
    if wall.any():
        q, fw = p[wall], face[wall]
        s = np.where(fw < 2, q[:, 1], q[:, 0])     # horizontal coordinate along the wall
        out[wall] = _wall(room_style["walls"], lat, fw, s, q[:, 2])
    return out


def _floor(st, lat, p):
    x, y = p[:, 0], p[:, 1]
    if st["axis"] == 1:
        x, y = y, x
    c1, c2 = srgb_to_linear(st["color"]), srgb_to_linear(st["color2"])
    if st["kind"] == "planks":
        w, length = st["plank_width"], st["plank_length"]
        row = np.floor(y / w)
        shift = cell_value(lat, row, 11) * length
        col = np.floor((x + shift) / length)
        tone = cell_value(lat, row * 13 + col, 5)
        base = c1 * (1 - tone[:, None]) + c2 * tone[:, None]
        grain = _wood(lat, x, y * 0.3 + tone * 3, tone)
        fy = (y / w) % 1.0
        fx = ((x + shift) / length) % 1.0
        seam = (np.minimum(fy, 1 - fy) * w < 0.003) | (np.minimum(fx, 1 - fx) * length < 0.003)
        f = grain * np.where(seam, 0.55, 1.0)
        return base * f[:, None]
    if st["kind"] == "tiles":
        s, g = st["tile"], st["grout"]
        i, j = np.floor(x / s), np.floor(y / s)
        fx, fy = (x / s) % 1.0, (y / s) % 1.0
        grout = (np.minimum(fx, 1 - fx) * s < g / 2) | (np.minimum(fy, 1 - fy) * s < g / 2)
        checker = ((i + j) % 2 == 1) & st["checker"]
        base = np.where(checker[:, None], c2, c1)
        base = base * (0.93 + 0.1 * cell_value(lat, i * 5 + j, 9))[:, None]
        base = base * (0.96 + 0.06 * noise2(lat, x * 8, y * 8))[:, None]
        return np.where(grout[:, None], srgb_to_linear(st["grout_color"]), base)
    # carpet
    f = 0.8 + 0.25 * noise2(lat, x * 50, y * 50) + 0.1 * noise2(lat, x * 3, y * 3)
    return c1 * f[:, None]


def _wall(st, lat, face, s, z):
    c1 = srgb_to_linear(st["color"])
    c2 = srgb_to_linear(st["color2"])
    accent = np.isin(face, st["accent_faces"])
    base = np.where(accent[:, None], srgb_to_linear(st["accent"]), c1)
    if st["kind"] == "stripes":
        stripe = (np.floor(s / st["stripe"]) % 2 == 1)
        base = np.where(stripe[:, None], base * 0.85 + c2 * 0.15, base)
    elif st["kind"] == "wainscot":
        lower = z < st["wainscot"]
        rail = np.abs(z - st["wainscot"]) < 0.02
        base = np.where(lower[:, None], c2, base)
        base = np.where(rail[:, None], c2 * 0.7, base)
    base = base * (0.95 + 0.07 * noise2(lat, s * 6, z * 6))[:, None]
    board = z < st["baseboard"]
    return np.where(board[:, None], srgb_to_linear(st["baseboard_color"]), base)


# ----------------------------------------------------------------------------- render

@dataclass
class View:
    """One rendered frame: rgb uint8 (H, W, 3); depth (H, W) float64 camera z in metres;
    hit (H, W) int64 global primitive id or -1 - room face; instance (H, W) int64 object index
    or -1 for the room; normal (H, W, 3) world normals; points (H, W, 3) world hit points."""

    rgb: np.ndarray
    depth: np.ndarray
    hit: np.ndarray
    instance: np.ndarray
    normal: np.ndarray
    points: np.ndarray


def render(scene, T_world_camera, noise_rng=None, compiled=None, rays_cam=None) -> View:
    """Render ``scene`` (scene.Scene) from the camera-to-world pose (4, 4)."""
    comp = compiled if compiled is not None else scene.compiled()
    w, h = scene.size
    camera = np.asarray(scene.camera, dtype=np.float64)
    if rays_cam is None:
        rays_cam = camera_rays(camera, scene.size)
    T = np.asarray(T_world_camera, dtype=np.float64)
    depth, hit = cast_primary(comp, scene.room, T, camera, scene.size, rays_cam)
    origin = T[:3, 3]
    d_world = _mm(rays_cam, T[:3, :3].T)
    points = origin + depth[..., None] * d_world
    flat_hit = hit.reshape(-1)
    P = points.reshape(-1, 3)
    normal = np.empty_like(P)
    albedo = np.empty_like(P)
    emission = np.zeros(len(P))
    lat = scene.lattice
    on_room = flat_hit < 0
    face = -1 - flat_hit[on_room]
    normal[on_room] = ROOM_NORMALS[face]
    albedo[on_room] = room_albedo(scene.style, lat, face, P[on_room])
    on_obj = ~on_room
    instance = np.full(len(P), -1, dtype=np.int64)
    if on_obj.any():
        gid = flat_hit[on_obj]
        n_world, p_obj = object_normals(comp, gid, P[on_obj])
        normal[on_obj] = n_world
        R = comp.R[comp.obj[gid]]
        n_obj = np.einsum("nji,nj->ni", R, n_world)
        albedo[on_obj] = object_albedo(comp, lat, gid, p_obj, np.argmax(np.abs(n_obj), -1))
        emission[on_obj] = comp.emission[gid]
        instance[on_obj] = comp.obj[gid]
    light = shade(scene, comp, P, normal)
    rgb_lin = albedo * light * scene.exposure
    scr = emission > 0
    if scr.any():
        g = P[scr, 2]
        glow = np.asarray(scene.screen_color) * (0.8 + 0.2 * np.cos(g * 9.0))[:, None]
        rgb_lin[scr] += emission[scr, None] * glow
    # gamma 2.2 through a table (linear quantised to 1/16384: below a grey level)
    rgb = _GAMMA[np.rint(np.clip(rgb_lin, 0, 1) * (len(_GAMMA) - 1)).astype(np.intp)]
    if noise_rng is not None and scene.sensor_noise > 0:
        rgb = rgb + noise_rng.normal(0.0, scene.sensor_noise * 255, rgb.shape)
    rgb8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(h, w, 3)
    return View(rgb8, depth, hit, instance.reshape(h, w), normal.reshape(h, w, 3), points)


_GAMMA = np.linspace(0, 1, 16385) ** (1 / 2.2) * 255


def shade(scene, comp: Compiled, P, normal):
    """Irradiance (n, 3), linear RGB: ambient + unshadowed Lambertian lights."""
    E = np.broadcast_to(np.asarray(scene.ambient, dtype=np.float64), P.shape).copy()
    for light in scene.lights:
        if light["type"] == "point":
            to = np.asarray(light["position"]) - P
            dist = np.linalg.norm(to, axis=-1)
            ldir = to / np.maximum(dist, 1e-9)[:, None]
            att = 1.0 / (1.0 + (dist / light["falloff"]) ** 2)
        else:
            ldir = np.broadcast_to(-np.asarray(light["direction"], dtype=np.float64), P.shape)
            dist = np.full(len(P), np.inf)
            att = np.ones(len(P))
        cos = np.einsum("ni,ni->n", normal, ldir)
        lit = cos > 0
        if light.get("shadows", True) and len(comp.c) and lit.any():
            idx = np.nonzero(lit)[0]
            if light["type"] == "point":
                occ = occluded(comp, P[idx] + normal[idx] * SHADOW_OFFSET, ldir[idx],
                               dist[idx], light_position=light["position"])
            else:
                occ = occluded(comp, P[idx] + normal[idx] * SHADOW_OFFSET, ldir[0], np.inf)
            lit[idx[occ]] = False
        contrib = np.where(lit, cos * att, 0.0)
        E += contrib[:, None] * np.asarray(light["color"], dtype=np.float64)
    return E
