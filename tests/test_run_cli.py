"""parq-run end to end, without torch, and with bad input of every kind."""
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from parq_runtime import cli
from parq_runtime.boxes import Box
from parq_runtime.iou import iou_matrix
from parq_runtime.results import SCHEMA

from conftest import ROOT, model_with_card, write_scannet

BLOCK_TORCH = textwrap.dedent("""
    import sys
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name == "torch" or name.startswith("torch."):
                raise ImportError("torch is blocked in this test")
    sys.meta_path.insert(0, Block())
""")


def run_cli(*args):
    """parq-run in a fresh interpreter; returns (code, stdout, stderr)."""
    p = subprocess.run([sys.executable, "-c", BLOCK_TORCH +
                        "from parq_runtime.cli import main; sys.exit(main(sys.argv[1:]))",
                        *map(str, args)], capture_output=True, text=True, cwd=ROOT)
    return p.returncode, p.stdout, p.stderr


def test_runtime_works_where_torch_cannot_be_imported(tiny_model, scannet_folder):
    code = BLOCK_TORCH + textwrap.dedent(f"""
        import numpy as np
        from parq_runtime import Detector
        from parq_runtime.readers import open_capture
        capture = open_capture({str(scannet_folder)!r})
        frames = capture.frames[:3]
        det = Detector({str(tiny_model)!r})
        r = det.detect([f.load_image() for f in frames], frames[0].intrinsics,
                       np.stack([f.cam_to_world for f in frames]), iters=3, queries=25,
                       score_threshold=0.0, region=False)
        assert len(r.iterations) == 3 and r.iterations[0].logits.shape == (25, 10)
        assert "torch" not in sys.modules
        try:
            import torch
        except ImportError:
            print("blocked")
    """)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "blocked"


@pytest.mark.parametrize("authors_names", [False, True])
def test_parq_run_end_to_end(tiny_model, tmp_path, authors_names):
    folder = write_scannet(tmp_path / "scene", frames=14, authors_names=authors_names)
    out = tmp_path / "out.json"
    code, stdout, stderr = run_cli(folder, "--model", tiny_model, "--iters", 2, "--queries",
                                   16, "--score-threshold", 0, "--all-regions", "-o", out)
    assert code == 0, stderr
    assert stdout == ""
    data = json.loads(out.read_text())
    assert data["schema"] == SCHEMA and data["version"] == 1
    assert data["capture"]["frames"] == 14 and data["capture"]["format"] == "scannet"
    # 0.15 m steps: every frame is a keyframe; 14 // 3 = 4 non-overlapping snippets
    assert data["capture"]["keyframes"] == 14
    assert [s["frames"] for s in data["snippets"]] == [
        [str(i) for i in range(s, s + 3)] for s in (0, 3, 6, 9)]
    total = sum(len(s["boxes"]) for s in data["snippets"])
    assert 0 < len(data["scene"]["boxes"]) <= total
    box = data["scene"]["boxes"][0]
    assert set(box) >= {"class", "label", "score", "center", "size", "rotation", "yaw",
                        "corners", "snippet", "support"}
    R = np.array(box["rotation"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    # same run to stdout, sliding windows and a snippet cap
    code, stdout, _ = run_cli(folder, "--model", tiny_model, "--queries", 8, "--stride", 1,
                              "--max-snippets", 5, "-q")
    assert code == 0
    assert len(json.loads(stdout)["snippets"]) == 5
    assert (data["settings"]["fusion"], data["settings"]["min_support"]) == ("best", 1)
    # fusion chosen on the command line: every scene box is seen by at least 2 snippets
    code, stdout, _ = run_cli(folder, "--model", tiny_model, "--iters", 2, "--queries", 16,
                              "--score-threshold", 0, "--all-regions", "--fusion", "mean",
                              "--min-support", 2, "-q")
    assert code == 0
    mean = json.loads(stdout)
    assert (mean["settings"]["fusion"], mean["settings"]["min_support"]) == ("mean", 2)
    assert mean["scene"]["boxes"] and min(b["support"] for b in mean["scene"]["boxes"]) >= 2
    assert min(b["support"] for b in data["scene"]["boxes"]) >= 1
    assert data["settings"]["scene_nms"] is None                # this card has none
    assert (data["settings"]["labels"], mean["settings"]["labels"]) == ("best", "best")
    # the label vote from the command line reaches the fusion (tests/test_evaluation.py
    # checks what it does)
    code, stdout, _ = run_cli(folder, "--model", tiny_model, "--iters", 2, "--queries", 16,
                              "--score-threshold", 0, "--all-regions", "--fusion", "mean",
                              "--min-support", 2, "--labels", "vote", "-q")
    assert code == 0
    vote = json.loads(stdout)
    assert vote["settings"]["labels"] == "vote" and vote["scene"]["boxes"]
    assert min(b["support"] for b in vote["scene"]["boxes"]) >= 2
    _one_line_error(*run_cli(folder, "--model", tiny_model, "--labels", "majority"),
                    "--labels")
    # scene NMS from the command line: no two scene boxes of one class overlap at all
    code, stdout, _ = run_cli(folder, "--model", tiny_model, "--iters", 2, "--queries", 16,
                              "--score-threshold", 0, "--all-regions", "--fusion", "mean",
                              "--scene-nms", 0, "-q")
    assert code == 0
    nms = json.loads(stdout)
    assert nms["settings"]["scene_nms"] == 0.0
    assert nms["settings"]["match_iou"] == 0.1                  # the card's: the authors'
    # the matching IoU from the command line reaches the fusion (tests/test_evaluation.py
    # checks what it does): at the card's IoU the snippets' boxes join (``mean`` above keeps
    # boxes of support 2); at 1.0 only identical boxes would, so every scene box stands alone
    code, stdout, _ = run_cli(folder, "--model", tiny_model, "--iters", 2, "--queries", 16,
                              "--score-threshold", 0, "--all-regions", "--fusion", "mean",
                              "--match-iou", 1.0, "-q")
    assert code == 0
    apart = json.loads(stdout)
    assert apart["settings"]["match_iou"] == 1.0 and apart["scene"]["boxes"]
    assert all(b["support"] == 1 for b in apart["scene"]["boxes"])
    boxes = [Box.from_json(b) for b in nms["scene"]["boxes"]]
    for name in {b.class_name for b in boxes}:
        same = [b for b in boxes if b.class_name == name]
        overlap = iou_matrix(same, same)[~np.eye(len(same), dtype=bool)]
        assert (overlap <= 0).all()


def test_parq_run_pulls_the_cards_floor_classes_to_a_given_floor(tiny_model, tmp_path):
    """A card naming floor classes: --floor HEIGHT uses that floor (recorded as given) and
    moves only the centers of those classes' scene boxes; --floor off, or a fusion other than
    ray, turns the prior off; by default the floor comes from the images or is absent, and the
    output says which."""
    card = json.loads((tiny_model / "model.json").read_text())
    classes = card["classes"]
    card["postprocess"].update(fusion="ray", ray_ratio=10.0, floor_classes=classes[:4],
                               floor_weight=3.0)
    model = model_with_card(tiny_model, tmp_path / "floor-model", card)
    folder = write_scannet(tmp_path / "scene", frames=16)
    common = (folder, "--model", model, "--iters", 2, "--queries", 16, "--score-threshold",
              0, "--all-regions", "-q")
    runs = {}
    for floor in ("off", "0.25", None):
        code, stdout, stderr = run_cli(*common, *(("--floor", floor) if floor else ()))
        assert code == 0, stderr
        runs[floor] = json.loads(stdout)
    code, stdout, stderr = run_cli(*common, "--floor", "0.25", "--fusion", "mean")
    assert code == 0, stderr
    assert json.loads(stdout)["capture"]["floor"] is None     # the pull is ray fusion's
    off, given, auto = runs["off"], runs["0.25"], runs[None]
    assert off["capture"]["floor"] is None and off["settings"]["floor_classes"] == []
    assert given["capture"]["floor"] == {"height": 0.25, "source": "given"}
    assert given["settings"]["floor_classes"] == classes[:4]
    assert auto["capture"]["floor"] is None or auto["capture"]["floor"]["source"] == "images"
    a, b = off["scene"]["boxes"], given["scene"]["boxes"]
    assert len(a) == len(b) and a
    moved = 0
    for x, y in zip(a, b):
        assert (x["class"], x["size"], x["score"]) == (y["class"], y["size"], y["score"])
        if x["class"] in classes[:4]:
            moved += x["center"] != y["center"]
        else:
            assert x["center"] == y["center"]
    assert moved > 0


def test_parq_run_spaces_a_snippets_views_by_the_gap(tiny_model, tmp_path):
    """--gap 2 takes every other keyframe into a snippet (the JSON records the gap); without
    the flag the model card's gap applies, and a capture too short for one such snippet is a
    one-line error that names the spacing."""
    folder = write_scannet(tmp_path / "scene", frames=14)
    code, stdout, stderr = run_cli(folder, "--model", tiny_model, "--queries", 8,
                                   "--stride", 1, "--gap", 2, "-q")
    assert code == 0, stderr
    data = json.loads(stdout)
    assert data["settings"]["gap"] == 2
    assert [s["frames"] for s in data["snippets"]] == [
        [str(i) for i in (s, s + 2, s + 4)] for s in range(10)]
    card = json.loads((tiny_model / "model.json").read_text())
    model = model_with_card(tiny_model, tmp_path / "model", dict(card, snippets={"gap": 3}))
    code, stdout, stderr = run_cli(folder, "--model", model, "--queries", 8, "-q")
    assert code == 0, stderr
    data = json.loads(stdout)
    assert data["settings"]["gap"] == 3
    assert [s["frames"] for s in data["snippets"]] == [
        [str(i) for i in (s, s + 3, s + 6)] for s in (0, 3, 6)]
    short = write_scannet(tmp_path / "short", frames=6)
    _one_line_error(*run_cli(short, "--model", model, "-q"), "6 keyframes",
                    "3 views 3 keyframes apart")


def test_parq_run_defaults_to_the_cards_run_setting(tiny_model, tmp_path):
    """Without --iters / --queries parq-run runs the card's run setting (the JSON says so);
    flags override it."""
    folder = write_scannet(tmp_path / "scene", frames=6)
    card = json.loads((tiny_model / "model.json").read_text())
    model = model_with_card(tiny_model, tmp_path / "model",
                            dict(card, run={"iters": 1, "queries": 6}))
    code, stdout, stderr = run_cli(folder, "--model", model, "-q")
    assert code == 0, stderr
    settings = json.loads(stdout)["settings"]
    assert (settings["iters"], settings["queries"]) == (1, 6)
    code, stdout, stderr = run_cli(folder, "--model", model, "--iters", 3, "--queries", 4, "-q")
    assert code == 0, stderr
    settings = json.loads(stdout)["settings"]
    assert (settings["iters"], settings["queries"]) == (3, 4)


def test_parq_run_follows_the_cards_mirror_setting_and_scales_its_support(tiny_model,
                                                                          tmp_path):
    """A card tuned with mirror runs makes them parq-run's default; its support counts runs,
    so --no-mirror halves it (rounded up) and a card tuned without doubles it for --mirror;
    --min-support is taken as given either way."""
    folder = write_scannet(tmp_path / "scene", frames=6)
    card = json.loads((tiny_model / "model.json").read_text())
    with_mirror = model_with_card(tiny_model, tmp_path / "mirror", dict(
        card, run=dict(card["run"], mirror=True),
        postprocess=dict(card["postprocess"], min_support=3)))

    def settings(model, *flags):
        code, stdout, stderr = run_cli(folder, "--model", model, "-q", *flags)
        assert code == 0, stderr
        out = json.loads(stdout)
        assert all(("mirrored_boxes" in s) == out["settings"]["mirror"]
                   for s in out["snippets"])
        return out["settings"]["mirror"], out["settings"]["min_support"]

    support = card["postprocess"]["min_support"]
    assert settings(tiny_model) == (False, support)
    assert settings(tiny_model, "--mirror") == (True, 2 * support)
    assert settings(with_mirror) == (True, 3)
    assert settings(with_mirror, "--no-mirror") == (False, 2)
    assert settings(with_mirror, "--no-mirror", "--min-support", 3) == (False, 3)


def test_parq_run_adds_the_second_sampling_grid_where_frames_have_one(tiny_model, tmp_path):
    """--phases 2 (or a card's run.phases 2) runs each snippet again on the frames' second
    point-sampling grid where they are at least twice the network size (its boxes in
    phase_boxes, its mirror run's in phase_mirrored_boxes) and asks the card's phase_support
    of the runs, scaled as mirror runs scale it; a smaller capture has one grid and keeps the
    card's support; a card that does not point-sample has one grid at any size."""
    card = json.loads((tiny_model / "model.json").read_text())
    w, h = card["image"]["width"], card["image"]["height"]
    large = write_scannet(tmp_path / "large", frames=6, size=(2 * w, 2 * h))
    small = write_scannet(tmp_path / "small", frames=6, size=(w * 3 // 2, h * 3 // 2))
    point = dict(card, image=dict(card["image"], filter="point"),
                 run=dict(card["run"], mirror=True),
                 postprocess=dict(card["postprocess"], min_support=2))
    plain = model_with_card(tiny_model, tmp_path / "plain", point)
    phased = model_with_card(tiny_model, tmp_path / "phased", dict(
        point, run=dict(point["run"], phases=2),
        postprocess=dict(point["postprocess"], phase_support=3)))
    pillow = model_with_card(tiny_model, tmp_path / "pillow", dict(
        card, run=dict(card["run"], phases=2)))

    def run(folder, model, *flags):
        code, stdout, stderr = run_cli(folder, "--model", model, "-q", *flags)
        assert code == 0, stderr
        out = json.loads(stdout)
        phases = out["settings"]["phases"]
        for s in out["snippets"]:
            assert ("phase_boxes" in s) == (phases == 2)
            assert ("phase_mirrored_boxes" in s) == (phases == 2 and out["settings"]["mirror"])
        return phases, out["settings"]["min_support"], out

    assert run(large, plain)[:2] == (1, 2)
    assert run(large, plain, "--phases", 2)[:2] == (2, 4)         # twice min_support
    assert run(large, phased)[:2] == (2, 3)                         # the card's phase_support
    out = run(large, phased, "--score-threshold", 0, "--all-regions")[2]
    assert all(s["phase_boxes"] and s["phase_boxes"] != s["boxes"]    # other pixels
               for s in out["snippets"])
    assert run(large, phased, "--no-mirror")[:2] == (2, 2)          # 3 of 4 runs -> 2 of 2
    assert run(large, phased, "--phases", 1)[:2] == (1, 2)
    assert run(small, phased)[:2] == (1, 2)                         # one grid: min_support
    assert run(large, pillow)[0] == 1
    _one_line_error(*run_cli(large, "--model", plain, "--phases", 3), "--phases")
    broken = model_with_card(tiny_model, tmp_path / "broken", dict(
        point, run=dict(point["run"], phases=3)))
    _one_line_error(*run_cli(large, "--model", broken), "model.json", "run.phases")
    broken = model_with_card(tiny_model, tmp_path / "broken2", dict(
        point, postprocess=dict(point["postprocess"], phase_support=0)))
    _one_line_error(*run_cli(large, "--model", broken), "model.json", "phase_support")


def _one_line_error(code, stdout, stderr, *needles):
    assert code == 2, (code, stderr)
    assert "Traceback" not in stderr
    lines = [line for line in stderr.strip().splitlines() if line]
    assert len(lines) == 1 or lines[0].startswith("usage:"), stderr
    for needle in needles:
        assert needle in stderr, (needle, stderr)


def test_bad_arguments(tiny_model, scannet_folder, tmp_path):
    for args, needle in ((["--iters", 0], "--iters"), (["--queries", -3], "--queries"),
                         (["--queries", "many"], "--queries"),
                         (["--queries", 5000], "queries = 5000"),
                         (["--views", 0], "--views"), (["--form", "fast"], "--form"),
                         (["--threads", 0], "--threads"), (["--fusion", "avg"], "--fusion"),
                         (["--min-support", 0], "--min-support"),
                         (["--ray-ratio", 0.5], "--ray-ratio"),
                         (["--ray-ratio", "inf"], "--ray-ratio"),
                         (["--scene-nms", 1.5], "--scene-nms"),
                         (["--scene-nms", "none"], "--scene-nms"),
                         (["--match-iou", 0], "--match-iou"),
                         (["--match-iou", 1.5], "--match-iou"),
                         (["--floor", "low"], "--floor"), (["--floor", "nan"], "--floor"),
                         (["--floor", "1e308"], "--floor")):
        out = tmp_path / "x.json"
        _one_line_error(*run_cli(scannet_folder, "--model", tiny_model, "-o", out, *args),
                        needle)
        assert not out.exists()


def test_bad_model_folders(tiny_model, scannet_folder, tmp_path):
    _one_line_error(*run_cli(scannet_folder, "--model", tmp_path / "nope"), "not found")
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(*run_cli(scannet_folder, "--model", empty), "no model.json")
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in ("model.json", "backbone.onnx"):
        (broken / f).write_bytes((tiny_model / f).read_bytes())
    _one_line_error(*run_cli(scannet_folder, "--model", broken), "layer.onnx",
                    "missing from the model folder")
    (broken / "layer.onnx").write_bytes(b"not onnx")
    _one_line_error(*run_cli(scannet_folder, "--model", broken), "layer.onnx",
                    "does not match the model card")
    card = json.loads((tiny_model / "model.json").read_text())
    card["format_version"] = 99
    old = model_with_card(tiny_model, tmp_path / "old", card)
    _one_line_error(*run_cli(scannet_folder, "--model", old), "format 99", "export")
    card["format_version"] = json.loads((tiny_model / "model.json").read_text())[
        "format_version"]
    card["postprocess"].update(fusion="ray", ray_ratio=0.1)
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "ray_ratio")
    card["postprocess"].update(ray_ratio=10.0, scene_nms=2.0)
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "scene_nms")
    card["postprocess"].update(scene_nms=None, floor_classes=["chair"], floor_weight=-1)
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "floor_weight")
    card["postprocess"].update(floor_classes=["unicorn"], floor_weight=3.0)
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "unicorn")
    card["postprocess"].update(floor_classes=[], labels="majority")
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "labels")
    card["postprocess"].update(labels="best", match_iou=0)
    (old / "model.json").write_text(json.dumps(card))
    _one_line_error(*run_cli(scannet_folder, "--model", old), "model.json", "match_iou")


def test_bad_captures(tiny_model, tmp_path):
    def fresh(name, **kw):
        return write_scannet(tmp_path / name, **kw)

    _one_line_error(*run_cli(tmp_path / "missing", "--model", tiny_model), "not found")
    (tmp_path / "emptydir").mkdir()
    _one_line_error(*run_cli(tmp_path / "emptydir", "--model", tiny_model),
                    "no known capture layout")
    f = fresh("nopose")
    (f / "pose" / "4.txt").unlink()
    _one_line_error(*run_cli(f, "--model", tiny_model), "no pose", "4.png")
    f = fresh("extra")
    np.savetxt(f / "pose" / "40.txt", np.eye(4))
    _one_line_error(*run_cli(f, "--model", tiny_model), "no colour frame", "40.txt")
    f = fresh("nan")
    (f / "pose" / "2.txt").write_text("1 0 0 0\n0 nan 0 0\n0 0 1 0\n0 0 0 1\n")
    _one_line_error(*run_cli(f, "--model", tiny_model), "2.txt", "NaN")
    f = fresh("scaled")
    np.savetxt(f / "pose" / "3.txt", np.diag([2.0, 2, 2, 1]))
    _one_line_error(*run_cli(f, "--model", tiny_model), "3.txt", "not a rotation")
    f = fresh("short")
    (f / "pose" / "5.txt").write_text("1 0 0\n")
    _one_line_error(*run_cli(f, "--model", tiny_model), "5.txt", "expected 4x4")
    f = fresh("corrupt")
    (f / "color" / "1.png").write_bytes(b"\x89PNG garbage")
    out = tmp_path / "corrupt.json"
    _one_line_error(*run_cli(f, "--model", tiny_model, "-o", out), "1.png",
                    "not a readable image")
    assert not out.exists()
    f = fresh("intrinsics")
    np.savetxt(f / "intrinsic" / "intrinsic_color.txt", np.diag([500.0, 500, 1, 1]))
    _one_line_error(*run_cli(f, "--model", tiny_model), "principal point",
                    "do not fit")
    f = fresh("few", frames=2)
    _one_line_error(*run_cli(f, "--model", tiny_model), "fewer than one snippet")
    f = fresh("unwritable")
    _one_line_error(*run_cli(f, "--model", tiny_model, "-o", tmp_path / "no" / "x.json"),
                    "does not exist")


def test_help_describes_every_flag():
    text = cli.parser().format_help()
    for action in cli.parser()._actions:
        assert action.help, action.dest
    assert "--iters" in text and "--queries" in text


# ------------------------------------------------------------------------ formats, --vis, --ply

def run_main(capsys, *args):
    """parq-run in this process (faster than a subprocess; a traceback would fail the test)."""
    try:
        code = cli.main([str(a) for a in args])
    except SystemExit as e:         # argparse
        code = e.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_colmap_capture_with_vis_and_ply(tiny_model, tmp_path):
    from test_formats import COLMAP_WORLD, write_colmap
    from test_visualize import parse_ply

    folder = write_colmap(write_scannet(tmp_path / "scene", frames=9), tmp_path / "colmap",
                          COLMAP_WORLD)
    out, ply_path, vis = tmp_path / "out.json", tmp_path / "boxes.ply", tmp_path / "vis"
    code, stdout, stderr = run_cli(folder, "--model", tiny_model, "--score-threshold", 0,
                                   "--all-regions", "--queries", 8, "-o", out, "--ply",
                                   ply_path, "--vis", vis)
    assert code == 0, stderr
    assert "note: up -y estimated from 9 cameras" in stderr and "warning" not in stderr
    data = json.loads(out.read_text())
    assert data["capture"]["format"] == "colmap" and data["capture"]["up"] == [0, -1, 0]
    boxes = data["scene"]["boxes"]
    parsed = parse_ply(ply_path.read_text())
    assert len(parsed["vertex"]) == 8 * len(boxes) and len(parsed["edge"]) == 12 * len(boxes)
    index = json.loads((vis / "index.json").read_text())
    assert len(index["images"]) == 3 * len(data["snippets"]) == 9
    assert all((vis / i["file"]).is_file() for i in index["images"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["boxes.ply", "colmap", "out.json",
                                                          "scene", "vis"]


def test_bad_input_in_every_format(tiny_model, tmp_path, capsys):
    from test_formats import write_arkit, write_colmap, write_demo, write_nerfstudio

    scene = write_scannet(tmp_path / "scene", frames=6)
    outputs = [tmp_path / "o.json", tmp_path / "o.ply", tmp_path / "vis"]
    flags = ["-o", outputs[0], "--ply", outputs[1], "--vis", outputs[2], "--model", tiny_model,
             "--threads", 1]

    def fails(folder, *needles, extra=()):
        _one_line_error(*run_main(capsys, folder, *flags, *extra), *needles)
        assert not any(p.exists() for p in outputs)
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no debris

    f = write_nerfstudio(scene, tmp_path / "ns")
    (f / "images" / "frame_00003.png").unlink()
    fails(f, "frame_00003.png: image not found")
    meta = json.loads((f / "transforms.json").read_text())
    (f / "transforms.json").write_text(json.dumps(dict(meta, frames=[])))
    fails(f, "transforms.json", "empty")

    f = write_colmap(scene, tmp_path / "colmap")
    cams = f / "sparse" / "0" / "cameras.txt"
    cams.write_text(cams.read_text().replace("96 72", "32 24"))
    fails(f, "cameras.txt", "outside")              # principal point outside the stated size
    for p in (f / "sparse" / "0").iterdir():
        p.rename(p.with_suffix(".bin"))
    fails(f, "model_converter")

    f = write_arkit(scene, tmp_path / "arkit")
    traj = f / "lowres_wide.traj"
    traj.write_text(traj.read_text().replace("6000.502", "6000.502 nan", 1))
    fails(f, "lowres_wide.traj:", "expected 7 numbers")
    f = write_arkit(scene, tmp_path / "arkit2")
    pincam = next((f / "lowres_wide_intrinsics").iterdir())
    pincam.write_text(pincam.read_text().replace("96.0 72.0", "128.0 96.0"))
    fails(f, pincam.stem + ".png", "image is 96x72", "state 128x96")

    marker = tmp_path / "pwned"
    f = write_demo(scene, tmp_path / "demo")
    exploit = b"cos\nsystem\n(V" + f"touch {marker}".encode() + b"\ntR."
    (f / "fragments.pkl").write_bytes(exploit)
    fails(f, "fragments.pkl", "refuses to load os.system")
    assert not marker.exists()

    fails(scene, "COLMAP layout needs", extra=["--format", "colmap"])
    fails(scene, "--up", "invalid choice", extra=["--up", "sideways"])
    fails(scene, "--views 50", extra=["--views", 50])
    fails(scene, "--iters 5000", extra=["--iters", 5000])
    fails(scene, "--score-threshold", extra=["--score-threshold", 1.5])
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "a.jpg").write_bytes(b"x")
    _one_line_error(*run_main(capsys, scene, "--model", tiny_model, "--vis", foreign),
                    "not an earlier --vis output")
    assert [p.name for p in foreign.iterdir()] == ["a.jpg"]
    for args, needle in ((["--ply", tmp_path / "no" / "x.ply"], "does not exist"),
                         (["--vis", tmp_path / "no" / "vis"], "does not exist"),
                         (["--ply", scene], "is a folder"),
                         (["-o", tmp_path / "same", "--ply", tmp_path / "same"], "both")):
        _one_line_error(*run_main(capsys, scene, "--model", tiny_model, *args), needle)
    # a corrupt frame found while detecting: no output of any kind
    (scene / "color" / "4.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    fails(scene, "4.png", "not a readable image")


def test_poses_and_intrinsics_a_reader_must_refuse(tiny_model, tmp_path):
    f = write_scannet(tmp_path / "plusinf")    # only -inf marks a lost frame in ScanNet
    np.savetxt(f / "pose" / "4.txt", np.full((4, 4), np.inf))
    _one_line_error(*run_cli(f, "--model", tiny_model), "4.txt", "infinite")
    f = write_scannet(tmp_path / "far")
    T = np.loadtxt(f / "pose" / "4.txt")
    T[0, 3] = 1e300
    np.savetxt(f / "pose" / "4.txt", T)
    _one_line_error(*run_cli(f, "--model", tiny_model), "4.txt", "translation")
    for name, (i, j, value) in {"row": (2, 0, 0.5), "lower": (1, 0, 5.0),
                                "skew": (0, 1, 3.0)}.items():
        f = write_scannet(tmp_path / name)
        K = np.loadtxt(f / "intrinsic" / "intrinsic_color.txt")
        K[i, j] = value
        np.savetxt(f / "intrinsic" / "intrinsic_color.txt", K)
        _one_line_error(*run_cli(f, "--model", tiny_model), "intrinsic_color.txt",
                        "not pinhole")


def test_outputs_named_twice_through_other_spellings_are_refused(tiny_model, scannet_folder,
                                                                 tmp_path):
    outputs = tmp_path / "outputs"
    (outputs / "a").mkdir(parents=True)
    _one_line_error(*run_cli(scannet_folder, "--model", tiny_model, "-o", outputs / "o.json",
                             "--ply", outputs / "a" / ".." / "o.json"), "both -o and --ply")
    _one_line_error(*run_cli(scannet_folder, "--model", tiny_model, "-o", outputs / "vv",
                             "--vis", outputs / "a" / ".." / "vv"), "both --vis")
    assert [p.name for p in outputs.iterdir()] == ["a"]


def test_a_failed_output_leaves_none_of_the_others(tiny_model, scannet_folder, tmp_path,
                                                    capsys, monkeypatch):
    from parq_runtime import ply
    from parq_runtime.errors import ParqError

    def fail(boxes):
        raise ParqError("o.ply: could not write (disk full)")

    monkeypatch.setattr(ply, "ply_text", fail)
    outputs = tmp_path / "outputs"
    outputs.mkdir()
    code, _, err = run_main(capsys, scannet_folder, "--model", tiny_model, "-q",
                            "--max-snippets", 1, "-o", outputs / "o.json",
                            "--ply", outputs / "o.ply", "--vis", outputs / "vis")
    assert code == 2 and "disk full" in err and "Traceback" not in err
    assert list(outputs.iterdir()) == []


def test_an_os_error_no_check_foresaw_is_one_line(tiny_model, scannet_folder, capsys,
                                                  monkeypatch):
    from parq_runtime import readers

    def unreadable(*args, **kwargs):     # what a folder without read permission gives
        raise PermissionError(13, "Permission denied", f"{scannet_folder}/color")

    monkeypatch.setattr(readers, "open_capture", unreadable)
    code, out, err = run_main(capsys, scannet_folder, "--model", tiny_model)
    assert code == 2 and out == ""
    assert err.strip() == f"parq-run: error: {scannet_folder}/color: Permission denied"
