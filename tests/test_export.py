"""The exported graphs: names, metadata, parity with PyTorch through the numpy runtime,
agreement with onnx's reference evaluator, and an export that fails leaves nothing behind."""
import json

import numpy as np
import onnx
import pytest
import torch
from onnx.reference import ReferenceEvaluator

from parq_export import checkpoint, verify
from parq_export.export import export
from parq_runtime.detector import Detector
from parq_runtime.errors import ParqError
from parq_runtime.model_card import METADATA_KEY

from conftest import model_with_card, tiny_config


def test_graphs_name_every_input_and_output_and_carry_the_card(tiny_model):
    card = json.loads((tiny_model / "model.json").read_text())
    for role, inputs, outputs in (
            ("backbone", ["images", "cached_level_0", "cached_level_1", "cached_level_2",
                          "cached_level_3", "camera", "T_local_camera", "key_value"],
             ["level_0", "level_1", "level_2", "level_3", "ray_hidden", "memory", "attention_keys",
              "attention_values"]),
            ("layer", ["query_features", "query_ray_hidden", "query_weight", "reference_points",
                       "attention_keys", "attention_values", "level_0", "level_1", "level_2",
                       "level_3", "ray_hidden", "key_value"],
             ["center", "size", "ortho6d", "rotation", "logits", "next_reference_points"])):
        proto = onnx.load(tiny_model / f"{role}.onnx")
        assert [i.name for i in proto.graph.input] == inputs
        assert [o.name for o in proto.graph.output] == outputs
        assert proto.opset_import[0].version in (17, 18)
        meta = {p.key: p.value for p in proto.metadata_props}
        assert meta["parq.graph"] == role
        embedded = json.loads(meta[METADATA_KEY])
        assert embedded["reference_points"] == card["reference_points"]
        assert embedded["classes"] == card["classes"] == list(tiny_config().classes)
        assert card["graphs"][role]["file"] == f"{role}.onnx"
        assert card["graphs"][role]["inputs"] == inputs
    assert card["checkpoint"]["layout"] == "parq-onnx"
    assert len(card["checkpoint"]["sha256"]) == 64
    assert card["verification"] and all(v["max_abs_diff"] <= v["tolerance"]
                                        for v in card["verification"].values())


def test_fewer_queries_start_from_the_cards_ranking_or_farthest_points(tiny_model, tmp_path):
    """With a query_order in the card, K queries are its first K (in stored order); without
    one, farthest-point sampling; the learned count is always every learned point; an order
    that is not a permutation of the learned queries is refused when the folder is opened."""
    from parq_runtime.queries import farthest_point_sampling

    card = json.loads((tiny_model / "model.json").read_text())
    learned = np.asarray(card["reference_points"])
    K = len(learned)
    assert card["query_order"] == []
    plain = Detector(tiny_model)
    np.testing.assert_array_equal(plain.reference_points(5),
                                  learned[farthest_point_sampling(learned, 5)])
    order = list(range(K))[::-1]
    ranked = model_with_card(tiny_model, tmp_path / "ranked", dict(card, query_order=order))
    det = Detector(ranked)
    np.testing.assert_array_equal(det.reference_points(5), learned[K - 5:])
    np.testing.assert_array_equal(det.reference_points(K), learned)
    for bad in ([0] * K, order[:-1], [str(i) for i in order]):
        (ranked / "model.json").write_text(json.dumps(dict(card, query_order=bad)))
        with pytest.raises(ParqError, match="query_order must list each of the"):
            Detector(ranked)
    config = tiny_config()
    assert config.replace(query_order=tuple(order)).query_order == tuple(order)
    with pytest.raises(ValueError, match="query_order must be a permutation"):
        config.replace(query_order=(0,) * K)


def test_snippet_gap_is_written_to_the_card_and_checked(tiny_model, tmp_path):
    """The exported card records the training gap (1 by default); a card without one reads as
    1 (cards written before it); one that is not an integer >= 1 is refused, as is a config."""
    card = json.loads((tiny_model / "model.json").read_text())
    assert card["snippets"] == {"gap": 1} and Detector(tiny_model).card.snippet_gap == 1
    old = {k: v for k, v in card.items() if k != "snippets"}
    other = model_with_card(tiny_model, tmp_path / "other", old)
    assert Detector(other).card.snippet_gap == 1
    (other / "model.json").write_text(json.dumps(dict(card, snippets={"gap": 3})))
    assert Detector(other).card.snippet_gap == 3
    for bad in ({"gap": 0}, {"gap": "3"}, {"gap": True}, [3]):
        (other / "model.json").write_text(json.dumps(dict(card, snippets=bad)))
        with pytest.raises(ParqError, match="snippets.gap must be an integer"):
            Detector(other)
    assert tiny_config().replace(snippet_gap=2).snippet_gap == 2
    with pytest.raises(ValueError, match="snippet_gap"):
        tiny_config().replace(snippet_gap=0)


def test_image_filter_is_written_to_the_card_and_used(tiny_model, tmp_path):
    """The card records how frames are resized (the authors' Pillow filter unless the config
    says otherwise); a card without it reads as Pillow (cards written before); with "point"
    the detector takes pixel centres of a frame twice the network size, with the same
    intrinsics; an unknown filter is refused, as in a config."""
    card = json.loads((tiny_model / "model.json").read_text())
    assert card["image"]["filter"] == "pillow-bilinear" == card["config"]["image_filter"]
    image = {k: v for k, v in card["image"].items() if k != "filter"}
    other = model_with_card(tiny_model, tmp_path / "other", dict(card, image=image))
    assert Detector(other).card.image_filter == "pillow-bilinear"
    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 256, (96, 128, 3), dtype=np.uint8) for _ in range(2)]
    K = np.array([[120.0, 0, 64], [0, 120.0, 48], [0, 0, 1]])
    T_world_camera = np.repeat(np.eye(4)[None], 2, 0)
    T_world_camera[:, :3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along world y
    T_world_camera[:, 0, 3] = [0.0, 0.1]
    soft, camera, *_ = Detector(other).prepare(frames, K, T_world_camera)
    (other / "model.json").write_text(json.dumps(dict(card, image=dict(image, filter="point"))))
    sharp, camera_point, *_ = Detector(other).prepare(frames, K, T_world_camera)
    np.testing.assert_array_equal(sharp, np.stack([f[::2, ::2] for f in frames]))
    assert not np.array_equal(soft, sharp)
    np.testing.assert_array_equal(camera_point, camera)
    (other / "model.json").write_text(json.dumps(dict(card, image=dict(image, filter="area"))))
    with pytest.raises(ParqError, match="image.filter must be one of pillow-bilinear, point"):
        Detector(other)
    assert tiny_config().replace(image_filter="point").image_filter == "point"
    with pytest.raises(ValueError, match="image_filter"):
        tiny_config().replace(image_filter="area")


def test_run_setting_is_written_to_the_card_and_checked(tiny_model, tmp_path):
    """The card records parq-run's default iterations, queries and mirror runs (2 x 32, none,
    unless tuned); a card without them reads as 2 x 32 without mirror runs (cards written
    before), detect() without them uses the card's, and a value that is not an integer in
    range (or for mirror, a boolean) is refused, as is a config."""
    card = json.loads((tiny_model / "model.json").read_text())
    assert card["run"] == {"iters": 2, "queries": 32, "mirror": False, "phases": 1}
    other = model_with_card(tiny_model, tmp_path / "other",
                            {k: v for k, v in card.items() if k != "run"})
    assert (Detector(other).card.run_iters, Detector(other).card.run_queries) == (2, 32)
    assert Detector(other).card.run_mirror is False
    (other / "model.json").write_text(json.dumps(dict(card, run={"iters": 1, "queries": 5})))
    det = Detector(other)
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(3)]
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    T_world_camera = np.repeat(np.eye(4)[None], 3, 0)
    T_world_camera[:, 0, 3] = [0.0, 0.1, 0.2]
    result = det.detect(images, K, T_world_camera, score_threshold=0.0, region=False,
                        up=(0.0, -1.0, 0.0))
    assert len(result.iterations) == 1 and result.iterations[0].center.shape[-2] == 5
    for bad in ({"iters": 0, "queries": 5}, {"iters": 2, "queries": 10 ** 6},
                {"iters": "2", "queries": 5}, {"iters": 2, "queries": True}, [2, 32]):
        (other / "model.json").write_text(json.dumps(dict(card, run=bad)))
        with pytest.raises(ParqError, match=r"run\.(iters|queries) must be an integer"):
            Detector(other)
    for bad in ("yes", 1, None):
        (other / "model.json").write_text(json.dumps(dict(card, run={"iters": 2,
                                                                     "mirror": bad})))
        with pytest.raises(ParqError, match=r"run\.mirror must be true or false"):
            Detector(other)
    assert tiny_config().replace(run_queries=64).run_queries == 64
    with pytest.raises(ValueError, match="run_iters"):
        tiny_config().replace(run_iters=0)
    with pytest.raises(ValueError, match="run_mirror"):
        tiny_config().replace(run_mirror="no")


def _without(section: dict, key: str) -> dict:
    return {k: v for k, v in section.items() if k != key}


MALFORMED_CARDS = {   # a change to the tiny model's card -> what the refusal says
    "missing key": (lambda c: dict(c, image=_without(c["image"], "width")),
                    "model card lacks image.width"),
    "empty section": (lambda c: dict(c, limits={}), "model card lacks limits.max_views"),
    "missing threshold": (lambda c: dict(c, postprocess=_without(c["postprocess"], "nms_iou")),
                          "model card lacks postprocess.nms_iou"),
    "section not an object": (lambda c: dict(c, graphs="x"), "graphs must be an object"),
    "graph file not a name": (
        lambda c: dict(c, graphs=dict(c["graphs"], backbone=dict(c["graphs"]["backbone"],
                                                                 file=None))),
        "graphs.backbone.file must be a file name, got None"),
    "graph file a folder": (
        lambda c: dict(c, graphs=dict(c["graphs"], layer=dict(c["graphs"]["layer"], file="."))),
        "graphs.layer.file '.' is not a file in the model folder"),
    "width not a number": (lambda c: dict(c, image=dict(c["image"], width="abc")),
                           "image.width must be an integer from 16 to 4096, got 'abc'"),
    "width zero": (lambda c: dict(c, image=dict(c["image"], width=0)),
                   "image.width must be an integer from 16 to 4096, got 0"),
    "width huge": (lambda c: dict(c, image=dict(c["image"], width=100000)),
                   "image.width must be an integer from 16 to 4096, got 100000"),
    "stride zero": (lambda c: dict(c, feature=dict(c["feature"], stride=0)),
                    "feature.stride must be an integer from 1 to 64, got 0"),
    "no heads": (lambda c: dict(c, decoder=dict(c["decoder"], heads=0)),
                 "decoder.heads must be an integer from 1 to"),
    "short decoder scale": (lambda c: dict(c, decoder=dict(c["decoder"], scale=[1, 2])),
                            "decoder.scale must be 6 numbers"),
    "threshold a word": (lambda c: dict(c, postprocess=dict(c["postprocess"],
                                                            score_threshold="high")),
                         "postprocess.score_threshold must be a number in [0, 1), got 'high'"),
    "short region": (lambda c: dict(c, postprocess=dict(c["postprocess"], eval_region=[1, 2])),
                     "postprocess.eval_region must be 4 numbers"),
    "negative limit": (lambda c: dict(c, limits=dict(c["limits"], max_queries=-5)),
                       "limits.max_queries must be an integer >= 1, got -5"),
    "ragged mean sizes": (lambda c: dict(c, mean_sizes=[[1.0, 1.0]] + c["mean_sizes"][1:]),
                          "mean_sizes must be a list of [x, y, z] sizes > 0"),
    "format version a string": (lambda c: dict(c, format_version=str(c["format_version"])),
                                "format_version must be an integer"),
    "reference points a number": (lambda c: dict(c, reference_points=5),
                                  "reference_points must be a non-empty list"),
    "no reference points": (lambda c: dict(c, reference_points=[], query_order=[]),
                            "reference_points must be a non-empty list"),
    "2-D reference points": (lambda c: dict(c, reference_points=[p[:2] for p in
                                                                 c["reference_points"]]),
                             "reference_points[0] must be [x, y, z] in [0, 1]"),
}


@pytest.mark.parametrize("case", MALFORMED_CARDS)
def test_malformed_card_is_refused_naming_the_key(tiny_model, tmp_path, case):
    """A model.json with a key missing, of the wrong type or out of range is refused when the
    folder is opened, naming the file and the key, not with a Python error later (or no boxes
    at all, as a decoder scale of the wrong length gave)."""
    change, message = MALFORMED_CARDS[case]
    card = json.loads((tiny_model / "model.json").read_text())
    other = model_with_card(tiny_model, tmp_path / "other", change(card))
    with pytest.raises(ParqError) as refused:
        Detector(other)
    assert str(refused.value).startswith(f"{other / 'model.json'}: ")
    assert message in str(refused.value)


@pytest.mark.parametrize("files, card_change, message", [
    (("layer.onnx", "backbone.onnx"), {}, "backbone.onnx: not a PARQ backbone graph"),
    (("layer.onnx", "layer.onnx"), {}, "backbone.onnx: not a PARQ backbone graph"),
    (("backbone.onnx", "backbone.onnx"), {}, "layer.onnx: not a PARQ layer graph"),
    (("backbone.onnx", "layer.onnx"), {"image": 128, "feature": 32},
     "backbone.onnx: input images has shape"),
], ids=["swapped", "layer twice", "backbone twice", "other image size"])
def test_graph_files_that_do_not_fit_the_card_are_named(tiny_model, tmp_path, files,
                                                        card_change, message):
    """Without checksums in the card, graph files swapped (or one copied over the other), or a
    card whose image size is not the graphs', are refused when the sessions are created,
    naming the file, not at the first run."""
    card = json.loads((tiny_model / "model.json").read_text())
    for role in ("backbone", "layer"):
        del card["graphs"][role]["sha256"]
    for section, width in card_change.items():
        card[section]["width"] = width
    folder = tmp_path / "model"
    folder.mkdir()
    for name, source in zip(("backbone.onnx", "layer.onnx"), files):
        (folder / name).write_bytes((tiny_model / source).read_bytes())
    (folder / "model.json").write_text(json.dumps(card))
    with pytest.raises(ParqError, match=message):
        Detector(folder)


def test_parq_run_says_in_one_line_what_is_wrong_with_the_model_folder(tiny_model,
                                                                       scannet_folder,
                                                                       tmp_path, capsys):
    """--model given the model.json instead of its folder, or a folder whose card lacks a key:
    one line naming the path and the problem, exit status 2, no traceback."""
    from parq_runtime import cli

    card = json.loads((tiny_model / "model.json").read_text())
    broken = model_with_card(tiny_model, tmp_path / "broken", dict(card, feature={}))
    for model, needle in ((tiny_model / "model.json", "model.json: is a file, not a model "
                                                      "folder"),
                          (broken, "model.json: model card lacks feature.stride")):
        code = cli.main([str(scannet_folder), "--model", str(model), "-o",
                         str(tmp_path / "out.json"), "-q"])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert needle in err, err
        assert not (tmp_path / "out.json").exists()


def test_views_resized_in_parallel_equal_one_at_a_time(tiny_model):
    """The thread pool that resizes a snippet's views changes nothing: the same images and
    cameras as one view at a time, and a bad view is still named (the first in view order)."""
    rng = np.random.default_rng(7)
    sizes = [(96, 128), (240, 320), (120, 160), (200, 260)]
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in sizes]
    K = np.stack([[[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1]] for h, w in sizes])
    T_world_camera = np.repeat(np.eye(4)[None], len(sizes), 0)
    T_world_camera[:, :3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along world y
    T_world_camera[:, 0, 3] = np.arange(len(sizes)) * 0.1
    serial = Detector(tiny_model, threads=1).prepare(images, K, T_world_camera)
    parallel = Detector(tiny_model, threads=3)
    for got, expected in zip(parallel.prepare(images, K, T_world_camera), serial):
        np.testing.assert_array_equal(got, expected)
    bad = list(images)
    bad[1] = bad[1].astype(np.float32)
    bad[3] = bad[3][..., :2]
    with pytest.raises(ParqError, match="^view 1: expected an RGB uint8 image"):
        parallel.prepare(bad, K, T_world_camera)

@pytest.mark.parametrize("views,queries,iters", [(1, 5, 1), (2, 20, 3), (4, 45, 2),
                                                 (3, 7, 9)])
@pytest.mark.parametrize("form", ["cached", "folded"])
def test_runtime_matches_torch(tiny_checkpoint, tiny_model, views, queries, iters, form):
    """The whole loop (numpy sampling + ORT layer) against the torch model run the authors'
    way (keys and values projected at every iteration)."""
    model = checkpoint.load(tiny_checkpoint).model()
    det = Detector(tiny_model)
    rng = np.random.default_rng(views * 100 + queries)
    camera, T_local_camera = verify.random_snippet(rng, views, model.config)
    T_world_camera = T_local_camera.astype(np.float64)  # any world frame will do
    w, h = model.config.image_size
    images = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(views)]
    K = np.array([[0.9 * w, 0, w / 2 - 0.5], [0, 0.9 * w, h / 2 - 0.5], [0, 0, 1]])
    result = det.detect(images, K, T_world_camera, iters=iters, queries=queries, form=form,
                        score_threshold=0.0)
    assert result.form == form
    net, cam, _, T_lc = det.prepare(images, K, T_world_camera)
    with torch.no_grad():
        expected = model(torch.from_numpy(net).permute(0, 3, 1, 2)[None].float() / 255,
                         torch.from_numpy(cam).float()[None],
                         torch.from_numpy(T_lc).float()[None], iterations=iters,
                         reference_points=torch.from_numpy(det.reference_points(queries))
                         .float())
    assert len(result.iterations) == iters
    for got, ref in zip(result.iterations, expected):
        assert got.center.shape == (queries, 3)
        np.testing.assert_allclose(got.reference, ref["reference"][0], atol=1e-4)
        np.testing.assert_allclose(got.center, ref["center"][0], atol=1e-4)
        np.testing.assert_allclose(got.rotation, ref["rotation"][0], atol=1e-3)
        np.testing.assert_allclose(got.logits, ref["logits"][0], atol=1e-3)
        np.testing.assert_allclose(got.size, ref["size"][0], rtol=1e-3)


@pytest.mark.parametrize("form", ["cached", "folded"])
def test_device_bound_layer_gives_the_plain_runs_outputs(tiny_model, form, monkeypatch):
    """The IOBinding path that keeps a snippet's large constant inputs on an accelerator,
    run here with the CPU as its device: the same outputs, to the bit, as session.run, with
    large inputs bound as device values and small ones as host arrays."""
    import onnxruntime as ort

    from parq_runtime import loop, sessions

    det = Detector(tiny_model)
    assert sessions.device(det.layer) == ("cpu", 0)
    assert loop.LayerRunner(det.layer, {}).binding is None    # CPU sessions run plainly
    rng = np.random.default_rng(3)
    camera, T_local_camera = verify.random_snippet(rng, 3, det.card)
    w, h = det.card.image_size
    images = rng.integers(0, 256, (3, h, w, 3), dtype=np.uint8)
    factors, operands = det.encode(images, camera, T_local_camera, cached=form == "cached")
    # level_0 and larger inputs bound as device values, the coarser levels as host arrays
    monkeypatch.setattr(loop, "DEVICE_RESIDENT_ELEMENTS", factors["level_0"].size)
    runs = [loop.run(det.layer, factors, operands, camera, np.linalg.inv(T_local_camera),
                     det.reference_points(11), 3, det.card.decoder_scale, form == "cached",
                     bind=bind) for bind in (False, True)]
    for plain, bound in zip(*runs):
        for name in ("center", "size", "rotation", "logits"):
            np.testing.assert_array_equal(getattr(bound, name), getattr(plain, name))
    runner = loop.LayerRunner(det.layer, {n: factors[n] for n in ("level_0", "level_3")},
                              bind=True)
    assert len(runner.resident) == 1 and runner.resident[0].device_name() == "cpu"
    # the whole detector with the backbone's keys and values left as device values
    bound = Detector(tiny_model, device_binding=True)
    images = list(images)
    K = np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1]])
    T_world_camera = np.linalg.inv(np.asarray(T_local_camera, np.float64))
    plain = det.detect(images, K, T_world_camera, iters=2, queries=9, form=form)
    on_device = bound.detect(images, K, T_world_camera, iters=2, queries=9, form=form)
    for a, b in zip(plain.iterations, on_device.iterations):
        np.testing.assert_array_equal(a.center, b.center)
        np.testing.assert_array_equal(a.logits, b.logits)
    _, operands = bound.encode(images, camera, T_local_camera, cached=form == "cached")
    assert isinstance(operands["attention_keys"], ort.OrtValue) == (form == "cached")


def test_cuda_provider_named_alone_runs_in_exact_fp32(monkeypatch):
    """--providers CUDAExecutionProvider turns TF32 off (it moved box centres by 6e-3 m on an
    H200); options given by the caller are kept; unknown providers are refused in one line."""
    from parq_runtime import sessions

    monkeypatch.setattr(sessions.ort, "get_available_providers",
                        lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert sessions.resolve_providers("CUDAExecutionProvider") == [
        ("CUDAExecutionProvider", {"use_tf32": "0"}), "CPUExecutionProvider"]
    chosen = ("CUDAExecutionProvider", {"use_tf32": "1"})
    assert sessions.resolve_providers([chosen]) == [chosen, "CPUExecutionProvider"]
    assert sessions.resolve_providers(None) == ["CPUExecutionProvider"]
    with pytest.raises(ParqError, match="^execution provider TensorrtExecutionProvider is not"):
        sessions.resolve_providers("TensorrtExecutionProvider")


def test_exported_ray_arrangement_equals_the_training_one(tiny_checkpoint):
    """The backbone's coordinate-major ray points and permuted first layer give the ray MLP's
    hidden layer of training (``RayEncoder.hidden``) up to float rounding."""
    model = checkpoint.load(tiny_checkpoint).model()
    camera, T_local_camera = verify.random_snippet(np.random.default_rng(5), 3, model.config)
    encoder = model.ray_encoder
    with torch.no_grad():
        expected = encoder.hidden(torch.from_numpy(camera), torch.from_numpy(T_local_camera))
        got = encoder.hidden_coordinate_major(torch.from_numpy(camera),
                                              torch.from_numpy(T_local_camera))
    assert got.shape == expected.shape
    np.testing.assert_allclose(got.numpy(), expected.numpy(), atol=1e-5, rtol=1e-5)


def test_graphs_agree_with_onnx_reference_evaluator(tiny_model):
    """Both graphs, both forms, one frame cached and one new, against onnx's reference
    evaluator (an independent implementation of every operator, the If included)."""
    from parq_runtime.detector import empty_cache

    rng = np.random.default_rng(3)
    config = tiny_config()
    w, h = config.image_size
    camera, T_local_camera = verify.random_snippet(rng, 2, config)
    cached = {k: rng.normal(0, 1, (1, *v.shape[1:])).astype(np.float32)
              for k, v in empty_cache(config.feature_size, config.feature_dim).items()}
    feeds = {"images": rng.integers(0, 256, (1, h, w, 3), dtype=np.uint8), **cached,
             "camera": camera, "T_local_camera": T_local_camera}
    det = Detector(tiny_model)
    for key_value in (True, False):
        inputs = dict(feeds, key_value=np.array(key_value))
        names = [o.name for o in det.backbone.get_outputs()]
        ours = dict(zip(names, det.backbone.run(None, inputs)))
        ref = dict(zip(names, ReferenceEvaluator(str(tiny_model / "backbone.onnx"))
                       .run(None, inputs)))
        for name in names:
            assert ours[name].shape == ref[name].shape, name
            np.testing.assert_allclose(ours[name], ref[name], atol=1e-4, rtol=1e-4,
                                       err_msg=name)
        C = config.feature_dim
        layer_inputs = {"query_features": rng.normal(0, 1, (9, C)).astype(np.float32),
                        "query_ray_hidden": rng.uniform(0, 1, (9, C)).astype(np.float32),
                        "query_weight": rng.uniform(0, 1, (9, 1)).astype(np.float32),
                        "reference_points": rng.uniform(0, 1, (9, 3)).astype(np.float32),
                        "key_value": np.array(key_value),
                        **{n: v for n, v in ours.items() if n != "memory"}}
        got = det.layer.run(None, layer_inputs)
        want = ReferenceEvaluator(str(tiny_model / "layer.onnx")).run(None, layer_inputs)
        for name, a, b in zip([o.name for o in det.layer.get_outputs()], got, want):
            np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-4, err_msg=name)


def test_failed_check_writes_nothing(tiny_checkpoint, tmp_path, monkeypatch):
    monkeypatch.setattr(verify, "ABSOLUTE_TOLERANCE",
                        {k: -1.0 for k in verify.ABSOLUTE_TOLERANCE})
    with pytest.raises(ParqError, match="export check failed"):
        export(tiny_checkpoint, tmp_path / "model", log=lambda *_: None)
    assert list(tmp_path.iterdir()) == []


def test_export_refuses_to_overwrite(tiny_checkpoint, tmp_path):
    (tmp_path / "model").mkdir()
    with pytest.raises(ParqError, match="already exists"):
        export(tiny_checkpoint, tmp_path / "model", log=lambda *_: None)
    with pytest.raises(ParqError, match="opset"):
        export(tiny_checkpoint, tmp_path / "other", opset=20, log=lambda *_: None)


def test_int8_export_quantizes_convolutions_and_runs(tiny_checkpoint, tmp_path):
    """--quantize int8: QDQ around the backbone's convolutions only, calibrated on generated
    scenes; the runtime runs it and its memory stays close to the fp32 torch model's."""
    import onnx

    from parq_runtime import Detector
    from parq_runtime.geometry import camera_pose
    from parq_synth import generate

    from parq_export import quantize
    from parq_export.checkpoint import load

    generate(tmp_path / "calibration", 2, 7, frames=12, size=(64, 48))
    # two snippets at most per scene: more than two means the second scene was read too
    feeds = quantize.calibration_feeds(tmp_path / "calibration", load(tiny_checkpoint).config)
    assert len(feeds) > 2
    out = tmp_path / "int8"
    export(tiny_checkpoint, out, log=lambda *_: None, quantize="int8",
           calibration=tmp_path / "calibration")
    card = json.loads((out / "model.json").read_text())
    assert card["quantization"]["calibration_snippets"] >= 1
    assert card["quantization"]["memory_relative"] < 0.1
    graph = onnx.load(str(out / "backbone.onnx")).graph
    ops = [n.op_type for n in graph.node]
    assert "DequantizeLinear" in ops and "QuantizeLinear" in ops
    assert "If" in ops   # the operands branch is still there, after quantization
    rng = np.random.default_rng(0)
    det = Detector(out)
    images = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(2)]
    K = np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    poses = [camera_pose([0, 0, 1.5], 0.0, 0.3), camera_pose([0.2, 0, 1.5], 0.1, 0.3)]
    result = det.detect(images, K, poses, iters=2, queries=8)
    assert len(result.iterations) == 2
    assert np.isfinite(result.iterations[-1].center).all()


@pytest.mark.parametrize("form", ["cached", "folded"])
def test_streaming_reuses_features_and_changes_nothing(tiny_model, form):
    """Sliding 3-view windows with a FeatureCache: each frame goes through the image encoder
    once (a cached frame is not passed again), and every snippet's outputs equal those of
    the snippet run from scratch."""
    from parq_runtime.detector import FeatureCache
    from parq_runtime.geometry import camera_pose

    det = Detector(tiny_model)
    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]
    poses = [camera_pose([0.15 * i, 0.0, 1.4], 0.1 * i, 0.3) for i in range(6)]
    K = np.array([[55.0, 0, 31.5], [0, 55.0, 23.5], [0, 0, 1]])
    cache = FeatureCache(3)
    for start in range(4):
        window = list(range(start, start + 3))
        images = [None if i in cache else frames[i] for i in window]
        assert sum(im is not None for im in images) == (3 if start == 0 else 1)
        streamed = det.detect(images, K, np.stack([poses[i] for i in window]), iters=2,
                              queries=10, form=form, frame_keys=window, cache=cache,
                              score_threshold=0.0)
        scratch = det.detect([frames[i] for i in window], K,
                             np.stack([poses[i] for i in window]), iters=2, queries=10,
                             form=form, score_threshold=0.0)
        for a, b in zip(streamed.iterations, scratch.iterations):
            np.testing.assert_allclose(a.center, b.center, atol=1e-5)
            np.testing.assert_allclose(a.logits, b.logits, atol=1e-4)


@pytest.mark.parametrize("gap, stride", [(1, 1), (2, 1), (3, 1), (3, 2), (2, 3)])
def test_scene_run_encodes_each_frame_once_whatever_the_gap(tiny_model, tmp_path, gap, stride):
    """Overlapping windows whose views are ``gap`` keyframes apart: the scene's LRU feature
    cache is large enough that no frame goes through the image encoder twice."""
    from parq_runtime import readers, scene

    from conftest import write_scannet

    capture = readers.open_capture(write_scannet(tmp_path / "scene", frames=14))
    det = Detector(tiny_model)
    passed = []
    detect = det.detect

    def counting(images, *args, **kwargs):
        passed.extend(k for k, im in zip(kwargs["frame_keys"], images) if im is not None)
        return detect(images, *args, **kwargs)

    det.detect = counting
    result = scene.run(det, capture, scene.RunSettings(queries=8, stride=stride, gap=gap))
    windows = [[int(name) for name in s.frames] for s in result.snippets]
    assert windows and all(w == list(range(w[0], w[0] + 2 * gap + 1, gap)) for w in windows)
    assert sorted(passed) == sorted({i for w in windows for i in w})


def test_attention_form_is_the_one_with_fewer_multiply_adds():
    """The authors' configuration (3 views, 80 x 60 features, C = 1024, 4 heads), counted here
    from scratch: the folded form scores P2 and the ray hidden layer (C/4 + C channels) on
    14,400 tokens and the coarse levels (40x30, 20x15, 10x8; C/4 channels) per head; the cached
    one pays W2 and the key/value projections once (3 S C^2), then 2 K S C per iteration."""
    from parq_runtime.detector import attention_cost, choose_form

    S, C, H = 3 * 80 * 60, 1024, 4
    width = S * (C // 4 + C) + 3 * (40 * 30 + 20 * 15 + 10 * 8) * (C // 4)
    for queries, iterations in ((16, 1), (32, 2), (64, 8), (256, 1), (256, 8)):
        folded = iterations * 2 * H * queries * width
        cached = 3 * S * C * C + iterations * 2 * queries * S * C
        args = (3, (80, 60), C, H, queries, iterations)
        assert attention_cost("folded", *args) == folded
        assert attention_cost("cached", *args) == cached
        assert choose_form(*args) == ("cached" if cached < folded else "folded")
    # the README's crossovers: 32 queries fold up to 11 iterations; 256 fold only for one
    assert [choose_form(3, (80, 60), C, H, 32, n) for n in (11, 12)] == ["folded", "cached"]
    assert [choose_form(3, (80, 60), C, H, 256, n) for n in (1, 2)] == ["folded", "cached"]


def test_if_branch_writes_its_outputs_without_a_copy():
    """conditional.add_if: an output made inside a branch is written under its outer name
    even when the branch reads it again (an Identity there is a whole-tensor copy in
    onnxruntime); an output passed through from outside still gets its Identity."""
    from onnx import TensorProto, helper

    from parq_export import conditional

    def model(nodes, outputs):
        return helper.make_model(helper.make_graph(
            nodes, "branch", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2])],
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, [2]) for n in outputs]))

    one = helper.make_tensor("one", TensorProto.FLOAT, [], [1.0])
    made = model([helper.make_node("Constant", [], ["c"], value=one),
                  helper.make_node("Add", ["x", "c"], ["y"]),
                  helper.make_node("Mul", ["y", "y"], ["z"])], ["y", "z"])
    passed = model([helper.make_node("Neg", ["x"], ["n"])], ["x", "n"])
    outer = helper.make_model(helper.make_graph(
        [], "outer", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [2])], []),
        opset_imports=[helper.make_opsetid("", 18)])
    infos = [helper.make_tensor_value_info(n, TensorProto.FLOAT, [2]) for n in ("a", "b")]
    joined = conditional.add_if(outer, "flag", made, passed, ["a", "b"], infos)
    onnx.checker.check_model(joined)
    branches = {a.name: a.g for a in joined.graph.node[-1].attribute}
    assert [n.op_type for n in branches["then_branch"].node] == ["Constant", "Add", "Mul"]
    assert [(n.op_type, list(n.input)) for n in branches["else_branch"].node] == [
        ("Neg", ["x"]), ("Identity", ["x"])]
    x = np.array([1.0, -2.0], np.float32)
    for flag, want in ((True, [x + 1, (x + 1) ** 2]), (False, [x, -x])):
        got = ReferenceEvaluator(joined).run(None, {"x": x, "flag": np.array(flag)})
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)


def test_cached_operands_without_token_biases_give_the_same_attention():
    """The exported cached form leaves the key and value biases off the tokens (softmax
    removes the one, the weights' sum of 1 carries the other): the attention agrees with the
    biased operands the authors' arithmetic uses."""
    torch.manual_seed(0)
    from parq_export.model import PARQ

    model = PARQ(tiny_config()).eval()
    decoder = model.layer.decoder
    with torch.no_grad():
        decoder.multihead_attn.in_proj_bias.normal_(0, 1.0)
        memory = torch.randn(1, 37, tiny_config().feature_dim)
        x = torch.randn(1, 5, tiny_config().feature_dim)
        biased = decoder.attention_operands(memory, cached=True)
        bare = decoder.attention_operands(memory, cached=True, token_bias=False)
        assert not torch.allclose(biased[0], bare[0])
        torch.testing.assert_close(decoder.cross_attention(x, *bare),
                                   decoder.cross_attention(x, *biased), atol=2e-5, rtol=1e-5)


def export_cli(capsys, *args):
    """parq-export in this process: (exit code, stderr)."""
    from parq_export import cli

    code = cli.main([str(a) for a in args])
    return code, capsys.readouterr().err


def test_force_replaces_only_a_model_folder(tiny_checkpoint, tmp_path, capsys):
    work = tmp_path / "work"                # the checkpoint beside a user's notes
    work.mkdir()
    ckpt = work / "model.pt"
    ckpt.write_bytes(tiny_checkpoint.read_bytes())
    (work / "notes.txt").write_text("precious")
    code, err = export_cli(capsys, ckpt, "-o", work, "--force", "--no-check")
    assert code == 2 and "notes.txt" in err and "--force replaces only a model folder" in err
    assert sorted(p.name for p in work.iterdir()) == ["model.pt", "notes.txt"]
    (tmp_path / "keep.txt").write_text("keep")
    code, err = export_cli(capsys, ckpt, "-o", tmp_path / "keep.txt", "--force", "--no-check")
    assert code == 2 and "is a file, not a model folder" in err
    assert (tmp_path / "keep.txt").read_text() == "keep"
    out = tmp_path / "model"                # an earlier export is replaced
    assert export_cli(capsys, ckpt, "-o", out, "--no-check")[0] == 0
    before = (out / "model.json").stat().st_mtime_ns
    assert export_cli(capsys, ckpt, "-o", out, "--force", "--no-check")[0] == 0
    assert sorted(p.name for p in out.iterdir()) == ["backbone.onnx", "layer.onnx",
                                                    "model.json"]
    assert (out / "model.json").stat().st_mtime_ns >= before


def test_export_arguments_that_cannot_be_meant(tiny_checkpoint, tmp_path, capsys):
    code, err = export_cli(capsys, tiny_checkpoint, "-o", tmp_path / "m", "--calibration",
                           tmp_path / "scenes")
    assert code == 2 and "only used with --quantize" in err
    code, err = export_cli(capsys, tmp_path, "-o", tmp_path / "m")
    assert code == 2 and "is a folder, expected a checkpoint file" in err
    assert not (tmp_path / "m").exists()
