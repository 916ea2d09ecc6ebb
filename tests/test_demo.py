"""The shipped demo model: a complete, self-describing model folder that detects objects in
its sample scene (a generated room it has never seen), through the runtime alone."""
from __future__ import annotations

import hashlib
import json
import pathlib

import numpy as np
import onnx

from parq_runtime import Detector, evaluation, readers, scene
from parq_runtime.model_card import METADATA_KEY

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEMO = ROOT / "models" / "parq-demo"
SAMPLE = DEMO / "sample-scene"


def test_demo_folder_is_small_and_its_card_says_how_it_was_made():
    size = sum(p.stat().st_size for p in DEMO.rglob("*") if p.is_file())
    assert size < 30e6
    card = json.loads((DEMO / "model.json").read_text())
    training = card["extra"]["training"]
    assert training["command"].startswith("parq-train ")
    assert training["seed"] == 0 and training["data"]["seed"] == 1000
    assert sum(training["minutes"].values()) <= 90
    tuning = card["extra"]["postprocess_tuning"]
    for key in ("score_threshold", "eval_region", "fusion", "min_support", "ray_ratio",
                "scene_nms", "floor_classes", "floor_weight", "labels", "match_iou"):
        assert tuning["chosen"][key] == card["postprocess"][key], key
    # the run setting parq-run uses by default is the one the post-processing was chosen for
    assert (tuning["iters"], tuning["queries"], tuning.get("mirror", False)) == (
        card["run"]["iters"], card["run"]["queries"], card["run"].get("mirror", False))
    assert (tuning.get("phases", 1), tuning.get("phase_support")) == (
        card["run"].get("phases", 1), card["postprocess"].get("phase_support"))
    for role in ("backbone", "layer"):
        path = DEMO / card["graphs"][role]["file"]
        assert hashlib.sha256(path.read_bytes()).hexdigest() == card["graphs"][role]["sha256"]
        meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False)
                .metadata_props}
        assert json.loads(meta[METADATA_KEY])["extra"] == card["extra"]


def test_sample_scene_is_unseen():
    generated = json.loads((SAMPLE / "scene.json").read_text())
    card = json.loads((DEMO / "model.json").read_text())
    used = {card["extra"]["training"]["data"]["seed"], 3000,   # 3000: benchmarks/tradeoff.py
            *card["extra"]["postprocess_tuning"]["seeds"]}
    assert generated["seed"] not in used


def test_benchmarks_refuse_the_seeds_the_demo_saw(monkeypatch):
    """benchmarks/tradeoff.py --seed refuses DEMO_SEEDS: they must be the card's own."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import tradeoff
    card = json.loads((DEMO / "model.json").read_text())
    assert set(tradeoff.DEMO_SEEDS) == {card["extra"]["training"]["data"]["seed"],
                                        *card["extra"]["postprocess_tuning"]["seeds"]}


def test_demo_detects_objects_of_its_sample_scene():
    det = Detector(DEMO)
    capture = readers.open_capture(SAMPLE)
    result = scene.run(det, capture, scene.RunSettings())   # the card's run setting
    truth, up = evaluation.load_ground_truth(SAMPLE / "boxes.json")
    metrics = evaluation.evaluate([(result.fusion.boxes, truth, up)], det.classes)
    # At least one object found with the right class at IoU 0.25, and the boxes are real
    # boxes in the room (centers inside its floor plan, sizes of furniture).
    assert metrics["0.25"]["per_class"] and metrics["0.25"]["recall"] > 0
    centers = np.array([b.center for b in result.fusion.boxes])
    corners = np.concatenate([t.corners for t in truth])
    assert (centers[:, :2] > corners[:, :2].min(0) - 1.0).all()
    assert (centers[:, :2] < corners[:, :2].max(0) + 1.0).all()
    sizes = np.array([b.size for b in result.fusion.boxes])
    assert ((sizes > 0.05) & (sizes < 4.0)).all()
    # the card pulls its floor classes to the floor, which the images put at the room's
    # (parq-synth: z = 0, the lowest ground-truth box bottom)
    assert det.card.floor_classes and result.floor["source"] == "images"
    assert abs(result.floor["height"]) < 0.02
    # every detection knows the camera it was seen from: its snippet frame's origin, the
    # middle view's camera (what ray fusion triangulates with)
    for s in result.snippets:
        middle = next(f for f in capture.frames if f.name == s.frames[1])
        for b in s.boxes:
            np.testing.assert_allclose(b.viewpoint, s.T_world_local[:3, 3])
            np.testing.assert_allclose(b.viewpoint, middle.cam_to_world[:3, 3])


def test_demo_point_samples_larger_frames_as_its_training_frames_were_rendered(tmp_path):
    """The card names point sampling (image.filter): the sample scene enlarged twice (every
    pixel repeated 2 x 2, intrinsics doubled) reaches the network as the original pixels with
    the original intrinsics, so every snippet detects the same boxes in it. (Not the same
    scene boxes to the bit: the floor sweep reads the frames at their own size.)"""
    import shutil

    from PIL import Image

    det = Detector(DEMO)
    assert det.card.image_filter == "point"
    large = tmp_path / "large"
    shutil.copytree(SAMPLE, large)
    K = np.loadtxt(SAMPLE / "intrinsic" / "intrinsic_color.txt")
    K[:2] *= 2
    np.savetxt(large / "intrinsic" / "intrinsic_color.txt", K)
    for f in (large / "color").iterdir():
        small = np.asarray(Image.open(f))
        Image.fromarray(small.repeat(2, 0).repeat(2, 1)).save(f)
    results = [scene.run(det, readers.open_capture(folder), scene.RunSettings())
               for folder in (SAMPLE, large)]

    def detections(result):
        return [(b.label, b.score, b.center.tolist(), b.size.tolist())
                for s in result.snippets for b in s.boxes]
    assert detections(results[0]) and detections(results[0]) == detections(results[1])
