"""A whole capture: keyframes -> snippets -> detections -> scene fusion.

Images are read from disk one snippet at a time, so memory stays flat however long the video.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import floor, keyframes, mirror, preprocess
from .detector import FeatureCache
from .errors import ParqError
from .fusion import FLOOR_OFF, SCENE_NMS_OFF, SceneFusion
from .model_card import PHASE_COUNTS
from .readers import Capture


@dataclass
class RunSettings:
    iters: int | None = None              # None: the model card's run setting
    queries: int | None = None            # None: the model card's run setting
    views: int = 3
    stride: int | None = None
    gap: int | None = None                # None: the model card's
    score_threshold: float | None = None
    region: bool = True
    form: str = "auto"
    keyframe_angle: float = 15.0
    keyframe_distance: float = 0.1
    max_snippets: int | None = None
    fusion: str | None = None             # None: the model card's
    min_support: int | None = None        # None: the model card's
    ray_ratio: float | None = None        # None: the model card's
    scene_nms: float | str | None = None  # None: the model card's; SCENE_NMS_OFF: none
    mirror: bool | None = None            # also run each snippet's mirror image; None: the
                                          # model card's run setting
    phases: int | None = None             # point-sampling grids a snippet is run at (1 or 2,
                                          # parq_runtime.preprocess.grids); None: the card's
    floor: float | str | None = None      # the floor's height along up (metres), FLOOR_OFF,
                                          # or None: found in the images when the card has
                                          # floor classes (parq_runtime.floor)
    labels: str | None = None             # which class a scene box reports (best, vote);
                                          # None: the model card's
    match_iou: float | None = None        # IoU at which a detection joins a scene box;
                                          # None: the model card's


def scene_nms(settings: RunSettings, card) -> float | None:
    """The fusion's scene NMS IoU: the settings', else the card's; None when off."""
    if settings.scene_nms == SCENE_NMS_OFF:
        return None
    return card.scene_nms if settings.scene_nms is None else float(settings.scene_nms)


@dataclass
class SnippetResult:
    index: int
    frames: list          # frame names
    T_world_local: np.ndarray
    boxes: list
    form: str
    seconds: float
    mirrored: list = field(default_factory=list)   # the mirror run's boxes, reflected back
    phased: list = field(default_factory=list)     # the second sampling grid's run's boxes
    phased_mirrored: list = field(default_factory=list)   # and its mirror run's, reflected


@dataclass
class SceneResult:
    capture: Capture
    keyframes: list       # frame names
    snippets: list = field(default_factory=list)
    fusion: SceneFusion | None = None
    seconds: float = 0.0
    gap: int = 1          # keyframes between a snippet's views, as run
    mirror: bool = False  # whether each snippet was also run on its mirror image
    phases: int = 1       # point-sampling grids each snippet was run at
    floor: dict | None = None   # {"height", "source": "given" | "images", "candidates"};
                                # None: no floor prior (none asked for, or none found)


def snippet_gap(settings: RunSettings, card) -> int:
    """Keyframes between a snippet's views: the settings' gap, else the model card's."""
    return settings.gap or card.snippet_gap


def plan(capture: Capture, settings: RunSettings, card) -> tuple:
    """(keyframe indices, snippets as lists of frame indices) for a model with ``card``."""
    keys = keyframes.select([f.cam_to_world for f in capture.frames], settings.keyframe_angle,
                            settings.keyframe_distance)
    snippets = keyframes.windows(keys, settings.views, settings.stride,
                                 snippet_gap(settings, card))
    if settings.max_snippets is not None:
        snippets = snippets[:settings.max_snippets]
    return keys, snippets


def resolved(settings: RunSettings, card) -> RunSettings:
    """``settings`` with iterations, queries and mirror runs left None taken from the model
    card's run setting (the one its post-processing was chosen for)."""
    iters, queries = card.run_setting(settings.iters, settings.queries)
    return replace(settings, iters=iters, queries=queries, mirror=uses_mirror(settings, card))


def uses_mirror(settings: RunSettings, card) -> bool:
    """Whether each snippet is also run on its mirror image: the settings' choice, else the
    card's run setting."""
    return card.run_mirror if settings.mirror is None else bool(settings.mirror)


def min_support(settings: RunSettings, card, phases: int = 1) -> int:
    """The fusion's minimum support: the settings', else the card's scaled to the runs a
    snippet gets, since support counts runs (two a snippet with mirror runs) and the card's
    counts them at its own run setting.  A card chosen without mirror runs asks twice its
    support of a mirror run; one chosen with them (the demo: 3) half of it, rounded up (2),
    of a run without.  At two sampling grids (``phases``) the base is the card's
    ``phase_support``, else twice its ``min_support``."""
    if settings.min_support is not None:
        return settings.min_support
    runs = 2 if uses_mirror(settings, card) else 1
    base = card.min_support if phases == 1 else (card.phase_support or 2 * card.min_support)
    return -(-base * runs // card.runs_per_snippet)


def sampling_phases(settings: RunSettings, card, capture: Capture) -> int:
    """The point-sampling grids the capture's snippets are run at: the settings' (else the
    card's) count, 1 where the first frame is not at least twice the network size each way
    (preprocess.grids)."""
    wanted = card.run_phases if settings.phases is None else settings.phases
    if wanted not in PHASE_COUNTS:
        raise ParqError(f"sampling phases must be 1 or 2, got {wanted!r}")
    return 1 if wanted == 1 else capture_grids(card, capture)


def capture_grids(card, capture: Capture) -> int:
    """The point-sampling grids the capture's frames hold for ``card``'s network
    (preprocess.grids; the first frame stands for the capture, 1 if it has none)."""
    if not capture.frames:
        return 1
    height, width = capture.frames[0].load_image().shape[:2]
    return preprocess.grids((width, height), card.image_size, card.image_filter)


def run(detector, capture: Capture, settings: RunSettings, progress=None) -> SceneResult:
    """Detect in every snippet and fuse; ``progress(done, total)`` is called per snippet.
    Iterations, queries and mirror runs left None are the model card's.  With mirror runs
    each snippet is also run on its mirror image (twice the time) and both
    runs' detections are fused (parq_runtime.mirror)."""
    start = time.perf_counter()
    settings = replace(settings, mirror=uses_mirror(settings, detector.card))
    phases = sampling_phases(settings, detector.card, capture)
    keys, snippets = plan(capture, settings, detector.card)
    result = SceneResult(capture, [capture.frames[i].name for i in keys],
                         mirror=settings.mirror, phases=phases, fusion=SceneFusion(
                             settings.match_iou or detector.card.match_iou, up=capture.up,
                             mode=settings.fusion or detector.card.fusion,
                             min_support=min_support(settings, detector.card, phases),
                             ray_ratio=settings.ray_ratio or detector.card.ray_ratio,
                             scene_nms=scene_nms(settings, detector.card),
                             floor_classes=floor_classes(settings, detector.card),
                             floor_weight=detector.card.floor_weight,
                             labels=settings.labels or detector.card.labels))
    # Overlapping windows share frames: their image features are computed once (streaming).
    # An LRU cache of span + gap - 1 frames never encodes one twice (simulated for 1-9 views,
    # gaps 1-6 and every stride below the span; tests/test_export.py runs five cases); with
    # gap 1 that is the span, as before gaps existed.
    gap = result.gap = snippet_gap(settings, detector.card)
    span = keyframes.span_of(settings.views, gap)
    cache = FeatureCache(span + gap - 1) if (settings.stride or settings.views) < span \
        else None
    for n, indices in enumerate(snippets):
        t = time.perf_counter()
        frames = [capture.frames[i] for i in indices]
        images = [None if cache is not None and i in cache else f.load_image()
                  for i, f in zip(indices, frames)]
        K = np.stack([f.intrinsics for f in frames])
        T_world_camera = np.stack([f.cam_to_world for f in frames])
        options = dict(iters=settings.iters, queries=settings.queries,
                       score_threshold=settings.score_threshold, region=settings.region,
                       form=settings.form, up=capture.up)
        found = detector.detect(images, K, T_world_camera, frame_keys=indices, cache=cache,
                                **options)
        result.fusion.add(found.boxes, n)
        reflected = []
        if settings.mirror:
            if any(image is None for image in images):   # the cache holds unmirrored features
                images = [f.load_image() for f in frames]
            seen = detector.detect(*mirror.mirror_snippet(images, K, T_world_camera,
                                                          capture.up), **options)
            reflected = [mirror.unmirror_box(b, capture.up) for b in seen.boxes]
            result.fusion.add(reflected, n, mirrored=True)
        phased, phased_mirrored = [], []
        for phase in preprocess.PHASES[1:phases]:
            if any(image is None for image in images):
                images = [f.load_image() for f in frames]
            if any(preprocess.grids(image.shape[1::-1], detector.card.image_size,
                                    detector.card.image_filter) < 2 for image in images):
                continue   # a frame smaller than the capture's first: one grid only
            seen = detector.detect(images, K, T_world_camera, phase=phase, **options)
            result.fusion.add(seen.boxes, n, phase=phase)
            phased = seen.boxes
            if settings.mirror:
                seen = detector.detect(*mirror.mirror_snippet(images, K, T_world_camera,
                                                              capture.up), phase=phase,
                                       **options)
                phased_mirrored = [mirror.unmirror_box(b, capture.up) for b in seen.boxes]
                result.fusion.add(phased_mirrored, n, mirrored=True, phase=phase)
        result.snippets.append(SnippetResult(n, [f.name for f in frames], found.T_world_local,
                                             found.boxes, found.form, time.perf_counter() - t,
                                             reflected, phased, phased_mirrored))
        if progress is not None:
            progress(n + 1, len(snippets))
    result.floor = find_floor(result, settings)
    result.seconds = time.perf_counter() - start
    return result


def floor_classes(settings: RunSettings, card) -> tuple:
    """The classes pulled to the floor: the card's; none with ``--floor off`` or a fusion
    other than ``ray`` (the pull is a term of its solve)."""
    if settings.floor == FLOOR_OFF or (settings.fusion or card.fusion) != "ray":
        return ()
    return card.floor_classes


def find_floor(result: SceneResult, settings: RunSettings) -> dict | None:
    """Set the fusion's floor height: the one given, else the images' floor-like plane nearest
    the fused boxes' bottoms (parq_runtime.floor); the record for the output (None: none)."""
    fusion = result.fusion
    if not fusion.floor_classes:
        return None
    if settings.floor is not None:
        fusion.floor_height = float(settings.floor)
        return {"height": fusion.floor_height, "source": "given"}
    capture = result.capture

    def sweep(guess):
        return floor.candidates(capture.frames, capture.up, near=guess)
    fusion.floor_height, found = floor.locate(fusion.floor_guess(), sweep)
    if fusion.floor_height is None:
        return None
    return {"height": round(fusion.floor_height, 4), "source": "images",
            "candidates": [round(h, 4) for h, _ in found]}
