"""The JSON that ``parq-run`` writes (schema ``parq-onnx/detections``, version 1).

    {
      "schema": "parq-onnx/detections", "version": 1,
      "model":    {"folder", "checkpoint_sha256", "package_version"},
      "settings": {"iters", "queries", "views", "stride", "gap", "score_threshold", "region",
                   "fusion", "labels", "min_support", "ray_ratio", "scene_nms", "match_iou",
                   "mirror", "phases", "form",
                   "keyframe_angle_deg", "keyframe_distance_m", "floor_classes"},
      "capture":  {"path", "format", "up", "frames", "keyframes", "notes", "floor": null or
                   {"height" m along up, "source": "given" | "images", "candidates": [m]}},
      "snippets": [{"index", "frames": [names], "T_world_local": 4x4, "form", "seconds",
                    "boxes": [box, ...], "mirrored_boxes": [box, ...] (only with mirror runs:
                    the mirror-image run's boxes, reflected back), "phase_boxes" and, with mirror
                    runs, "phase_mirrored_boxes": [box, ...] (only at two sampling phases: the
                    second point-sampling grid's runs)}],
      "scene":    {"boxes": [box + "snippet": index of the snippet it came from, "support":
                   how many snippets (runs, with mirror runs) detected it]},
      "seconds":  total
    }

A box: {"class", "label", "score", "center" [3] m, "size" [3] m (full extents along the object's
x, y = up, z), "rotation" 3x3 = R_world_object (columns = object axes), "yaw" rad,
"corners" 8x3 m}; every coordinate is in the capture's world frame.
"""
from __future__ import annotations

import numpy as np

from . import __version__

SCHEMA = "parq-onnx/detections"
VERSION = 1


def to_json(scene, settings, card, score_threshold: float) -> dict:
    snippets = []
    for s in scene.snippets:
        snippets.append({"index": s.index, "frames": s.frames,
                         "T_world_local": np.round(s.T_world_local, 8).tolist(),
                         "form": s.form, "seconds": round(s.seconds, 4),
                         "boxes": [b.to_json() for b in s.boxes]})
        if scene.mirror:
            snippets[-1]["mirrored_boxes"] = [b.to_json() for b in s.mirrored]
        if scene.phases > 1:
            snippets[-1]["phase_boxes"] = [b.to_json() for b in s.phased]
            if scene.mirror:
                snippets[-1]["phase_mirrored_boxes"] = [b.to_json() for b in s.phased_mirrored]
    fused = [dict(b.to_json(), snippet=int(src), support=int(n))
             for b, src, n in zip(scene.fusion.boxes, scene.fusion.sources,
                                  scene.fusion.supports)]
    return {
        "schema": SCHEMA, "version": VERSION,
        "model": {"folder": str(card.folder),
                  "checkpoint_sha256": card.raw["checkpoint"]["sha256"],
                  "package_version": __version__},
        "settings": {"iters": settings.iters, "queries": settings.queries,
                     "views": settings.views, "stride": settings.stride or settings.views,
                     "gap": scene.gap,
                     "score_threshold": score_threshold, "region": settings.region,
                     "fusion": scene.fusion.mode, "labels": scene.fusion.labels,
                     "min_support": scene.fusion.min_support,
                     "ray_ratio": scene.fusion.ray_ratio,
                     "scene_nms": scene.fusion.scene_nms,
                     "match_iou": scene.fusion.iou_threshold, "mirror": scene.mirror,
                     "phases": scene.phases,
                     "form": settings.form, "keyframe_angle_deg": settings.keyframe_angle,
                     "keyframe_distance_m": settings.keyframe_distance,
                     "floor_classes": list(scene.fusion.floor_classes)},
        "capture": {"path": str(scene.capture.path), "format": scene.capture.format,
                    "up": list(map(float, scene.capture.up)),
                    "frames": len(scene.capture.frames), "keyframes": len(scene.keyframes),
                    "notes": scene.capture.notes, "floor": scene.floor},
        "snippets": snippets,
        "scene": {"boxes": fused},
        "seconds": round(scene.seconds, 4),
    }


def summary_lines(boxes: list, limit: int = 30) -> list:
    """One line per scene box, best first, for a terminal: class, score, center and size in
    metres (world frame)."""
    ordered = sorted(boxes, key=lambda b: -b.score)
    lines = [f"  {b.class_name:<10} {b.score:4.2f}  center "
             + " ".join(f"{v:+6.2f}" for v in b.center) + "  size "
             + " ".join(f"{v:4.2f}" for v in b.size) for b in ordered[:limit]]
    if len(ordered) > limit:
        lines.append(f"  ... and {len(ordered) - limit} more (see the JSON)")
    return lines
