"""parq_synth: the synthetic scene generator renders exact geometry and writes what it says.

The checks compare the renderer with independent computations: the runtime's projection of box
corners, a per-pixel scalar ray caster written here, and the primitives' surface equations.
"""
from __future__ import annotations

import dataclasses
import json
import os
import pathlib

import cv2
import numpy as np
import pytest

import parq_synth
from parq_runtime import geometry
from parq_runtime.errors import ParqError
from parq_synth import cli, render, scene as scene_mod, shapes, writer
from parq_synth.render import camera_rays
from parq_synth.scene import SceneObject, build_scene

TINY = (48, 36)


def _single_object_scene(prims, yaw=0.4, xy=(2.5, 2.0), cam=(1.5, -0.6, 1.4), roll=2.0,
                         size=(96, 72), base=0.0, class_name="other"):
    """One object in an otherwise empty room, seen from ``cam`` (offset from the object)
    looking at its centre."""
    base_scene = build_scene(0, 0, frames=1, size=size)
    obj = SceneObject.place(class_name, prims, xy, yaw, base_height=base)
    position = np.array([xy[0] + cam[0], xy[1] + cam[1], cam[2]])
    to = obj.center - position
    tilt = np.arctan2(-to[2], np.hypot(to[0], to[1]))
    pose = geometry.camera_pose(position, np.arctan2(to[1], to[0]), tilt, np.radians(roll))
    return dataclasses.replace(base_scene, room=np.array([5.0, 4.0, 2.8]), objects=[obj],
                               poses=pose[None])


def _camera_points(scene, points_world, frame=0):
    T_cw = geometry.invert(scene.poses[frame])
    return geometry.transform(T_cw, np.asarray(points_world))


def _pixel_grid(size):
    w, h = size
    v, u = np.mgrid[0:h, 0:w]
    return u, v


def _signed_distance_to_hull(u, v, hull_uv):
    """Signed distance (pixels) of pixel centres to a convex polygon's boundary, > 0 inside."""
    from scipy.spatial import ConvexHull
    hull = ConvexHull(hull_uv)
    # hull.equations: a u + b v + c <= 0 inside, (a, b) unit
    eq = hull.equations
    d = u[..., None] * eq[:, 0] + v[..., None] * eq[:, 1] + eq[:, 2]
    return -d.max(-1)


# ----------------------------------------------------------------------------- rendering

def test_a_box_covers_exactly_the_pixels_inside_its_projected_hull():
    size = np.array([0.6, 0.4, 0.5])
    scene = _single_object_scene([shapes.box_prim(-size / 2, size / 2, (0.8, 0.2, 0.2))])
    obj = scene.objects[0]
    np.testing.assert_allclose(obj.size, size)
    view = scene.render(0, noise=False)
    mask = view.instance == 0
    corners = geometry.box_corners(obj.center, obj.size, obj.rotation)
    uv, valid = geometry.project(_camera_points(scene, corners), scene.camera, scene.size)
    assert valid.all(), "the whole box should be in view"
    # bounding rectangle of the mask == pixel centres spanned by the projected corners, +-1 px
    rows, cols = np.nonzero(mask)
    assert abs(cols.min() - np.ceil(uv[:, 0].min())) <= 1
    assert abs(cols.max() - np.floor(uv[:, 0].max())) <= 1
    assert abs(rows.min() - np.ceil(uv[:, 1].min())) <= 1
    assert abs(rows.max() - np.floor(uv[:, 1].max())) <= 1
    # and pixel by pixel: inside the hull <=> on the object (away from the boundary)
    u, v = _pixel_grid(scene.size)
    sd = _signed_distance_to_hull(u, v, uv)
    assert mask[sd > 1e-3].all()
    assert not mask[sd < -1e-3].any()
    assert mask.sum() > 300


def test_the_pixel_at_a_face_centre_shows_that_face_at_the_analytic_depth():
    size = np.array([0.7, 0.5, 0.4])
    scene = _single_object_scene([shapes.box_prim(-size / 2, size / 2, (0.2, 0.6, 0.3))],
                                 yaw=-0.7, cam=(-1.3, 0.9, 1.6))
    obj = scene.objects[0]
    view = scene.render(0, noise=False)
    T = scene.poses[0]
    origin = T[:3, 3]
    seen = 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n_obj = np.zeros(3)
            n_obj[axis] = sign
            n_world = obj.rotation @ n_obj
            face_centre = obj.center + n_world * obj.size[axis] / 2
            if n_world @ (origin - face_centre) <= 0.05:      # back-facing or grazing
                continue
            uv, valid = geometry.project(_camera_points(scene, face_centre[None]),
                                         scene.camera, scene.size)
            assert valid[0]
            u, v = np.rint(uv[0]).astype(int)
            assert view.instance[v, u] == 0
            np.testing.assert_allclose(view.normal[v, u], n_world, atol=1e-9)
            # depth == camera z of the ray-plane intersection for that pixel centre
            d_cam = camera_rays(scene.camera, scene.size)[v, u]
            d_world = T[:3, :3] @ d_cam
            t = n_world @ (face_centre - origin) / (n_world @ d_world)
            assert view.depth[v, u] == pytest.approx(t, abs=1e-9)
            point = origin + t * d_world
            assert _camera_points(scene, point[None])[0, 2] == pytest.approx(view.depth[v, u],
                                                                              abs=1e-9)
            seen += 1
    assert seen >= 2
    assert (view.instance == -1).any()


def test_an_elliptic_cylinder_silhouette_and_depth_match_the_analytic_surface():
    a, b, h = 0.3, 0.18, 0.5
    scene = _single_object_scene([shapes.cylinder_prim((-a, -h / 2, -b), (a, h / 2, b),
                                                       (0.2, 0.3, 0.8))], yaw=0.9)
    obj = scene.objects[0]
    view = scene.render(0, noise=False)
    T = scene.poses[0]
    mask = view.instance == 0
    assert mask.sum() > 200
    p = view.points.reshape(-1, 3)[mask.ravel()]
    local = (p - obj.center) @ obj.rotation
    radial = (local[:, 0] / a) ** 2 + (local[:, 2] / b) ** 2
    on_side = np.abs(radial - 1) < 1e-9
    on_cap = np.abs(np.abs(local[:, 1]) - h / 2) < 1e-9
    assert (on_side | on_cap).all()
    assert (radial <= 1 + 1e-9).all() and (np.abs(local[:, 1]) <= h / 2 + 1e-9).all()
    assert on_side.sum() > 50 and on_cap.sum() > 20     # seen from above: top cap and side
    # every ray through the ellipse's projected centre line hits; rays far outside miss
    corners = geometry.box_corners(obj.center, obj.size, obj.rotation)
    uv, _ = geometry.project(_camera_points(scene, corners), scene.camera, scene.size)
    u, v = _pixel_grid(scene.size)
    sd = _signed_distance_to_hull(u, v, uv)
    assert not mask[sd < -1e-3].any()                  # never outside the box's hull
    del T


def _hit_primitive(prim, ol, dl):
    """Scalar reference: nearest t > 0 where the ray ol + t dl (object frame) enters a
    primitive, inf if it misses."""
    if prim.kind == shapes.BOX:
        t0, t1 = -np.inf, np.inf
        for k in range(3):
            if dl[k] == 0:
                if not prim.lo[k] <= ol[k] <= prim.hi[k]:
                    return np.inf
                continue
            a_, b_ = (prim.lo[k] - ol[k]) / dl[k], (prim.hi[k] - ol[k]) / dl[k]
            t0, t1 = max(t0, min(a_, b_)), min(t1, max(a_, b_))
        return t0 if t0 <= t1 and t0 > 0 else np.inf
    c = (prim.lo + prim.hi) / 2
    s = (prim.hi - prim.lo) / 2
    ts = []
    # side: ((x - cx) / a)^2 + ((z - cz) / b)^2 = 1 with |y - cy| <= h
    A = (dl[0] / s[0]) ** 2 + (dl[2] / s[2]) ** 2
    B = 2 * ((ol[0] - c[0]) * dl[0] / s[0] ** 2 + (ol[2] - c[2]) * dl[2] / s[2] ** 2)
    C = ((ol[0] - c[0]) / s[0]) ** 2 + ((ol[2] - c[2]) / s[2]) ** 2 - 1
    disc = B * B - 4 * A * C
    if A > 0 and disc >= 0:
        for t in ((-B - np.sqrt(disc)) / (2 * A), (-B + np.sqrt(disc)) / (2 * A)):
            if t > 0 and abs(ol[1] + t * dl[1] - c[1]) <= s[1]:
                ts.append(t)
    # caps
    if dl[1] != 0:
        for y in (c[1] - s[1], c[1] + s[1]):
            t = (y - ol[1]) / dl[1]
            q = ol + t * dl
            if t > 0 and ((q[0] - c[0]) / s[0]) ** 2 + ((q[2] - c[2]) / s[2]) ** 2 <= 1:
                ts.append(t)
    return min(ts) if ts else np.inf


def _first_object_hit(scene, o, d):
    best, best_obj = np.inf, -1
    for j, obj in enumerate(scene.objects):
        ol = obj.rotation.T @ (o - obj.center)
        dl = obj.rotation.T @ d
        for prim in obj.primitives:
            t = _hit_primitive(prim, ol, dl)
            if t < best:
                best, best_obj = t, j
    return best, best_obj


def _brute_force(scene, pixels, frame=0):
    """Scalar reference ray caster: (depth, object index or -1) of pixel centres."""
    fx, fy, cx, cy = scene.camera
    T = scene.poses[frame]
    o = T[:3, 3]
    out = []
    for u, v in pixels:
        d = T[:3, :3] @ np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        # room: leave the box [0, L]
        room = min(((scene.room[k] if d[k] > 0 else 0.0) - o[k]) / d[k]
                   for k in range(3) if d[k] != 0)
        t, j = _first_object_hit(scene, o, d)
        out.append((t, j) if t < room else (room, -1))
    return out


def test_shadow_rays_agree_with_a_scalar_segment_test():
    scene = build_scene(3, 0, frames=30, size=(48, 36))
    comp = scene.compiled()
    rng = np.random.default_rng(1)
    points, normals = [], []
    for frame in (0, 15, 29):
        view = scene.render(frame, noise=False)
        pick = rng.choice(48 * 36, 120, replace=False)
        points.append(view.points.reshape(-1, 3)[pick])
        normals.append(view.normal.reshape(-1, 3)[pick])
    p = np.concatenate(points) + np.concatenate(normals) * render.SHADOW_OFFSET
    lamp = np.array([scene.room[0] * 0.4, scene.room[1] * 0.6, 1.2])   # low: long shadows
    to = lamp - p
    dist = np.linalg.norm(to, axis=-1)
    dirs = to / dist[:, None]
    sun = np.array([0.5, -0.4, 0.5]) / np.linalg.norm([0.5, -0.4, 0.5])
    for got, seg_dirs, seg_len in (
            (render.occluded(comp, p, dirs, dist, light_position=lamp), dirs, dist),
            (render.occluded(comp, p, sun, np.inf), np.broadcast_to(sun, p.shape),
             np.full(len(p), np.inf))):
        want = np.array([_first_object_hit(scene, p[i], seg_dirs[i])[0] < seg_len[i]
                         for i in range(len(p))])
        np.testing.assert_array_equal(got, want)
        assert 10 < want.sum() < len(p) - 10


def test_rendered_depth_and_ids_equal_a_scalar_reference_ray_caster():
    scene = build_scene(3, 0, frames=30, size=(64, 48))
    rng = np.random.default_rng(0)
    for frame in (0, 12, 29):
        view = scene.render(frame, noise=False)
        on_obj = np.argwhere(view.instance >= 0)
        picks = [tuple(p[::-1]) for p in on_obj[rng.choice(len(on_obj), min(40, len(on_obj)),
                                                           replace=False)]] if len(on_obj) else []
        picks += [tuple(rng.integers([0, 0], scene.size)) for _ in range(20)]
        for (u, v), (t, j) in zip(picks, _brute_force(scene, picks, frame)):
            assert view.depth[v, u] == pytest.approx(t, abs=1e-9, rel=1e-12), (frame, u, v)
            assert view.instance[v, u] == j, (frame, u, v)


def _surface_distance(prim, p):
    """Distance-like residual (metres) of object-frame points p (n, 3) from a primitive's
    surface: 0 on the surface."""
    c, s = (prim.lo + prim.hi) / 2, (prim.hi - prim.lo) / 2
    q = p - c
    if prim.kind == shapes.BOX:
        return np.max(np.abs(q) - s, -1)
    r = np.sqrt((q[:, 0] / s[0]) ** 2 + (q[:, 2] / s[2]) ** 2)
    return np.maximum((r - 1) * min(s[0], s[2]), np.abs(q[:, 1]) - s[1])


def test_depth_pixels_back_project_onto_the_primitives_and_into_the_gt_boxes(tmp_path):
    out = tmp_path / "scene"
    scene = parq_synth.generate_scene(out, 11, frames=6, size=(64, 48))
    boxes = json.loads((out / "boxes.json").read_text())["boxes"]
    comp = scene.compiled()
    K = np.loadtxt(out / "intrinsic" / "intrinsic_depth.txt")[:3, :3]
    checked = 0
    for frame in range(6):
        T = np.loadtxt(out / "pose" / f"{frame}.txt")
        depth_mm = cv2.imread(str(out / "depth" / f"{frame}.png"), cv2.IMREAD_UNCHANGED)
        assert depth_mm.dtype == np.uint16 and depth_mm.shape == (48, 64)
        instance = cv2.imread(str(out / "instance" / f"{frame}.png"), cv2.IMREAD_UNCHANGED)
        view = scene.render(frame, noise=False)
        np.testing.assert_array_equal(depth_mm, np.rint(view.depth * 1000).astype(np.uint16))
        np.testing.assert_array_equal(instance.astype(int) - 1, view.instance)
        v, u = np.nonzero(instance > 0)
        if len(u) == 0:
            continue
        for z, what, tol in ((depth_mm[v, u] / 1000.0, "png", 2e-3),
                             (view.depth[v, u], "float", 1e-9)):
            rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1],
                             np.ones(len(u))], -1)
            world = geometry.transform(T, rays * z[:, None])
            for j, box in enumerate(boxes):
                sel = instance[v, u] == j + 1
                if not sel.any():
                    continue
                R, c = np.array(box["rotation"]), np.array(box["center"])
                local = (world[sel] - c) @ R
                assert (np.abs(local) <= np.array(box["size"]) / 2 + tol).all(), (what, j)
                gid = view.hit[v[sel], u[sel]]
                for g in np.unique(gid):
                    prim = scene.objects[j].primitives[g - comp.obj.tolist().index(j)]
                    res = _surface_distance(prim, local[gid == g])
                    # png depth: 1 mm steps along z, more along the surface at grazing angles
                    assert np.abs(res).max() < (tol if what == "float" else 6e-3), (what, j, g)
                checked += int(sel.sum())
    assert checked > 500


def test_room_pixels_lie_on_the_room_planes():
    scene = build_scene(4, 0, frames=3, size=TINY)
    view = scene.render(2, noise=False)
    room = view.instance < 0
    p = view.points.reshape(-1, 3)[room.ravel()]
    L = scene.room
    dist = np.minimum(np.abs(p), np.abs(p - L)).min(-1)
    assert dist.max() < 1e-9
    assert (p >= -1e-9).all() and (p <= L + 1e-9).all()


# ----------------------------------------------------------------------------- shapes, layout

@pytest.mark.parametrize("class_name", shapes.CLASSES)
def test_every_class_fills_its_box_exactly(class_name):
    for seed in range(15):
        rng = np.random.default_rng(seed)
        size = shapes.sample_size(rng, class_name)
        if class_name == "other":
            assert np.all((size >= 0.3) & (size <= 1.0))
        else:
            ratio = size / np.array(shapes.MEAN_SIZES[class_name])
            assert np.all((ratio >= 0.8) & (ratio <= 1.2))
        prims = shapes.build(rng, class_name, size)
        lo = np.min([p.lo for p in prims], 0)
        hi = np.max([p.hi for p in prims], 0)
        np.testing.assert_allclose(lo, -size / 2, atol=1e-12)
        np.testing.assert_allclose(hi, size / 2, atol=1e-12)
        assert all(np.all(p.hi > p.lo) for p in prims)
    assert len(prims) >= {"chair": 6, "table": 5, "cabinet": 3, "bookshelf": 6,
                          "sofa": 8, "bathtub": 5, "display": 4}.get(class_name, 1)


def _check_scene_layout(scene):
    L = scene.room
    assert 3.5 <= L[0] <= 7 and 3.5 <= L[1] <= 7 and 2.5 <= L[2] <= 3
    assert 4 <= len(scene.objects) <= 10
    floor = []
    for obj in scene.objects:
        corners = geometry.box_corners(obj.center, obj.size, obj.rotation)
        assert (corners[:, :2] > 0).all() and (corners[:, 0] < L[0]).all()
        assert (corners[:, 1] < L[1]).all()
        bottom = obj.center[2] - obj.size[1] / 2
        if abs(bottom) < 1e-9:
            floor.append(obj)
        else:     # only displays stand on something: a table's top
            assert obj.class_name == "display"
            assert any(t.class_name == "table"
                       and abs(t.center[2] + t.size[1] / 2 - bottom) < 1e-9
                       for t in scene.objects)
    for i, a in enumerate(floor):
        for b in floor[i + 1:]:
            assert not scene_mod._sat_overlap(a.footprint(), b.footprint(), 0.0)
    # the camera is never inside or right next to an object
    for obj in floor:
        assert scene_mod._point_quad_distance(scene.poses[:, :2, 3], obj).min() > 0.3


def test_layouts_are_valid_over_many_seeds():
    counts = {c: 0 for c in shapes.CLASSES}
    for seed in range(12):
        scene = build_scene(seed, 0, frames=60, size=TINY)
        _check_scene_layout(scene)
        for o in scene.objects:
            counts[o.class_name] += 1
    assert sum(v > 0 for v in counts.values()) >= 7


def test_camera_is_a_smooth_handheld_scan():
    for seed in range(5):
        scene = build_scene(seed, 0, frames=60, size=TINY)
        T = scene.poses
        geometry.check_rigid(T, tol=1e-9)
        eye = T[:, 2, 3]
        assert np.all((eye >= 1.3) & (eye <= 1.7))
        forward, right = T[:, :3, 2], T[:, :3, 0]
        tilt = np.degrees(np.arcsin(-forward[:, 2]))
        assert np.all((tilt >= 10 - 1e-9) & (tilt <= 30 + 1e-9))
        roll = np.degrees(np.arcsin(-right[:, 2]))      # right tips down = clockwise roll
        assert np.all(np.abs(roll) <= 3 + 1e-9)
        step = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=-1)
        assert np.all((step > 0.04) & (step < 0.15)), step
        cos = np.clip(np.einsum("ni,ni->n", forward[1:], forward[:-1]), -1, 1)
        assert np.degrees(np.arccos(cos)).max() < 15


def test_objects_are_seen_by_the_camera():
    scene = build_scene(2, 0, frames=60, size=(40, 30))
    pixels = np.zeros(len(scene.objects))
    for frame in range(0, 60, 3):
        view = scene.render(frame, noise=False)
        pixels += np.bincount(view.instance[view.instance >= 0].ravel(),
                              minlength=len(scene.objects))
    assert (pixels > 20).mean() >= 0.75, pixels


def test_boxes_json_records_what_the_capture_shows_of_each_object(tmp_path):
    """"visible": the frames whose instance mask holds the object and its most pixels in one,
    as the written masks count them; an object behind the camera is shown in no frame."""
    size = np.array([0.6, 0.4, 0.5])
    scene = _single_object_scene([shapes.box_prim(-size / 2, size / 2, (0.8, 0.2, 0.2))],
                                 size=(40, 30))
    shown = scene.objects[0]
    camera_xy = scene.poses[0][:2, 3]
    behind_xy = camera_xy + 0.6 * (camera_xy - shown.center[:2]) / np.linalg.norm(
        camera_xy - shown.center[:2])
    hidden = SceneObject.place("other", [shapes.box_prim(-size / 4, size / 4, (0.2, 0.8, 0.2))],
                               behind_xy, 0.0)
    frames = np.stack([scene.poses[0], scene.poses[0]])
    frames[1, :3, 3] += [0.0, 0.0, 0.05]                   # a second, slightly higher view
    scene = dataclasses.replace(scene, objects=[shown, hidden], poses=frames)
    writer.write_scene_files(scene, tmp_path)
    records = [b["visible"] for b in json.loads((tmp_path / "boxes.json").read_text())["boxes"]]
    masks = [cv2.imread(str(tmp_path / "instance" / f"{i}.png"), cv2.IMREAD_UNCHANGED)
             for i in range(2)]
    pixels = np.array([[(m == 1 + j).sum() for j in range(2)] for m in masks])
    assert records == [{"frames": int((pixels[:, j] > 0).sum()),
                        "max_pixels": int(pixels[:, j].max())} for j in range(2)]
    assert records[0]["frames"] == 2 and records[0]["max_pixels"] > 50
    assert records[1] == {"frames": 0, "max_pixels": 0}


# ----------------------------------------------------------------------------- determinism

def _json(scene):
    return json.dumps(scene.boxes_json())


def test_same_seed_same_scene_and_different_seeds_differ():
    a = build_scene(21, 3, frames=5, size=TINY)
    b = build_scene(21, 3, frames=5, size=TINY)
    assert _json(a) == _json(b)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.render(4).rgb, b.render(4).rgb)
    for other in (build_scene(22, 3, frames=5, size=TINY), build_scene(21, 4, frames=5,
                                                                       size=TINY)):
        assert _json(other) != _json(a)
        assert not np.allclose(other.poses, a.poses)
    # the frame count and the image size change neither the furniture nor the path
    longer = build_scene(21, 3, frames=9, size=(64, 48))
    assert _json(longer) == _json(a)
    np.testing.assert_array_equal(longer.poses[:5], a.poses)
    np.testing.assert_allclose(geometry.scale_camera(longer.camera, 48 / 64), a.camera)


def test_scene_k_is_reproducible_alone(tmp_path):
    parq_synth.generate(tmp_path / "all", 2, 5, frames=2, size=TINY)
    parq_synth.generate_scene(tmp_path / "alone", 5, frames=2, size=TINY, index=1)
    a, b = tmp_path / "all" / "scene_00001", tmp_path / "alone"
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    assert (tmp_path / "all" / "scene_00000" / "boxes.json").read_bytes() != \
        (a / "boxes.json").read_bytes()


def test_the_shipped_sample_scene_is_what_its_seed_generates_on_this_machine(tmp_path):
    """The same seed gives the same scene on any machine: the demo's sample scene
    (models/parq-demo/sample-scene, seed 4000, scene 0) was generated on another computer and
    committed; generated again here it has the same pixels (decoded, so that another zlib's
    PNG bytes do not count), poses, intrinsics, boxes and record."""
    sample = pathlib.Path(__file__).parent.parent / "models" / "parq-demo" / "sample-scene"
    record = json.loads((sample / "scene.json").read_text())
    here = tmp_path / "scene"
    parq_synth.generate_scene(here, record["seed"], frames=record["frames"],
                              size=(record["width"], record["height"]), index=record["index"])
    mine = json.loads((here / "scene.json").read_text())
    for r in (record, mine):
        r.pop("package_version")
    assert mine == record
    assert (here / "boxes.json").read_bytes() == (sample / "boxes.json").read_bytes()
    for folder in ("pose", "intrinsic"):
        names = sorted(p.name for p in (sample / folder).iterdir())
        assert names == sorted(p.name for p in (here / folder).iterdir())
        for name in names:
            assert (here / folder / name).read_bytes() == \
                (sample / folder / name).read_bytes(), f"{folder}/{name}"
    names = sorted(p.name for p in (sample / "color").iterdir())
    assert len(names) == record["frames"]
    assert names == sorted(p.name for p in (here / "color").iterdir())
    for name in names:
        np.testing.assert_array_equal(cv2.imread(str(here / "color" / name)),
                                      cv2.imread(str(sample / "color" / name)),
                                      err_msg=f"color/{name}")


# ----------------------------------------------------------------------------- files

def test_written_folder_has_the_documented_layout(tmp_path):
    results = parq_synth.generate(tmp_path, 1, 9, frames=3, size=(40, 30))
    assert [r[0] for r in results] == [0]
    d = tmp_path / "scene_00000"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene_00000"]   # no temp left
    for sub in ("color", "depth", "instance", "pose"):
        assert sorted(p.name for p in (d / sub).iterdir()) == sorted(
            f"{i}.{'txt' if sub == 'pose' else 'png'}" for i in range(3))
    for i in range(3):
        rgb = cv2.imread(str(d / "color" / f"{i}.png"), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (30, 40, 3) and rgb.dtype == np.uint8 and rgb.std() > 5
        depth = cv2.imread(str(d / "depth" / f"{i}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.shape == (30, 40) and depth.dtype == np.uint16
        assert depth.min() > 0 and depth.max() < 10000          # inside a <= 7 m room
        geometry.check_rigid(np.loadtxt(d / "pose" / f"{i}.txt"), tol=1e-12)
    info = json.loads((d / "scene.json").read_text())
    assert info["seed"] == 9 and info["index"] == 0 and info["frames"] == 3
    assert info["generator_version"] == parq_synth.GENERATOR_VERSION
    assert (info["width"], info["height"]) == (40, 30)
    for name in ("intrinsic_color", "intrinsic_depth"):
        M = np.loadtxt(d / "intrinsic" / f"{name}.txt")
        assert M.shape == (4, 4)
        np.testing.assert_array_equal(M[3], [0, 0, 0, 1])
        np.testing.assert_array_equal(M[:3, 3], [0, 0, 0])
        fx, fy, cx, cy = M[0, 0], M[1, 1], M[0, 2], M[1, 2]
        assert fx == fy and 0.9 * 40 <= fx <= 1.1 * 40
        assert abs(cx - 19.5) < 1 and abs(cy - 14.5) < 1
        np.testing.assert_array_equal(M[:3, :3], [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    boxes = json.loads((d / "boxes.json").read_text())
    assert {k: boxes[k] for k in ("format", "version", "frame", "up")} == {
        "format": "parq-onnx-boxes", "version": 1, "frame": "world", "up": [0, 0, 1]}
    assert 4 <= len(boxes["boxes"]) <= 10
    for b in boxes["boxes"]:
        R = np.array(b["rotation"])
        geometry.check_rigid(np.block([[R, np.zeros((3, 1))], [np.zeros((1, 3)), 1]]),
                             tol=1e-12)
        yaw = b["yaw"]
        np.testing.assert_allclose(R[:, 0], [np.cos(yaw), np.sin(yaw), 0], atol=1e-12)
        np.testing.assert_allclose(R[:, 1], [0, 0, 1], atol=1e-15)
        np.testing.assert_allclose(R[:, 2], np.cross(R[:, 0], R[:, 1]), atol=1e-12)
        assert yaw == pytest.approx(float(geometry.yaw(R)), abs=1e-12)
        assert b["class"] == shapes.CLASSES[b["label"]]
        assert len(b["center"]) == 3 and all(s > 0 for s in b["size"])


def test_a_failing_scene_leaves_nothing_behind(tmp_path, monkeypatch):
    def boom(scene, folder, timings=None):
        (folder / "color").mkdir()
        (folder / "color" / "0.png").write_bytes(b"partial")
        raise RuntimeError("disk on fire")
    monkeypatch.setattr(writer, "write_scene_files", boom)
    with pytest.raises(RuntimeError):
        parq_synth.generate(tmp_path, 1, 0, frames=1, size=TINY)
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_a_scene_atomically(tmp_path):
    parq_synth.generate_scene(tmp_path / "s", 1, frames=1, size=TINY)
    with pytest.raises(ParqError, match="already exists"):
        parq_synth.generate_scene(tmp_path / "s", 2, frames=1, size=TINY)
    parq_synth.generate_scene(tmp_path / "s", 2, frames=2, size=TINY, overwrite=True)
    assert json.loads((tmp_path / "s" / "scene.json").read_text())["seed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_skip_existing_writes_only_the_missing_scenes(tmp_path):
    """A cache of generated scenes: kept folders are not rewritten, missing ones are written
    exactly as a full run writes them."""
    parq_synth.generate(tmp_path / "full", 3, 7, frames=2, size=TINY)
    cache = tmp_path / "cache"
    parq_synth.generate(cache, 1, 7, frames=2, size=TINY, start=1)
    kept = (cache / "scene_00001" / "boxes.json").stat().st_mtime_ns
    written = parq_synth.generate(cache, 3, 7, frames=2, size=TINY, skip_existing=True)
    assert sorted(r[0] for r in written) == [0, 2]
    assert (cache / "scene_00001" / "boxes.json").stat().st_mtime_ns == kept
    for k in range(3):
        name = f"scene_{k:05d}"
        assert (cache / name / "boxes.json").read_bytes() == \
            (tmp_path / "full" / name / "boxes.json").read_bytes()
    assert parq_synth.generate(cache, 3, 7, frames=2, size=TINY, skip_existing=True) == []
    with pytest.raises(ParqError, match="exclude each other"):
        parq_synth.generate(cache, 3, 7, frames=2, size=TINY, skip_existing=True,
                            overwrite=True)


# ----------------------------------------------------------------------------- CLI

def test_cli_writes_scenes(tmp_path, capsys):
    assert cli.main([str(tmp_path), "--scenes", "2", "--seed", "3", "--start", "4",
                     "--frames", "2", "--width", "32", "--height", "24"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene_00004", "scene_00005"]
    assert "scene_00005" in capsys.readouterr().out
    a = json.loads((tmp_path / "scene_00005" / "boxes.json").read_text())
    visible = [b.pop("visible") for b in a["boxes"]]        # what the frames show: rendered
    assert all(0 <= v["frames"] <= 2 and v["max_pixels"] >= 0 for v in visible)
    assert a == build_scene(3, 5, frames=2, size=(32, 24)).boxes_json()


def test_cli_help_documents_every_flag(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    for flag in ("OUT", "--scenes", "--seed", "--start", "--frames", "--width", "--height",
                 "--overwrite", "--jobs", "--quiet"):
        assert flag in text
    parser = cli.build_parser()
    assert all(a.help for a in parser._actions)


@pytest.mark.parametrize("argv, message", [
    (["--scenes", "-1", "--seed", "0"], "argument --scenes: -1 must be at least 1"),
    (["--scenes", "1", "--seed", "-5"], "argument --seed: -5 must not be negative"),
    (["--scenes", "1", "--seed", "0", "--start", "-2"], "argument --start: -2 must not be"),
    (["--scenes", "1", "--seed", "0", "--frames", "0"], "argument --frames: 0 must be at least"),
    (["--scenes", "1", "--seed", "0", "--width", "8"], "argument --width: 8 must be at least 16"),
    (["--scenes", "1", "--seed", "0", "--height", "5000"],
     "argument --height: 5000 must be at most 4096"),
    (["--scenes", "1", "--seed", "0", "--jobs", "0"], "argument --jobs: 0 must be at least 1"),
    (["--scenes", "x", "--seed", "0"], "not an integer"),
    (["--seed", "0"], "--scenes"),
])
def test_cli_bad_arguments_are_one_line_errors(tmp_path, capsys, argv, message):
    try:
        rc = cli.main([str(tmp_path / "out")] + argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("parq-synth: error: ") and message in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_cli_unwritable_or_existing_output_is_an_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert cli.main([str(blocker / "out"), "--scenes", "1", "--seed", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("parq-synth: error: ") and "cannot create" in err
    assert cli.main([str(blocker), "--scenes", "1", "--seed", "0"]) == 2
    assert "not a folder" in capsys.readouterr().err
    if os.geteuid() != 0:          # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        assert cli.main([str(ro), "--scenes", "1", "--seed", "0"]) == 2
        assert "cannot write" in capsys.readouterr().err
    (tmp_path / "out" / "scene_00000").mkdir(parents=True)
    assert cli.main([str(tmp_path / "out"), "--scenes", "1", "--seed", "0", "--frames", "1",
                     "--width", "16", "--height", "16"]) == 2
    assert "already exists" in capsys.readouterr().err


def test_library_raises_parq_error_for_bad_arguments(tmp_path):
    with pytest.raises(ParqError):
        build_scene(-1)
    with pytest.raises(ParqError):
        build_scene(0, frames=0)
    with pytest.raises(ParqError):
        parq_synth.generate(tmp_path, 0, 0)
    with pytest.raises(ParqError):
        parq_synth.generate_scene(tmp_path / "s", 0, size=(10, 10))


@pytest.fixture
def no_scenes(monkeypatch):
    """Writing scenes fails the test: a bad argument must be refused before it."""
    def started(*args, **kwargs):
        raise AssertionError("parq-synth started work before refusing its arguments")

    monkeypatch.setattr(writer, "generate", started)


@pytest.mark.parametrize("argv, message", [
    (["out", "--scenes", "1", "--seed", "0", "--frames", "100000000000"],
     "argument --frames: 100000000000 must be at most 100000"),
    (["out", "--scenes", "100000000", "--seed", "0"],
     "argument --scenes: 100000000 must be at most 1000000"),
    (["out", "--scenes", "1", "--seed", "0", "--start", "1000000"],
     "argument --start: 1000000 must be at most 999999"),
    (["out", "--scenes", "1", "--seed", "0", "--jobs", "5000"],
     "argument --jobs: 5000 must be at most 1024"),
    (["", "--scenes", "1", "--seed", "0"], "argument OUT: the output folder name is empty"),
])
def test_cli_refuses_huge_counts_and_an_empty_out_before_creating_anything(
        tmp_path, capsys, monkeypatch, no_scenes, argv, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2
    assert err.startswith("parq-synth: error: ") and message in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("failure", [ParqError("the scene failed"), MemoryError()])
def test_cli_run_that_writes_no_scene_leaves_no_folder(tmp_path, capsys, monkeypatch, failure):
    """OUT (and the missing folders above it) is created to write the first scene; when the
    run fails before any scene is whole they are removed again, whatever the failure.  An OUT
    that was there before stays."""
    def fail(*args, **kwargs):
        raise failure

    def run(out):
        try:
            return cli.main([str(out), "--scenes", "2", "--seed", "0", "--frames", "1",
                             "--width", "16", "--height", "16"])
        except MemoryError:
            return "MemoryError"

    monkeypatch.setattr(writer, "build_scene", fail)
    expected = 2 if isinstance(failure, ParqError) else "MemoryError"
    assert run(tmp_path / "a" / "b" / "out") == expected
    assert not any(tmp_path.iterdir())
    (tmp_path / "kept").mkdir()
    assert run(tmp_path / "kept") == expected
    assert [p.name for p in tmp_path.iterdir()] == ["kept"]
    if isinstance(failure, ParqError):
        assert capsys.readouterr().err == "parq-synth: error: the scene failed\n" * 2


def test_cli_output_folder_it_cannot_create_leaves_no_parent_folder(tmp_path, capsys):
    (tmp_path / "kept").mkdir()
    for out in (tmp_path / "q" / ("a" * 300), tmp_path / "kept" / "r" / ("a" * 300) / "s"):
        assert cli.main([str(out), "--scenes", "1", "--seed", "0"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("parq-synth: error: ") and err.count("\n") == 1
        assert "cannot create the output folder" in err
    assert [p.name for p in tmp_path.iterdir()] == ["kept"]
    assert not any((tmp_path / "kept").iterdir())
