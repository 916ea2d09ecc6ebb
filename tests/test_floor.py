"""The floor found in the images (parq_runtime.floor) and its pull on scene boxes (fusion)."""
import dataclasses

import numpy as np
import pytest

from parq_runtime import floor, geometry, readers
from parq_runtime.boxes import Box
from parq_runtime.errors import ParqError
from parq_runtime.fusion import SceneFusion
from parq_synth.writer import generate_scene

# parq-synth's held-out scene 0 (seed 3000) has a tiled floor at z = 0 and a table at 0.41 m
SEED, INDEX = 3000, 0


@pytest.fixture(scope="module")
def synth_capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("floor") / "scene"
    generate_scene(folder, SEED, frames=30, size=(160, 120), index=INDEX)
    return readers.open_capture(folder)


def lifted(capture, dz):
    """The same capture in a world frame moved down by ``dz``: every camera ``dz`` higher,
    so the floor is at z = dz."""
    frames = []
    for f in capture.frames:
        T = f.cam_to_world.copy()
        T[2, 3] += dz
        frames.append(dataclasses.replace(f, cam_to_world=T))
    return dataclasses.replace(capture, frames=frames)


def test_the_sweep_finds_the_floor_and_a_tabletop_and_follows_the_world_frame(synth_capture):
    """The whole sweep lists the floor (z = 0, within 1 cm) and the table's top among its
    planes; choose() takes the one nearest a guess; in a world moved by 0.73 m the floor moves
    with it; a sweep near a guess finds the same floor."""
    found = floor.candidates(synth_capture.frames, synth_capture.up)
    heights = [h for h, _ in found]
    assert min(abs(h) for h in heights) < 0.01
    assert any(0.35 < h < 0.6 for h in heights)           # a tabletop or a seat: not the floor
    assert abs(floor.choose(found, 0.08)) < 0.01
    assert floor.choose(found, 0.08, tolerance=0.001) is None
    assert floor.choose(found, None) is None
    moved = lifted(synth_capture, 0.73)
    near = floor.candidates(moved.frames, moved.up, near=0.78)
    assert abs(floor.choose(near, 0.78) - 0.73) < 0.01
    assert all(abs(h - 0.78) <= floor.TOLERANCE + floor.FLANK + floor.COARSE for h, _ in near)


def test_a_featureless_capture_or_one_without_baseline_has_no_floor(synth_capture):
    """Plain grey frames show no texture, so no plane; cameras that never move have no pair."""
    grey = np.full((120, 160, 3), 128, np.uint8)

    class Plain:
        def __init__(self, frame):
            self.cam_to_world, self.intrinsics = frame.cam_to_world, frame.intrinsics

        def load_image(self):
            return grey

    assert floor.candidates([Plain(f) for f in synth_capture.frames], synth_capture.up) == []
    still = [dataclasses.replace(synth_capture.frames[0]) for _ in range(10)]
    assert floor.candidates(still, synth_capture.up) == []


def chair(center, viewpoint, score=0.9, height=0.8):
    size = np.array([0.5, height, 0.5])
    R = np.stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]], -1)      # y (up) = world z
    c = np.asarray(center, float)
    return Box(c, size, R, 0.0, 0, "chair", score, geometry.box_corners(c, size, R),
               viewpoint=np.asarray(viewpoint, float))


def test_a_floor_pulls_a_standing_box_along_its_ray_to_stand_on_it():
    """A chair 0.8 m tall stands on the floor at z = 0 with its center at (3, 0, 0.4), seen
    from a camera at (0, 0, 1.5).  Its detection is 0.4 m too far along the ray.  With the
    floor known the reported center moves back, mostly along that ray: its height lands within 2 cm
    of 0.4 and its distance to the truth drops below a third.  The matching and the boxes
    without a floor class are unchanged, and the floor guess is the boxes' median bottom."""
    camera = np.array([0.0, 0.0, 1.5])
    truth = np.array([3.0, 0.0, 0.4])
    ray = (truth - camera) / np.linalg.norm(truth - camera)
    seen = chair(truth + 0.4 * ray, camera)

    def fusion(classes, height):
        f = SceneFusion(mode="ray", ray_ratio=30.0, floor_classes=classes)
        f.add([seen], 0)
        f.floor_height = height
        return f

    plain = fusion((), 0.0).boxes[0]
    pulled = fusion(("chair",), 0.0).boxes[0]
    assert np.allclose(plain.center, seen.center)
    assert abs(pulled.center[2] - 0.4) < 0.02
    moved = pulled.center - seen.center
    # mostly along the ray: moving across it costs 30 times more than along it
    assert np.linalg.norm(np.cross(moved, ray)) < 0.1 * np.linalg.norm(moved)
    assert np.linalg.norm(pulled.center - truth) < np.linalg.norm(seen.center - truth) / 3
    assert np.allclose(pulled.corners, geometry.box_corners(pulled.center, pulled.size,
                                                            pulled.rotation))
    unknown = fusion(("chair",), None)
    assert np.allclose(unknown.boxes[0].center, seen.center)
    assert unknown.floor_guess() == pytest.approx(seen.center[2] - 0.4)
    assert fusion(("table",), 0.0).floor_guess() is None
    # a second detection matches the cluster whatever the floor did to the reported box
    f = fusion(("chair",), 0.0)
    f.add([chair(truth + 0.3 * ray, camera + [0.5, -1.0, 0.0])], 1)
    assert len(f.clusters) == 1 and f.supports == [2]


@pytest.mark.parametrize("kwargs, message", [
    (dict(mode="mean", floor_classes=("chair",)), "need the ray mode"),
    (dict(mode="ray", floor_classes="chair"), "list of class names"),
    (dict(mode="ray", floor_classes=("chair",), floor_weight=0.0), "floor_weight"),
    (dict(mode="ray", floor_weight=float("inf")), "floor_weight"),
])
def test_bad_floor_settings_are_refused(kwargs, message):
    with pytest.raises(ParqError, match=message):
        SceneFusion(**kwargs)
