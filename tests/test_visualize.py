"""--vis and --ply: projections where geometry puts them, clipping behind the camera, a PLY
that parses back, and outputs that are complete or absent."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from parq_runtime import geometry, ply, visualize
from parq_runtime.boxes import Box
from parq_runtime.errors import ParqError
from parq_runtime.readers import Capture, Frame

# A level camera at the origin of a z-up world looking along +y.
T_LOOK_Y = np.eye(4)
T_LOOK_Y[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
K = np.array([[100.0, 0, 64], [0, 100, 48], [0, 0, 1]])
SIZE = (128, 96)


def box(center, size, label=0, name="chair", score=0.9, R=np.eye(3)):
    center, size = np.asarray(center, float), np.asarray(size, float)
    return Box(center, size, R, float(geometry.yaw(R)), label, name, score,
               geometry.box_corners(center, size, R))


def test_projection_of_a_known_box():
    b = box([0, 4, 0], [1, 1, 1])
    segments = visualize.box_segments(b.corners, T_LOOK_Y, K, SIZE)
    assert len(segments) == 12                        # all in front, all inside the image
    ends = np.array([p for _, p, q in segments] + [q for _, p, q in segments])
    # near face (y = 3.5) corner (0.5, 3.5, 0.5): x_cam 0.5, y_cam -0.5, z_cam 3.5
    near = [64 + 100 * 0.5 / 3.5, 48 - 100 * 0.5 / 3.5]
    far = [64 - 100 * 0.5 / 4.5, 48 + 100 * 0.5 / 4.5]
    for expected in (near, far):
        assert np.min(np.linalg.norm(ends - expected, axis=1)) < 1e-9
    # u and v ranges are the near face's
    np.testing.assert_allclose(ends.min(0), [64 - 100 / 7, 48 - 100 / 7])
    np.testing.assert_allclose(ends.max(0), [64 + 100 / 7, 48 + 100 / 7])


def test_edges_behind_the_camera_are_clipped_not_flipped():
    # a thin box from 1 m behind the camera to 3 m in front, 0.5 m to the right
    b = box([0.5, 1.0, 0], [0.01, 4.0, 0.01])
    segments = visualize.box_segments(b.corners, T_LOOK_Y, K, SIZE)
    # visible: the 4 edges along the box (object y: 1, 3, 5, 7) and the far end (2, 6, 10, 11)
    assert sorted(e for e, _, _ in segments) == [1, 2, 3, 5, 6, 7, 10, 11]
    for _, p, q in segments:
        for pt in (p, q):
            assert 0 <= pt[0] <= SIZE[0] - 1 and 0 <= pt[1] <= SIZE[1] - 1
            # the visible part starts at the far end (u ~ 80.7) and runs right, to the
            # border; a naive projection of the corner behind would land left, at u ~ 14
            assert pt[0] > 79
    us = [pt[0] for e, p, q in segments for pt in (p, q) if e in (1, 3, 5, 7)]
    assert max(us) == pytest.approx(SIZE[0] - 1)
    # entirely behind: nothing
    assert visualize.box_segments(box([0, -3, 0], [1, 1, 1]).corners, T_LOOK_Y, K, SIZE) == []


def test_clip_helpers():
    a, b = np.array([0.0, 0, -1]), np.array([0.0, 0, 1])
    p, q = visualize.clip_near(a, b, 0.05)
    np.testing.assert_allclose(p, [0, 0, 0.05])
    assert visualize.clip_near(-b, a, 0.05) is None
    p, q = visualize.clip_rect([-10, 5], [20, 5], 11, 11)
    np.testing.assert_allclose([p, q], [[0, 5], [10, 5]])
    assert visualize.clip_rect([-10, -5], [-1, -20], 11, 11) is None


def test_draw_puts_colour_on_the_box():
    image = np.zeros((96, 128, 3), np.uint8)
    b = box([0, 4, 0], [1, 1, 1], label=1)
    out = visualize.draw(image, K, T_LOOK_Y, [b], [box([0, 4, 0], [1.5, 1.5, 1.5])], "h")
    assert image.max() == 0                           # the input is not drawn on
    u, v = int(round(64 + 100 / 7)), 60              # on the right edge of the near face
    patch = out[v - 1:v + 2, u - 1:u + 2].reshape(-1, 3)
    assert any(np.abs(px.astype(int) - ply.class_color(1)).max() < 60 for px in patch)


# ----------------------------------------------------------------------------- PLY

def parse_ply(text: str) -> dict:
    lines = text.splitlines()
    assert lines[0] == "ply" and lines[1] == "format ascii 1.0"
    end = lines.index("end_header")
    elements, order = {}, []
    for line in lines[2:end]:
        parts = line.split()
        if parts[0] == "element":
            elements[parts[1]] = {"count": int(parts[2]), "props": []}
            order.append(parts[1])
        elif parts[0] == "property":
            elements[order[-1]]["props"].append(parts[-1])
    rows = lines[end + 1:]
    out = {}
    for name in order:
        n = elements[name]["count"]
        block, rows = rows[:n], rows[n:]
        out[name] = [dict(zip(elements[name]["props"], map(float, r.split()))) for r in block]
    assert rows == []
    return out


def test_ply_parses_back():
    boxes = [box([0, 4, 0], [1, 2, 3], label=0),
             box([1, 2, 0.5], [0.5, 0.5, 0.5], label=3, name="trash bin",
                 R=geometry.camera_pose([0, 0, 0], 0.3)[:3, :3])]
    data = parse_ply(ply.ply_text(boxes))
    assert len(data["vertex"]) == 8 * len(boxes) and len(data["edge"]) == 12 * len(boxes)
    for i, b in enumerate(boxes):
        xyz = np.array([[v["x"], v["y"], v["z"]] for v in data["vertex"][8 * i:8 * i + 8]])
        np.testing.assert_allclose(xyz, b.corners, atol=1e-6)
        edges = {(int(e["vertex1"]), int(e["vertex2"])) for e in data["edge"][12 * i:12 * i + 12]}
        assert edges == {(8 * i + a, 8 * i + c) for a, c in geometry.BOX_EDGES}
        colours = {(v["red"], v["green"], v["blue"]) for v in data["vertex"][8 * i:8 * i + 8]}
        assert colours == {ply.class_color(b.label)}
    empty = parse_ply(ply.ply_text([]))
    assert empty == {"vertex": [], "edge": []}


def test_ply_write_is_atomic(tmp_path):
    path = tmp_path / "boxes.ply"
    ply.write(path, [box([0, 4, 0], [1, 1, 1])])
    assert parse_ply(path.read_text())["edge"]
    with pytest.raises(ParqError, match="does not exist"):
        ply.write(tmp_path / "no" / "boxes.ply", [])


# ----------------------------------------------------------------------------- --vis folders

def fake_result(tmp_path, broken=False):
    frames = []
    for i in range(3):
        path = tmp_path / "img" / f"{i}.png"
        path.parent.mkdir(exist_ok=True)
        Image.fromarray(np.full((96, 128, 3), 40 * i, np.uint8)).save(path)
        frames.append(Frame(str(i), path, T_LOOK_Y.copy(), K.copy()))
    if broken:
        frames[2].image_path.write_bytes(b"garbage")
    capture = Capture(tmp_path, "scannet", frames)
    boxes = [box([0, 4, 0], [1, 1, 1])]
    snippets = [SimpleNamespace(index=0, frames=["0", "1", "2"], boxes=boxes)]
    return SimpleNamespace(capture=capture, snippets=snippets,
                           fusion=SimpleNamespace(boxes=boxes))


def test_vis_folder_complete_or_absent(tmp_path):
    out = tmp_path / "vis"
    assert visualize.write(fake_result(tmp_path), out) == 3
    index = json.loads((out / "index.json").read_text())
    assert [i["file"] for i in index["images"]] == [
        "snippet0000_view0_0.png", "snippet0000_view1_1.png", "snippet0000_view2_2.png"]
    assert Image.open(out / index["images"][0]["file"]).size == (128, 96)
    # an earlier --vis output is replaced; a failure leaves the earlier one and no debris
    (out / "stale.png").write_bytes(b"x")
    with pytest.raises(ParqError, match="2.png"):
        visualize.write(fake_result(tmp_path, broken=True), out)
    assert (out / "stale.png").exists()
    visualize.write(fake_result(tmp_path), out)
    assert not (out / "stale.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img", "vis"]
    # a folder of someone else's files is never replaced
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "photo.jpg").write_bytes(b"x")
    with pytest.raises(ParqError, match="not an earlier --vis output"):
        visualize.check_output(mine)
    with pytest.raises(ParqError, match="does not exist"):
        visualize.check_output(tmp_path / "no" / "vis")
