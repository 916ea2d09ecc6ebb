"""The model card (``model.json``): everything the runtime needs to drive the exported graphs.

``parq-export`` writes it beside ``backbone.onnx`` and ``layer.onnx`` and mirrors it in both
graphs' ``metadata_props`` under ``parq.model_card``.
"""
from __future__ import annotations

import hashlib
import json
import math
import pathlib
import reprlib
from dataclasses import dataclass

import numpy as np

from . import fusion, loop, preprocess
from .errors import ParqError

CARD_FORMAT = "parq-onnx-model"
CARD_VERSION = 2  # 2: graphs pass the memory in factored form
METADATA_KEY = "parq.model_card"
# parq-run's iterations, queries and mirror runs for a card without a "run" entry (written
# before it existed) or without one of its keys
DEFAULT_RUN = {"iters": 2, "queries": 32, "mirror": False, "phases": 1}
PHASE_COUNTS = (1, 2)   # point-sampling grids a run may use (parq_runtime.preprocess.PHASES)
MAX_ITERATIONS = 1000   # recurrent iterations a run may ask for (the detector checks it)
REQUIRED = ("classes", "mean_sizes", "image", "feature", "decoder", "reference_points",
            "postprocess", "graphs", "limits", "config")


@dataclass(frozen=True)
class ModelCard:
    """A validated model card; ``raw`` holds the whole JSON."""

    folder: pathlib.Path
    raw: dict

    @property
    def classes(self) -> list:
        return list(self.raw["classes"])

    @property
    def mean_sizes(self) -> np.ndarray:
        return np.asarray(self.raw["mean_sizes"], dtype=np.float64)

    @property
    def image_size(self) -> tuple:
        return (int(self.raw["image"]["width"]), int(self.raw["image"]["height"]))

    @property
    def image_filter(self) -> str:
        """How frames of another size are brought to :attr:`image_size`: ``pillow-bilinear``
        (the authors') or ``point`` (parq_runtime.preprocess; cards before it: the authors')."""
        return str(self.raw["image"].get("filter", preprocess.AUTHORS_FILTER))

    @property
    def feature_size(self) -> tuple:
        return (int(self.raw["feature"]["width"]), int(self.raw["feature"]["height"]))

    @property
    def feature_stride(self) -> int:
        return int(self.raw["feature"]["stride"])

    @property
    def feature_dim(self) -> int:
        return int(self.raw["feature"]["channels"])

    @property
    def heads(self) -> int:
        return int(self.raw["decoder"]["heads"])

    @property
    def decoder_scale(self) -> np.ndarray:
        return np.asarray(self.raw["decoder"]["scale"], dtype=np.float64)

    @property
    def training_iterations(self) -> int:
        return int(self.raw["decoder"]["iterations"])

    @property
    def reference_points(self) -> np.ndarray:
        """Learned reference points (K, 3), normalised to [0, 1]^3, in the stored order."""
        return np.asarray(self.raw["reference_points"], dtype=np.float64)

    @property
    def query_order(self) -> np.ndarray | None:
        """The learned queries' indices, most useful first (chosen on validation data by
        ``parq_train.tune``), or None: runs with fewer queries then use farthest-point sampling.
        Cards written before it was recorded have none."""
        order = self.raw.get("query_order") or None
        return None if order is None else np.asarray(order, dtype=np.int64)

    @property
    def score_threshold(self) -> float:
        return float(self.raw["postprocess"]["score_threshold"])

    @property
    def nms_iou(self) -> float:
        return float(self.raw["postprocess"]["nms_iou"])

    @property
    def eval_region(self) -> tuple:
        return tuple(float(v) for v in self.raw["postprocess"]["eval_region"])

    @property
    def fusion(self) -> str:
        """Scene fusion mode; cards written before it was recorded use the authors'."""
        return str(self.raw["postprocess"].get("fusion", fusion.AUTHORS_MODE))

    @property
    def min_support(self) -> int:
        return int(self.raw["postprocess"].get("min_support", fusion.AUTHORS_MIN_SUPPORT))

    @property
    def ray_ratio(self) -> float:
        """Along-ray over across-ray variance for ``ray`` fusion (cards before it: the
        default, parq_runtime.fusion.RAY_RATIO)."""
        return float(self.raw["postprocess"].get("ray_ratio", fusion.RAY_RATIO))

    @property
    def scene_nms(self) -> float | None:
        """IoU above which two scene boxes of one class are one object (parq_runtime.fusion;
        None, and cards before it: off)."""
        value = self.raw["postprocess"].get("scene_nms")
        return None if value is None else float(value)

    @property
    def match_iou(self) -> float:
        """IoU at which a snippet's detection joins a scene box (parq_runtime.fusion; cards
        before it: the authors' 0.1)."""
        return float(self.raw["postprocess"].get("match_iou", fusion.MATCH_IOU))

    @property
    def floor_classes(self) -> tuple:
        """Classes whose boxes stand on the floor, pulled to it once it is found in the images
        (parq_runtime.fusion, parq_runtime.floor; empty, and cards before it: none)."""
        return tuple(self.raw["postprocess"].get("floor_classes", ()))

    @property
    def labels(self) -> str:
        """Which class a scene box reports: ``best`` (its best detection's) or ``vote``
        (parq_runtime.fusion; cards before it: the authors' ``best``)."""
        return str(self.raw["postprocess"].get("labels", fusion.AUTHORS_LABELS))

    @property
    def floor_weight(self) -> float:
        return float(self.raw["postprocess"].get("floor_weight", fusion.FLOOR_WEIGHT))

    @property
    def snippet_gap(self) -> int:
        """Keyframes between a snippet's views the model was trained with (1: consecutive, the
        authors'; cards written before it was recorded have 1)."""
        return int(self.raw.get("snippets", {}).get("gap", 1))

    @property
    def run_iters(self) -> int:
        """Iterations parq-run uses when not told: the setting its post-processing was chosen
        for (``parq_train.tune``); cards without a ``run`` entry: 2."""
        return int(self.raw.get("run", {}).get("iters", DEFAULT_RUN["iters"]))

    @property
    def run_queries(self) -> int:
        """Queries parq-run uses when not told (as :attr:`run_iters`); cards without: 32."""
        return int(self.raw.get("run", {}).get("queries", DEFAULT_RUN["queries"]))

    @property
    def run_mirror(self) -> bool:
        """Whether parq-run also runs each snippet's mirror image when not told
        (``--mirror`` / ``--no-mirror``): the setting the post-processing was chosen for; its
        ``min_support`` then counts runs, two a snippet (parq_runtime.scene.min_support).
        Cards without it: no."""
        return bool(self.raw.get("run", {}).get("mirror", DEFAULT_RUN["mirror"]))

    @property
    def runs_per_snippet(self) -> int:
        """Runs a snippet gets at the card's run setting on frames of the network's own size:
        2 with mirror runs, else 1."""
        return 2 if self.run_mirror else 1

    @property
    def run_phases(self) -> int:
        """Point-sampling grids parq-run runs each snippet at when not told (``--phases``):
        1, or 2 to add the grid half a network pixel over where the frames are at least twice
        the network size each way (parq_runtime.preprocess.grids); cards without it: 1."""
        return int(self.raw.get("run", {}).get("phases", DEFAULT_RUN["phases"]))

    @property
    def phase_support(self) -> int | None:
        """The minimum support of snippets run at both sampling grids, counted in runs at the
        card's mirror setting (``min_support`` counts them at one grid); None: twice
        ``min_support`` (parq_runtime.scene.min_support)."""
        value = self.raw["postprocess"].get("phase_support")
        return None if value is None else int(value)

    def run_setting(self, iters=None, queries=None) -> tuple:
        """(iterations, queries): those given, the card's run setting for each left None."""
        return (self.run_iters if iters is None else iters,
                self.run_queries if queries is None else queries)

    @property
    def max_views(self) -> int:
        return int(self.raw["limits"]["max_views"])

    @property
    def max_queries(self) -> int:
        return int(self.raw["limits"]["max_queries"])

    def graph_path(self, role: str) -> pathlib.Path:
        return self.folder / self.raw["graphs"][role]["file"]


def level_sizes(feature_size: tuple, levels: int = 4) -> list:
    """(h_l, w_l) of the FPN levels P2..P5 for a stride-4 map of feature_size = (w, h): each
    stride-2 convolution halves the size, rounding up."""
    w, h = feature_size
    sizes = [(h, w)]
    for _ in range(levels - 1):
        h, w = -(-h // 2), -(-w // 2)
        sizes.append((h, w))
    return sizes


def _sha256(path: pathlib.Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) \
        and math.isfinite(value)


def _section(path, raw: dict, key: str) -> dict:
    value = raw[key]
    if not isinstance(value, dict):
        raise ParqError(f"{path}: {key} must be an object ({{...}}), got {reprlib.repr(value)}")
    return value


def _entry(path, section: dict, where: str, key: str):
    if key not in section:
        raise ParqError(f"{path}: model card lacks {where}.{key}")
    return section[key]


def _integer(path, section: dict, where: str, key: str, low: int, high: int | None = None):
    value = _entry(path, section, where, key)
    if isinstance(value, bool) or not isinstance(value, int) or value < low \
            or (high is not None and value > high):
        span = f"from {low} to {high}" if high is not None else f">= {low}"
        raise ParqError(f"{path}: {where}.{key} must be an integer {span}, got "
                        f"{reprlib.repr(value)}")
    return value


def _number(path, section: dict, where: str, key: str, span: str, inside) -> float:
    value = _entry(path, section, where, key)
    if not _is_number(value) or not inside(value):
        raise ParqError(f"{path}: {where}.{key} must be a number in {span}, got "
                        f"{reprlib.repr(value)}")
    return value


def _ranges(path, section: dict, where: str, key: str, names: str) -> list:
    """``key``: [min, max, min, max, ...] numbers, each min below its max."""
    value = _entry(path, section, where, key)
    count = len(names.split(", "))
    if not (isinstance(value, list) and len(value) == count and all(map(_is_number, value))
            and all(lo < hi for lo, hi in zip(value[0::2], value[1::2]))):
        raise ParqError(f"{path}: {where}.{key} must be {count} numbers [{names}], each min "
                        f"below its max, got {reprlib.repr(value)}")
    return value


def _check_graphs(path, folder: pathlib.Path, raw: dict, check_hashes: bool) -> None:
    graphs = _section(path, raw, "graphs")
    for role in ("backbone", "layer"):
        entry = graphs.get(role)
        if not isinstance(entry, dict) or "file" not in entry:
            raise ParqError(f"{path}: model card names no {role} graph")
        name = entry["file"]
        if not isinstance(name, str) or not name.strip():
            raise ParqError(f"{path}: graphs.{role}.file must be a file name, got "
                            f"{reprlib.repr(name)}")
        graph = folder / name
        if not graph.exists():
            raise ParqError(f"{graph}: missing from the model folder")
        if not graph.is_file():
            raise ParqError(f"{path}: graphs.{role}.file {name!r} is not a file in the model "
                            "folder")
        digest = entry.get("sha256")
        if digest is not None and not isinstance(digest, str):
            raise ParqError(f"{path}: graphs.{role}.sha256 must be a string (the file's "
                            f"sha256), got {reprlib.repr(digest)}")
        if check_hashes and digest and _sha256(graph) != digest:
            raise ParqError(f"{graph}: does not match the model card (sha256 differs; the file "
                            "was changed or comes from another export)")


def _check_sizes(path, raw: dict) -> None:
    """classes, mean_sizes, image, feature, decoder and reference_points."""
    classes = raw["classes"]
    if not (isinstance(classes, list) and classes and all(isinstance(c, str) for c in classes)):
        raise ParqError(f"{path}: classes must be a list of class names, got "
                        f"{reprlib.repr(classes)}")
    sizes = raw["mean_sizes"]
    if not (isinstance(sizes, list) and all(
            isinstance(s, list) and len(s) == 3 and all(_is_number(v) and v > 0 for v in s)
            for s in sizes)):
        raise ParqError(f"{path}: mean_sizes must be a list of [x, y, z] sizes > 0, got "
                        f"{reprlib.repr(sizes)}")
    if len(sizes) != len(classes) + 1:
        raise ParqError(f"{path}: {len(sizes)} mean sizes for {len(classes)} classes")
    image = _section(path, raw, "image")
    width = _integer(path, image, "image", "width", 16, 4096)
    height = _integer(path, image, "image", "height", 16, 4096)
    if image.get("filter", preprocess.AUTHORS_FILTER) not in preprocess.FILTERS:
        raise ParqError(f"{path}: image.filter must be one of {', '.join(preprocess.FILTERS)} "
                        f"(how frames are resized to the network size), got "
                        f"{image.get('filter')!r}")
    feature = _section(path, raw, "feature")
    stride = _integer(path, feature, "feature", "stride", 1, 64)
    for key, size in (("width", width), ("height", height)):
        value = _entry(path, feature, "feature", key)
        if isinstance(value, bool) or value != size // stride:
            raise ParqError(f"{path}: feature.{key} must be image.{key} / feature.stride = "
                            f"{size // stride}, got {reprlib.repr(value)}")
    channels = _integer(path, feature, "feature", "channels", 4)
    if channels % 4:
        raise ParqError(f"{path}: feature.channels must be a multiple of 4, got {channels}")
    decoder = _section(path, raw, "decoder")
    _ranges(path, decoder, "decoder", "scale", "xmin, xmax, ymin, ymax, zmin, zmax")
    heads = _integer(path, decoder, "decoder", "heads", 1, channels)
    if channels % heads:
        raise ParqError(f"{path}: decoder.heads must divide feature.channels ({channels}), "
                        f"got {heads}")
    _integer(path, decoder, "decoder", "iterations", 1)
    points = raw["reference_points"]
    if not isinstance(points, list) or not points:
        raise ParqError(f"{path}: reference_points must be a non-empty list of [x, y, z] "
                        f"points in [0, 1], got {reprlib.repr(points)}")
    for i, point in enumerate(points):
        if not (isinstance(point, list) and len(point) == 3
                and all(_is_number(v) and 0.0 <= v <= 1.0 for v in point)):
            raise ParqError(f"{path}: reference_points[{i}] must be [x, y, z] in [0, 1] "
                            f"(normalised), got {reprlib.repr(point)}")


def load(folder, check_hashes: bool = True) -> ModelCard:
    """Read and validate ``folder/model.json``; raises ParqError saying what is wrong."""
    folder = pathlib.Path(folder)
    if folder.is_file():
        raise ParqError(f"{folder}: is a file, not a model folder (give the folder that holds "
                        "model.json, backbone.onnx and layer.onnx)")
    if not folder.is_dir():
        raise ParqError(f"{folder}: model folder not found")
    path = folder / "model.json"
    if not path.is_file():
        raise ParqError(f"{folder}: not a parq-onnx model folder (no model.json; "
                        "create one with parq-export)")
    try:
        raw = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ParqError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(raw, dict) or raw.get("format") != CARD_FORMAT:
        raise ParqError(f"{path}: not a parq-onnx model card")
    version = raw.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise ParqError(f"{path}: format_version must be an integer (this version reads "
                        f"format {CARD_VERSION}), got {reprlib.repr(version)}")
    if version != CARD_VERSION:
        raise ParqError(f"{path}: written by parq-onnx {raw.get('package_version', '?')} in "
                        f"model format {version}; this version reads format "
                        f"{CARD_VERSION}: export the checkpoint again")
    missing = [k for k in REQUIRED if k not in raw]
    if missing:
        raise ParqError(f"{path}: model card lacks {', '.join(missing)}")
    try:
        return _checked(folder, path, raw, check_hashes)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError,
            ZeroDivisionError) as e:  # a case the checks did not foresee
        raise ParqError(f"{path}: not a valid model card ({type(e).__name__}: {e})") from None


def _checked(folder: pathlib.Path, path: pathlib.Path, raw: dict,
             check_hashes: bool) -> ModelCard:
    card = ModelCard(folder, raw)
    _check_graphs(path, folder, raw, check_hashes)
    _check_sizes(path, raw)
    order = raw.get("query_order") or []
    if not (isinstance(order, list) and all(isinstance(i, int) for i in order)
            and (not order or sorted(order) == list(range(len(raw["reference_points"]))))):
        raise ParqError(f"{path}: query_order must list each of the "
                        f"{len(raw['reference_points'])} learned queries once")
    post = _section(path, raw, "postprocess")
    _number(path, post, "postprocess", "score_threshold", "[0, 1)", lambda v: 0 <= v < 1)
    _number(path, post, "postprocess", "nms_iou", "[0, 1]", lambda v: 0 <= v <= 1)
    _ranges(path, post, "postprocess", "eval_region", "xmin, xmax, zmin, zmax")
    found = fusion.problems(post.get("fusion", fusion.AUTHORS_MODE),
                            post.get("min_support", fusion.AUTHORS_MIN_SUPPORT),
                            post.get("ray_ratio", fusion.RAY_RATIO), post.get("scene_nms"),
                            post.get("floor_classes", ()),
                            post.get("floor_weight", fusion.FLOOR_WEIGHT), card.classes,
                            post.get("labels", fusion.AUTHORS_LABELS),
                            post.get("match_iou", fusion.MATCH_IOU))
    if found:
        raise ParqError(f"{path}: postprocess: {'; '.join(found)}")
    limits = _section(path, raw, "limits")
    _integer(path, limits, "limits", "max_views", 1)
    max_queries = _integer(path, limits, "limits", "max_queries", 1)
    checkpoint = raw.get("checkpoint")
    digest = checkpoint.get("sha256") if isinstance(checkpoint, dict) else None
    if not isinstance(digest, str):     # parq-run's results name the checkpoint by it
        raise ParqError(f"{path}: checkpoint.sha256 must be a string (the exported "
                        f"checkpoint's sha256), got {reprlib.repr(digest)}")
    snippets = raw.get("snippets", {})
    gap = snippets.get("gap", 1) if isinstance(snippets, dict) else None
    if isinstance(gap, bool) or not isinstance(gap, int) or gap < 1:
        raise ParqError(f"{path}: snippets.gap must be an integer >= 1 (keyframes between a "
                        f"snippet's views), got {gap!r}")
    run = raw.get("run", DEFAULT_RUN)
    for key, limit in (("iters", MAX_ITERATIONS), ("queries", max_queries)):
        value = run.get(key, DEFAULT_RUN[key]) if isinstance(run, dict) else None
        if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= limit:
            raise ParqError(f"{path}: run.{key} must be an integer from 1 to {limit} (the "
                            f"default run setting), got {value!r}")
    value = run.get("mirror", DEFAULT_RUN["mirror"])
    if not isinstance(value, bool):
        raise ParqError(f"{path}: run.mirror must be true or false (whether the default run "
                        f"adds mirror-image runs), got {value!r}")
    value = run.get("phases", DEFAULT_RUN["phases"])
    if value not in PHASE_COUNTS or isinstance(value, bool):
        raise ParqError(f"{path}: run.phases must be 1 or 2 (the point-sampling grids the "
                        f"default run uses), got {value!r}")
    value = raw["postprocess"].get("phase_support")
    if value is not None and (isinstance(value, bool) or not isinstance(value, int)
                              or value < 1):
        raise ParqError(f"{path}: postprocess.phase_support must be an integer >= 1 (the "
                        f"minimum support at two sampling grids), got {value!r}")
    for name, member in vars(ModelCard).items():   # every property reads: none fails later
        if isinstance(member, property):
            getattr(card, name)
    return card


# The inputs the runtime feeds each graph (Detector.encode, parq_runtime.loop.run).
GRAPH_INPUTS = {
    "backbone": ("images",) + tuple(f"cached_{n}" for n in loop.FACTOR_NAMES[:4])
    + ("camera", "T_local_camera", "key_value"),
    "layer": loop.QUERY_NAMES + ("reference_points",) + loop.OPERAND_NAMES + loop.FACTOR_NAMES
    + ("key_value",),
}


def check_graph(card: ModelCard, role: str, session) -> None:
    """ParqError unless ``session``, the card's ``role`` graph, takes the inputs the runtime
    feeds that graph at the card's sizes (a graph file swapped for another, or a card from
    another export, would otherwise fail at its first run)."""
    path = card.graph_path(role)
    shapes = {i.name: i.shape for i in session.get_inputs()}
    if sorted(shapes) != sorted(GRAPH_INPUTS[role]):
        other = "layer" if role == "backbone" else "backbone"
        if sorted(shapes) == sorted(GRAPH_INPUTS[other]):
            raise ParqError(f"{path}: not a PARQ {role} graph (it takes the {other} graph's "
                            "inputs; are the graph files swapped?)")
        raise ParqError(f"{path}: not a PARQ {role} graph (inputs {', '.join(shapes)})")
    (w, h), levels = card.image_size, level_sizes(card.feature_size)
    expected = {"images": (None, h, w, 3)} if role == "backbone" else {}
    prefix = "cached_" if role == "backbone" else ""
    expected.update({f"{prefix}{n}": (None, lh, lw, card.feature_dim // 4)
                     for n, (lh, lw) in zip(loop.FACTOR_NAMES[:4], levels)})
    for name, want in expected.items():
        got = shapes[name] or want      # rank unknown: nothing to compare
        if len(got) != len(want) or any(isinstance(g, int) and e is not None and g != e
                                        for g, e in zip(got, want)):
            shown = ", ".join("?" if e is None else str(e) for e in want)
            raise ParqError(f"{path}: input {name} has shape {got}, the model card's image "
                            f"and feature sizes give ({shown}); the card and graph do not "
                            "belong together")
