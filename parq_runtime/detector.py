"""Detector: one snippet of posed RGB frames in, 3D boxes out.

    from parq_runtime import Detector
    det = Detector("models/parq-demo")
    result = det.detect(images, intrinsics, cam_to_world)   # iters, queries: the card's
    for box in result.boxes:
        print(box.class_name, box.score, box.center)
"""
from __future__ import annotations

import collections
import numbers
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from . import boxes as box_decoding
from . import geometry, loop, model_card, preprocess, queries as query_points, sessions
from .errors import ParqError

MAX_ITERATIONS = model_card.MAX_ITERATIONS
FORMS = ("auto", "cached", "folded")


@dataclass
class DetectionResult:
    """boxes: detections in the world frame, best first; iterations: one
    :class:`~parq_runtime.loop.Iteration` per iteration (local frame, every query, unfiltered);
    T_world_local (4, 4): the snippet frame; form: the attention form the loop used;
    timings: seconds per stage (``iterations`` is a list, one per iteration)."""

    boxes: list
    iterations: list
    T_world_local: np.ndarray
    form: str
    timings: dict = field(default_factory=dict)


def attention_cost(form: str, views: int, feature_size: tuple, channels: int, heads: int,
                   queries: int, iterations: int) -> float:
    """Multiply-adds that differ between the two exact forms over a snippet.

    Both read the memory m = [P2 | up(P3) | up(P4) | up(P5)] + W2 r + b2 in factored form
    (``parq_export.factored``), over S = views * h * w tokens of C channels.  cached: forms m
    (W2: S C^2) and projects keys and values (2 S C^2), then per iteration scores and weighted
    sum over heads of width d (2 K S C).  folded: per iteration every head scores and sums at
    full width over P2 and r (C / 4 + C channels on S tokens) and over each coarse level at its
    own resolution (C / 4 channels on S_l tokens); nothing is projected."""
    if form == "cached":
        h, w = model_card.level_sizes(feature_size)[0]
        S = views * h * w
        return 3 * S * channels ** 2 + iterations * 2 * queries * S * channels
    return iterations * 2 * heads * queries * folded_width(views, feature_size, channels)


def folded_width(views: int, feature_size: tuple, channels: int) -> int:
    """Channels x tokens that one head of the folded form scores (and sums) per query: P2 and
    the ray MLP's hidden layer on P2's S tokens (C / 4 + C wide) and each coarse level at its
    own resolution (C / 4 wide).  benchmarks/flops.py counts the layer with it too."""
    sizes = model_card.level_sizes(feature_size)
    S = views * sizes[0][0] * sizes[0][1]
    return S * (channels // 4 + channels) \
        + sum(views * h * w for h, w in sizes[1:]) * (channels // 4)


def choose_form(views, feature_size, channels, heads, queries, iterations) -> str:
    """The cheaper exact form by :func:`attention_cost`."""
    args = (views, feature_size, channels, heads, queries, iterations)
    return "cached" if attention_cost("cached", *args) < attention_cost("folded", *args) \
        else "folded"


def empty_cache(feature_size: tuple, channels: int) -> dict:
    """backbone.onnx's cached_level_* inputs for a call with no frames encoded before."""
    return {f"cached_{name}": np.zeros((0, h, w, channels // 4), np.float32)
            for name, (h, w) in zip(loop.FACTOR_NAMES, model_card.level_sizes(feature_size))}


def snippet_inputs(views, T_world_camera, feature_stride: int, up=geometry.UP_Z) -> tuple:
    """Network inputs of a snippet from its prepared views ((image, K) pairs of
    preprocess.prepare) and poses (N, 4, 4): (images (N, h, w, 3) uint8, camera (N, 4) at
    feature resolution, T_world_local, T_local_camera (N, 4, 4))."""
    camera = geometry.scale_camera(geometry.pinhole(np.stack([v[1] for v in views])),
                                   1.0 / feature_stride)
    T_world_local = geometry.snippet_frame(T_world_camera, up)
    T_local_camera = geometry.invert(T_world_local) @ T_world_camera
    return np.stack([v[0] for v in views]), camera, T_world_local, T_local_camera


def _check_count(value, name, low, high):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ParqError(f"{name} must be an integer, got {value!r}")
    if not low <= value <= high:
        raise ParqError(f"{name} = {value}: must be between {low} and {high}")
    return int(value)


class Detector:
    """Loads a model folder written by ``parq-export`` and runs it on snippets.

    providers: onnxruntime execution providers (None: CPU); threads: intra-op threads (None:
    onnxruntime's default, one per physical core); spinning: let the layer session's idle
    worker threads spin between iterations (``session.intra_op.allow_spinning``).  Off by
    default, and the backbone session never spins: a spinning pool keeps its cores busy for
    tens of milliseconds after its run returns, which slowed the first iteration after the
    backbone from 36 to 60 ms and whatever the caller does next (benchmarks/session_options.py).

    The views of a snippet are resized in a pool of ``threads`` (default: one per core) Python
    threads: Pillow releases the GIL while it resamples, so three 1296x968 frames take about
    11.5 ms instead of 16.5 on 2 cores (median of 20; ``benchmarks/latency.py`` times it as
    ``preprocess``).

    device_binding: on an accelerator (None: whenever the sessions run on one; True forces it,
    also on the CPU) the backbone leaves the attention keys and values on the device and the
    loop binds them there (``loop.LayerRunner``): 2 x 59 MB that would otherwise cross to the
    host and back for every snippet in the authors' configuration.
    """

    def __init__(self, model_dir, providers=None, threads=None, spinning: bool = False,
                 device_binding: bool | None = None):
        self.card = model_card.load(model_dir)
        self._threads = int(threads) if threads is not None else (os.cpu_count() or 1)
        self._pool = None
        self.backbone = sessions.create(self.card.graph_path("backbone"), threads, providers,
                                        spinning=False)
        self.layer = sessions.create(self.card.graph_path("layer"), threads, providers,
                                     spinning)
        for role, session in (("backbone", self.backbone), ("layer", self.layer)):
            model_card.check_graph(self.card, role, session)    # e.g. files swapped
        self.classes = self.card.classes
        self.device = sessions.device(self.backbone)     # (type, id)
        self.device_binding = (self.device[0] != "cpu") if device_binding is None \
            else bool(device_binding)

    def reference_points(self, queries: int) -> np.ndarray:
        queries = _check_count(queries, "queries", 1, self.card.max_queries)
        return query_points.reference_points(self.card.reference_points, queries,
                                             self.card.query_order)

    def _check_snippet(self, images, intrinsics, cam_to_world) -> tuple:
        N = len(images)
        if not 1 <= N <= self.card.max_views:
            raise ParqError(f"a snippet needs 1 to {self.card.max_views} views, got {N}")
        T_world_camera = np.asarray(cam_to_world, dtype=np.float64)
        if T_world_camera.shape != (N, 4, 4):
            raise ParqError(f"cam_to_world must be ({N}, 4, 4) for {N} images, got "
                            f"{T_world_camera.shape}")
        geometry.check_rigid(T_world_camera, "cam_to_world")
        K = np.asarray(intrinsics, dtype=np.float64)
        if K.shape == (3, 3):
            K = np.repeat(K[None], N, 0)
        if K.shape != (N, 3, 3):
            raise ParqError(f"intrinsics must be 3x3 or ({N}, 3, 3), got {K.shape}")
        return T_world_camera, K

    def _prepare_view(self, i, image, K, phase: float = 0.0):
        try:
            return preprocess.prepare(image, K, self.card.image_size, self.card.image_filter,
                                      phase)
        except ParqError as e:
            raise ParqError(f"view {i}: {e}") from None

    def _prepare_views(self, indices, images, K, phase: float = 0.0) -> dict:
        """{i: preprocess.prepare(images[i], K[i])} for the listed views, resized in parallel
        when there is more than one; the first failing view (in ``indices`` order) raises."""
        if len(indices) < 2 or self._threads < 2:
            return {i: self._prepare_view(i, images[i], K[i], phase) for i in indices}
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self._threads, thread_name_prefix="parq-prepare")
        futures = [self._pool.submit(self._prepare_view, i, images[i], K[i], phase)
                   for i in indices]
        return {i: f.result() for i, f in zip(indices, futures)}

    def prepare(self, images, intrinsics, cam_to_world, up=geometry.UP_Z):
        """Resize frames and compute the snippet geometry: returns (images (N, h, w, 3) uint8,
        camera (N, 4) at feature resolution, T_world_local, T_local_camera (N, 4, 4))."""
        images = list(images)
        T_world_camera, K = self._check_snippet(images, intrinsics, cam_to_world)
        prepared = self._prepare_views(range(len(images)), images, K)
        return snippet_inputs([prepared[i] for i in range(len(images))], T_world_camera,
                              self.card.feature_stride, up)

    def encode(self, images, camera, T_local_camera, cached: bool, cached_levels=None):
        """Run backbone.onnx on new frames (Nn, h, w, 3) after frames encoded before, whose
        levels P2..P5 are ``cached_levels`` (a list of four (Nc, h_l, w_l, F) arrays, or
        None); camera and T_local_camera list the Nc + Nn views in that order.  Returns
        (factors: level_0..3 (N, h_l, w_l, F) and ray_hidden (N, h', w', C), operands: the
        memory (N, h', w', C) and the attention keys and values (H, S, d), empty unless
        ``cached``).  All numpy arrays, except with ``device_binding`` in the cached form: the
        keys and values are then ``onnxruntime.OrtValue`` on the sessions' device."""
        feeds = empty_cache(self.card.feature_size, self.card.feature_dim)
        if cached_levels is not None:
            feeds = {name: np.ascontiguousarray(levels, dtype=np.float32)
                     for name, levels in zip(feeds, cached_levels)}
        if len(images) == 0:
            w, h = self.card.image_size
            images = np.zeros((0, h, w, 3), np.uint8)
        outputs = [o.name for o in self.backbone.get_outputs()]
        feeds.update({"images": np.ascontiguousarray(images),
                      "camera": np.ascontiguousarray(camera, dtype=np.float32),
                      "T_local_camera": np.ascontiguousarray(T_local_camera, dtype=np.float32),
                      "key_value": np.array(cached)})
        if self.device_binding:   # keys and values stay where the layer will read them
            on_device = loop.OPERAND_NAMES if cached else ()
            binding = self.backbone.io_binding()
            for name, value in feeds.items():
                binding.bind_cpu_input(name, np.ascontiguousarray(value))
            for name in outputs:
                binding.bind_output(name, *(self.device if name in on_device else ("cpu", 0)))
            self.backbone.run_with_iobinding(binding)
            result = {name: value if name in on_device else value.numpy()
                      for name, value in zip(outputs, binding.get_outputs())}
        else:
            result = dict(zip(outputs, self.backbone.run(None, feeds)))
        return ({k: result[k] for k in loop.FACTOR_NAMES},
                {k: result[k] for k in (loop.MEMORY_NAME,) + loop.OPERAND_NAMES})

    def detect(self, images, intrinsics, cam_to_world, iters: int | None = None,
               queries: int | None = None,
               score_threshold: float | None = None, region: bool = True,
               form: str = "auto", up=geometry.UP_Z, frame_keys=None,
               cache: "FeatureCache | None" = None, phase: float = 0.0) -> DetectionResult:
        """Detect objects in one snippet.

        images: N RGB uint8 arrays (H, W, 3), any size; intrinsics: 3x3 for all views or
        (N, 3, 3); cam_to_world: (N, 4, 4) OpenCV camera axes in a world whose up axis is
        ``up`` (z by default).  iters: recurrent iterations >= 1; queries: reference points
        (see parq_runtime.queries); None: the model card's run setting (``run``: what its
        post-processing was chosen for).  score_threshold: default from the model card; region:
        keep only centers inside the authors' evaluation region; form: attention form
        (``auto`` picks the cheaper of ``cached`` and ``folded``; both are exact).

        Streaming: with ``frame_keys`` (one hashable per view) and a :class:`FeatureCache`, the
        image encoder runs only for frames not in the cache (their ``images`` entry may be None
        when cached); every snippet still gets its own ray encoding.  The views are then
        encoded in the order [cached..., new...]; results do not depend on view order beyond
        float rounding.  The cache holds phase 0's features: ``phase`` (preprocess.PHASES, the
        frames' point-sampling grid, for frames at least twice the network size) takes
        neither."""
        iters, queries = self.card.run_setting(iters, queries)
        iters = _check_count(iters, "iters", 1, MAX_ITERATIONS)
        reference = self.reference_points(queries)
        if form not in FORMS:
            raise ParqError(f"form must be one of {', '.join(FORMS)}, got {form!r}")
        threshold = self.card.score_threshold if score_threshold is None else score_threshold
        if not 0.0 <= float(threshold) < 1.0:
            raise ParqError(f"score threshold {threshold}: must be in [0, 1)")
        timings = {}
        start = time.perf_counter()
        images = list(images)
        T_world_camera, K = self._check_snippet(images, intrinsics, cam_to_world)
        keys = list(frame_keys) if frame_keys is not None else [None] * len(images)
        if phase and (cache is not None or frame_keys is not None):
            raise ParqError("the feature cache holds the first sampling grid's features only")
        if len(keys) != len(images):
            raise ParqError(f"{len(keys)} frame keys for {len(images)} images")
        hit = [cache is not None and k is not None and k in cache for k in keys]
        old = [i for i in range(len(images)) if hit[i]]
        new = [i for i in range(len(images)) if not hit[i]]
        order = old + new
        prepared = self._prepare_views(new, images, K, phase)
        K_net = np.stack([cache.get(keys[i])[1] if hit[i] else prepared[i][1] for i in order])
        camera = geometry.scale_camera(geometry.pinhole(K_net), 1.0 / self.card.feature_stride)
        T_world_local = geometry.snippet_frame(T_world_camera, up)
        T_local_camera = geometry.invert(T_world_local) @ T_world_camera[order]
        T_camera_local = geometry.invert(T_local_camera)
        timings["preprocess"] = time.perf_counter() - start
        if form == "auto":
            form = choose_form(len(images), self.card.feature_size, self.card.feature_dim,
                               self.card.heads, len(reference), iters)
        start = time.perf_counter()
        cached_levels = None
        if old:
            entries = [cache.get(keys[i])[0] for i in old]
            cached_levels = [np.stack([e[level] for e in entries]) for level in range(4)]
        factors, operands = self.encode(
            np.stack([prepared[i][0] for i in new]) if new else [], camera, T_local_camera,
            form == "cached", cached_levels)
        if cache is not None:
            for j, i in enumerate(new):
                if keys[i] is not None:
                    levels = tuple(factors[n][len(old) + j].copy()
                                   for n in loop.FACTOR_NAMES[:-1])
                    cache.put(keys[i], (levels, prepared[i][1]))
        timings["backbone"] = time.perf_counter() - start
        timings["iterations"] = []
        iterations = loop.run(self.layer, factors, operands, camera, T_camera_local, reference,
                              iters, self.card.decoder_scale, form == "cached",
                              timings["iterations"], bind=self.device_binding)
        start = time.perf_counter()
        found = box_decoding.detections(
            iterations[-1], T_world_local, self.classes, float(threshold), self.card.nms_iou,
            self.card.eval_region if region else None, up)
        timings["postprocess"] = time.perf_counter() - start
        return DetectionResult(found, iterations, T_world_local, form, timings)


class FeatureCache:
    """Image features (the FPN levels P2..P5) of the last ``capacity`` frames, keyed by frame,
    for streaming: a frame shared by overlapping snippets goes through the image encoder
    once."""

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.entries = collections.OrderedDict()

    def __contains__(self, key) -> bool:
        return key in self.entries

    def get(self, key):
        self.entries.move_to_end(key)
        return self.entries[key]

    def put(self, key, value) -> None:
        self.entries[key] = value
        self.entries.move_to_end(key)
        while len(self.entries) > self.capacity:
            self.entries.popitem(last=False)
