"""Training snippets from generated scenes (ScanNet layout + boxes.json).

Each scene is cut into snippets of ``views`` keyframes exactly as ``parq-run`` does (0.1 m /
15 degree keyframes), with windows every ``stride`` keyframes.  A snippet's targets are the
scene's boxes that it sees, expressed in the snippet's local frame: a box counts as seen when
its center lies inside the decoder box and, in at least one view, projects into the image in
front of the camera without something nearer in the depth map covering it.

Everything is loaded once into memory: images as uint8 at the network size.
"""
from __future__ import annotations

import json
import pathlib
import time
from dataclasses import dataclass

import numpy as np
from PIL import Image

from parq_runtime import geometry, keyframes, preprocess
from parq_runtime.errors import ParqError
from parq_runtime.readers import open_capture

from .dense import class_lookup, dense_targets
from .progress import minutes


@dataclass
class Snippet:
    """images (N, h, w, 3) uint8; camera (N, 4) feature-resolution pinholes; T_local_camera
    (N, 4, 4); targets in the local frame: labels (M,), centers (M, 3), sizes (M, 3),
    rotations (M, 3, 3) = R_local_object; with ``dense`` loading, per view and feature cell
    dense_depth (N, h, w) float32 log-depth (NaN: none) and dense_labels (N, h, w) uint8 (the
    class seen there, len(classes) the room): :mod:`parq_train.dense`'s targets."""

    scene: str
    images: np.ndarray
    camera: np.ndarray
    T_local_camera: np.ndarray
    labels: np.ndarray
    centers: np.ndarray
    sizes: np.ndarray
    rotations: np.ndarray
    dense_depth: np.ndarray | None = None
    dense_labels: np.ndarray | None = None


def read_boxes(path) -> list:
    data = json.loads(pathlib.Path(path).read_text())
    if data.get("format") != "parq-onnx-boxes":
        raise ParqError(f"{path}: not a boxes.json of parq-synth")
    return data["boxes"]


def _inside(points, scale) -> np.ndarray:
    """(P,) bool: points (P, 3) strictly inside ``scale`` = [xmin, xmax, ymin, ymax, zmin,
    zmax] (the decoder box, in the snippet's local frame)."""
    lo, hi = np.asarray(scale[0::2]), np.asarray(scale[1::2])
    return np.all((points > lo) & (points < hi), -1)


def read_depth(folder, name: str) -> np.ndarray:
    """(H, W) float64 metres: a generated scene's ``depth/<name>.png`` (millimetres, 0 = none)."""
    return np.asarray(Image.open(pathlib.Path(folder) / "depth" / f"{name}.png"),
                      dtype=np.float64) / 1000.0


def snippet_targets(centers_world, sizes, T_world_camera, depths, decoder_scale) -> tuple:
    """The training-target rule of one snippet: (T_local_world (4, 4), centers_local (B, 3),
    seen (B,) bool). ``centers_world`` and ``sizes`` (B, 3) are the scene's boxes,
    ``T_world_camera`` (V, 4, 4) the views' poses, ``depths`` V (depth, K) pairs; a box is a
    target (``seen``) when its centre lies inside ``decoder_scale`` in the snippet's local frame
    and :func:`visible` in some view."""
    T_local_world = geometry.invert(geometry.snippet_frame(T_world_camera))
    centers_local = centers_world @ T_local_world[:3, :3].T + T_local_world[:3, 3]
    seen = _inside(centers_local, decoder_scale) & visible(
        centers_world, sizes, T_world_camera, depths)
    return T_local_world, centers_local, seen


def scene_snippets(folder, config, views: int = 3, stride: int = 1, dense: bool = False) -> list:
    """Snippets of one generated scene for a model with ``config`` (PARQConfig): windows of
    ``views`` keyframes ``config.snippet_gap`` apart, starting every ``stride`` keyframes;
    ``dense``: with each view's dense targets (from its depth map and instance mask)."""
    folder = pathlib.Path(folder)
    capture = open_capture(folder, "scannet")
    boxes = read_boxes(folder / "boxes.json")
    labels = np.array([b["label"] for b in boxes], dtype=np.int64)
    centers_world = np.array([b["center"] for b in boxes], dtype=np.float64).reshape(-1, 3)
    sizes = np.array([b["size"] for b in boxes], dtype=np.float64).reshape(-1, 3)
    R_world_object = np.array([b["rotation"] for b in boxes], dtype=np.float64).reshape(-1, 3, 3)
    keys = keyframes.select([f.cam_to_world for f in capture.frames])
    lut = class_lookup(boxes, len(config.classes))
    out = []
    cache = {}
    for window in keyframes.windows(keys, views, stride, config.snippet_gap):
        frames = [capture.frames[i] for i in window]
        images, K_net, depths = [], [], []
        for f in frames:
            if f.name not in cache:
                image, K = preprocess.prepare(f.load_image(), f.intrinsics, config.image_size,
                                              config.image_filter)
                depth = read_depth(folder, f.name)
                targets = None
                if dense:
                    mask = np.asarray(Image.open(folder / "instance" / f"{f.name}.png"), np.int64)
                    targets = dense_targets(depth, mask, lut, config.feature_size)
                cache[f.name] = (image, K, depth, f.intrinsics, targets)
            images.append(cache[f.name][0])
            K_net.append(cache[f.name][1])
            depths.append(cache[f.name][2:4])
        T_world_camera = np.stack([f.cam_to_world for f in frames])
        T_local_world, centers_local, seen = snippet_targets(
            centers_world, sizes, T_world_camera, depths, config.decoder_scale)
        T_local_camera = T_local_world @ T_world_camera
        camera = geometry.scale_camera(geometry.pinhole(np.stack(K_net)),
                                       1.0 / config.feature_stride)
        out.append(Snippet(
            folder.name, np.stack(images), camera.astype(np.float32),
            T_local_camera.astype(np.float32), labels[seen],
            centers_local[seen].astype(np.float32), sizes[seen].astype(np.float32),
            (T_local_world[:3, :3] @ R_world_object[seen]).astype(np.float32)))
        if dense:
            targets = [cache[f.name][4] for f in frames]
            out[-1].dense_depth = np.stack([t[0] for t in targets]).astype(np.float32)
            out[-1].dense_labels = np.stack([t[1] for t in targets]).astype(np.uint8)
    return out


def visible(centers_world, sizes, T_world_camera, depths, margin: float = 0.1) -> np.ndarray:
    """Whether each box center is seen by some view: in front (z > 0.2 m), inside the image,
    and not behind a surface nearer than its center minus half its largest extent."""
    seen = np.zeros(len(centers_world), dtype=bool)
    for T, (depth, K) in zip(T_world_camera, depths):
        h, w = depth.shape
        p = centers_world @ geometry.invert(T)[:3, :3].T + geometry.invert(T)[:3, 3]
        uv, ok = geometry.project(p, geometry.pinhole(K), (w, h))
        ok &= p[:, 2] > 0.2
        u = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
        surface = depth[v, u]
        ok &= (surface == 0) | (surface >= p[:, 2] - sizes.max(1) / 2 - margin)
        seen |= ok
    return seen


def training_scenes(root, scenes: int, seed: int, frames: int, size, jobs: int = 1,
                    log=print) -> list:
    """Folders ``root/scene_00000 .. scene_<scenes - 1>`` of parq-synth ``seed``, generating the
    ones missing.  A folder made with other arguments (seed, frames, size) is an error, not a
    silent change of the training set: a cache made for one recipe never trains another."""
    from parq_synth import generate
    from parq_synth.writer import scene_name

    root = pathlib.Path(root)
    missing = sum(not (root / scene_name(k)).exists() for k in range(scenes))
    done, start = [], time.perf_counter()

    def progress(result):
        done.append(result)
        if len(done) % 100 == 0:
            log(f"generated {len(done)}/{missing} scenes  "
                f"{minutes(time.perf_counter() - start, len(done), missing)}")

    made = generate(root, scenes, seed, frames=frames, size=tuple(size), jobs=jobs,
                    skip_existing=True, progress=progress)
    if made:
        log(f"generated {len(made)} scenes into {root}")
    folders = [root / scene_name(k) for k in range(scenes)]
    want = {"seed": seed, "frames": frames, "width": int(size[0]), "height": int(size[1])}
    for folder in folders:
        try:
            info = json.loads((folder / "scene.json").read_text())
        except (OSError, ValueError) as e:
            raise ParqError(f"{folder}: unreadable scene.json ({e}); remove the folder to "
                            f"regenerate it") from None
        have = {k: info.get(k) for k in want}
        if have != want:
            diff = ", ".join(f"{k} {have[k]} (wanted {want[k]})" for k in want
                             if have[k] != want[k])
            raise ParqError(f"{folder}: made with other arguments: {diff}; pass another "
                            f"--data folder")
    return folders


def load_scenes(folders: list, config, views: int = 3, stride: int = 1, log=print,
                dense: bool = False) -> list:
    """Snippets of every scene folder (from :func:`training_scenes`); ``dense``: with their
    dense targets (:func:`scene_snippets`)."""
    snippets = []
    for folder in folders:
        snippets += scene_snippets(folder, config, views, stride, dense)
    log(f"{len(snippets)} snippets from {len(folders)} scenes, "
        f"{sum(len(s.labels) for s in snippets)} targets")
    return snippets
