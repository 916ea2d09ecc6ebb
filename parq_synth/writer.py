"""Writing scenes as ScanNet-export folders, one scene at a time, atomically.

Layout of ``scene_<k>/`` (k = the scene's index, 5 digits):

    color/<i>.png                   RGB uint8, i = 0 .. F-1
    depth/<i>.png                   uint16 depth in millimetres (camera z), 0 = no depth
    instance/<i>.png                uint8 object mask: 0 = room, 1 + j = boxes[j]
    pose/<i>.txt                    T_world_camera 4x4 (OpenCV camera, z-up world, metres)
    intrinsic/intrinsic_color.txt   4x4, K in the top-left
    intrinsic/intrinsic_depth.txt   the same (depth is registered to colour)
    intrinsic/extrinsic_color.txt   identity (as ScanNet writes them)
    intrinsic/extrinsic_depth.txt   identity
    boxes.json                      ground-truth boxes in the world frame; each box's
                                    "visible" record says how much of it the capture shows
    scene.json                      provenance: seed, index, generator version, room, lights

A scene is rendered into a hidden temporary folder next to it and renamed into place when
complete, so an interrupted run never leaves a partial ``scene_<k>``.
"""
from __future__ import annotations

import json
import pathlib
import tempfile
import time

import cv2
import numpy as np

from parq_runtime.errors import ParqError
from parq_runtime.files import atomic_folder

from . import render as render_mod
from .scene import GENERATOR_VERSION, STREAM_NOISE, Scene, build_scene, check_args, rng_for

MAX_DEPTH_MM = 65535


def scene_name(index: int) -> str:
    return f"scene_{index:05d}"


def _intrinsic4(K: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = K
    return M


def _imwrite(path: pathlib.Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise ParqError(f"{path}: could not write the image")


def write_scene_files(scene: Scene, folder: pathlib.Path, timings: list | None = None) -> None:
    """Render every frame of ``scene`` and write the folder's files (not atomically)."""
    for sub in ("color", "depth", "instance", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    comp = scene.compiled()
    rays = render_mod.camera_rays(scene.camera, scene.size)
    shown = Visibility(len(scene.objects))
    for i, T in enumerate(scene.poses):
        t0 = time.perf_counter()
        view = render_mod.render(scene, T, rng_for(scene.seed, scene.index, STREAM_NOISE, i),
                                 compiled=comp, rays_cam=rays)
        if timings is not None:
            timings.append(time.perf_counter() - t0)
        _imwrite(folder / "color" / f"{i}.png", view.rgb[..., ::-1])
        _imwrite(folder / "depth" / f"{i}.png", depth_to_mm(view.depth))
        _imwrite(folder / "instance" / f"{i}.png", (view.instance + 1).astype(np.uint8))
        shown.add(view.instance)
        np.savetxt(folder / "pose" / f"{i}.txt", T, fmt="%.17g")
    K4 = _intrinsic4(scene.K)
    for name in ("intrinsic_color", "intrinsic_depth"):
        np.savetxt(folder / "intrinsic" / f"{name}.txt", K4, fmt="%.17g")
    for name in ("extrinsic_color", "extrinsic_depth"):
        np.savetxt(folder / "intrinsic" / f"{name}.txt", np.eye(4), fmt="%.17g")
    (folder / "boxes.json").write_text(json.dumps(shown.annotate(scene.boxes_json()), indent=1)
                                       + "\n")
    (folder / "scene.json").write_text(json.dumps(scene_json(scene), indent=1) + "\n")


class Visibility:
    """How much of each object a capture shows, from its frames' instance masks (the z-buffer's
    nearest surface, so occluded parts do not count): the frames that show any of it and the
    most pixels one frame shows.  parq-synth's rooms hold objects that the camera path may
    never face; ScanNet's ground truth comes from the reconstructed scan, where such an object
    has no box.  The record lets an evaluation leave them out (``parq-eval --seen-only``)."""

    def __init__(self, objects: int):
        self.frames = np.zeros(objects, dtype=np.int64)
        self.max_pixels = np.zeros(objects, dtype=np.int64)

    def add(self, instance: np.ndarray) -> None:
        """instance (H, W) int: object index per pixel, -1 the room."""
        pixels = np.bincount(instance[instance >= 0].ravel(),
                             minlength=len(self.frames))[:len(self.frames)]
        self.frames += pixels > 0
        self.max_pixels = np.maximum(self.max_pixels, pixels)

    def annotate(self, boxes_json: dict) -> dict:
        """``boxes_json`` with each box's {"visible": {"frames", "max_pixels"}} added."""
        for box, frames, pixels in zip(boxes_json["boxes"], self.frames, self.max_pixels):
            box["visible"] = {"frames": int(frames), "max_pixels": int(pixels)}
        return boxes_json


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """Metres (camera z) -> uint16 millimetres, 0 where not finite or not positive."""
    mm = np.where(np.isfinite(depth) & (depth > 0), np.rint(depth * 1000.0), 0)
    return np.clip(mm, 0, MAX_DEPTH_MM).astype(np.uint16)


def scene_json(scene: Scene) -> dict:
    from . import __version__
    return {"format": "parq-synth-scene", "generator": "parq_synth",
            "generator_version": GENERATOR_VERSION, "package_version": __version__,
            "seed": scene.seed, "index": scene.index,
            "seed_sequence": {"entropy": [scene.seed, scene.index],
                              "streams": "spawn_key=(stream,): 0 layout, 1 camera, 2 style, "
                                         "3 lighting, (4, frame) sensor noise"},
            "frames": int(len(scene.poses)), "width": scene.size[0], "height": scene.size[1],
            "camera": {"fx": scene.camera[0], "fy": scene.camera[1], "cx": scene.camera[2],
                       "cy": scene.camera[3]},
            "room": {"size": [float(v) for v in scene.room],
                     "extent": [[0.0, 0.0, 0.0], [float(v) for v in scene.room]],
                     "style": scene.style},
            "lighting": scene.meta["lighting"], "camera_path": scene.meta["path"],
            "depth_scale": 1000.0, "instance_mask": "instance/<i>.png: 0 room, 1 + j boxes[j]",
            "objects": len(scene.objects)}


def generate_scene(out_dir, seed: int, frames: int = 60, size=(320, 240), *, index: int = 0,
                   overwrite: bool = False, timings: list | None = None) -> Scene:
    """Build, render and write the scene ``index`` of ``seed`` into the folder ``out_dir``
    (created; its parent must be writable).  Returns the Scene."""
    check_args(seed=seed, index=index, frames=frames, size=size)
    out_dir = pathlib.Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise ParqError(f"{out_dir}: already exists (pass overwrite=True / --overwrite to "
                        "replace it)")
    ensure_writable(out_dir.parent)
    scene = build_scene(seed, index, frames, size)
    with atomic_folder(out_dir, "the scene") as tmp:
        write_scene_files(scene, tmp, timings)
    return scene


def ensure_writable(folder) -> pathlib.Path:
    folder = pathlib.Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ParqError(f"{folder}: exists and is not a folder") from None
    except OSError as e:
        raise ParqError(f"{folder}: cannot create the output folder "
                        f"({e.strerror or e})") from None
    if not folder.is_dir():
        raise ParqError(f"{folder}: exists and is not a folder")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise ParqError(f"{folder}: cannot write there ({e.strerror or e})") from None
    return folder


def _one(args):
    out, seed, index, frames, size, overwrite = args
    t0 = time.perf_counter()
    timings: list = []
    scene = generate_scene(pathlib.Path(out) / scene_name(index), seed, frames, size,
                           index=index, overwrite=overwrite, timings=timings)
    return index, len(scene.objects), time.perf_counter() - t0, timings


def generate(out, scenes: int, seed: int, frames: int = 60, size=(320, 240), *, start: int = 0,
             overwrite: bool = False, skip_existing: bool = False, jobs: int = 1,
             progress=None) -> list:
    """Write scenes start .. start + scenes - 1 of ``seed`` to ``out/scene_<k>``.  Returns
    [(index, objects, seconds, per-frame render seconds)] of the scenes written.
    ``progress`` is called with each of those as scenes finish.  ``skip_existing``: leave the
    scene folders already there (each is written atomically, so one that exists is whole) and
    write only the missing ones: a cache of scenes made earlier with the same arguments."""
    check_args(seed=seed, index=start, frames=frames, size=size, scenes=scenes)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ParqError(f"jobs must be an integer >= 1, got {jobs!r}")
    if overwrite and skip_existing:
        raise ParqError("overwrite and skip_existing exclude each other")
    out = ensure_writable(out)
    indices = range(start, start + scenes)
    if skip_existing:
        indices = [k for k in indices if not (out / scene_name(k)).exists()]
        if not indices:
            return []
        scenes = len(indices)
    elif not overwrite:
        existing = [scene_name(k) for k in indices if (out / scene_name(k)).exists()]
        if existing:
            raise ParqError(f"{out}: {existing[0]} already exists"
                            + (f" (and {len(existing) - 1} more)" if len(existing) > 1 else "")
                            + "; pass --overwrite to replace, or --start to continue after it")
    tasks = [(str(out), seed, k, frames, tuple(size), overwrite) for k in indices]
    results = []
    if jobs == 1 or scenes == 1:
        for t in tasks:
            results.append(_one(t))
            if progress:
                progress(results[-1])
    else:
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(max_workers=min(jobs, scenes)) as pool:
            for r in pool.map(_one, tasks):
                results.append(r)
                if progress:
                    progress(r)
    return results
