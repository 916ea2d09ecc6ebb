"""Check exported graphs against the torch model on random inputs.

The check runs at shapes other than the ones the graphs were traced with (other view counts,
query counts, a streaming call with cached features) and in both forms of the attention
operands.  Tolerances are those of ``../shared/golden/README.md`` for the box parameters;
intermediate tensors are compared relative to their magnitude.
"""
from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch

from parq_runtime import geometry

from .graphs import LAYER_OUTPUTS, OPERAND_NAMES
from .model import PARQ

# max abs difference allowed, as a fraction of the reference's largest magnitude (at least 1)
RELATIVE_TOLERANCE = {"features": 1e-4, "memory": 1e-4, "attention_keys": 1e-4,
                      "attention_values": 1e-4, "key_map": 1e-6, "value_map": 1e-6,
                      "value_bias": 1e-6}
# golden tolerances: centers in metres, rotation entries, logits, sizes relative
ABSOLUTE_TOLERANCE = {"center": 1e-4, "rotation": 1e-3, "ortho6d": 1e-3, "logits": 1e-3,
                      "next_reference_points": 1e-4, "size": 1e-3}


def random_snippet(rng: np.random.Generator, views: int, config) -> tuple:
    """Plausible random cameras for one snippet: (camera (N, 4) at feature resolution,
    T_local_camera (N, 4, 4)), float32.  Hand-held motion at 1.2-1.7 m, 5-25 degrees tilt."""
    w, h = config.image_size
    poses = []
    yaw0 = rng.uniform(-np.pi, np.pi)
    start = rng.uniform(-1, 1, 3) * (1, 1, 0) + (0, 0, rng.uniform(1.2, 1.7))
    for i in range(views):
        poses.append(geometry.camera_pose(
            start + rng.normal(0, 0.15, 3) * (1, 1, 0.3), yaw0 + 0.2 * i + rng.normal(0, 0.05),
            np.radians(rng.uniform(5, 25)), np.radians(rng.normal(0, 3))))
    T_world_camera = np.stack(poses)
    T_world_local = geometry.snippet_frame(T_world_camera)
    T_local_camera = geometry.invert(T_world_local) @ T_world_camera
    f = rng.uniform(0.8, 1.1) * w
    K = np.array([f, f * rng.uniform(0.98, 1.02), w / 2 + rng.normal(0, 3), h / 2 + rng.normal(0, 3)])
    camera = geometry.scale_camera(np.repeat(K[None], views, 0), 1 / config.feature_stride)
    return camera.astype(np.float32), T_local_camera.astype(np.float32)


def _max_abs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)))) \
        if np.size(a) else 0.0


def check(model: PARQ, backbone_path, layer_path, seed: int = 0) -> dict:
    """Run both graphs and the torch model on random inputs; returns {name: (max abs diff,
    tolerance)} over all cases.  ``failed(report)`` lists the entries past tolerance."""
    rng = np.random.default_rng(seed)
    c = model.config
    w, h = c.image_size
    options = ort.SessionOptions()
    options.log_severity_level = 3
    backbone = ort.InferenceSession(str(backbone_path), options,
                                    providers=["CPUExecutionProvider"])
    layer = ort.InferenceSession(str(layer_path), options, providers=["CPUExecutionProvider"])
    report: dict = {}

    def note(name, diff, tol):
        old = report.get(name, (0.0, tol))
        report[name] = (max(old[0], diff), tol)

    # (views encoded earlier, new views, queries); the graphs were traced with 3 views and
    # the learned query count.
    cases = ((0, 2, 7), (1, 3, min(c.num_queries + 44, 1024)))
    for cached_views, new_views, queries in cases:
        views = cached_views + new_views
        images = rng.integers(0, 256, (views, h, w, 3), dtype=np.uint8)
        camera, T_local_camera = random_snippet(rng, views, c)
        with torch.no_grad():
            ref_features = model.image_features(
                torch.from_numpy(images).permute(0, 3, 1, 2)[None].float() / 255.0)[0]
            ref_memory = model.memory(ref_features[None], torch.from_numpy(camera)[None],
                                      torch.from_numpy(T_local_camera)[None])[0]
        cached_features = ref_features[:cached_views].numpy()
        feeds = {"images": images[cached_views:], "cached_features": cached_features,
                 "camera": camera, "T_local_camera": T_local_camera}
        query = rng.normal(0, 1, (queries, c.feature_dim)).astype(np.float32)
        points = rng.uniform(0.05, 0.95, (queries, 3)).astype(np.float32)
        for cached_form in (True, False):
            outs = dict(zip([o.name for o in backbone.get_outputs()],
                            backbone.run(None, {**feeds, "key_value": np.array(cached_form)})))
            tokens = ref_memory.reshape(1, -1, c.feature_dim)
            with torch.no_grad():
                ref_ops = model.layer.attention_operands(tokens, cached=cached_form)
                ref_ops = [ref_ops[0][0], ref_ops[1][0], *ref_ops[2:]]
                expected = {"features": ref_features[cached_views:], "memory": ref_memory,
                            **dict(zip(OPERAND_NAMES, ref_ops))}
            for name, ref in expected.items():
                ref = ref.detach().numpy()
                got = outs[name]
                if not cached_form and name in ("attention_keys", "attention_values"):
                    got, ref = got.size, 0  # folded form: empty, the memory is used instead
                    note(f"backbone.{name} (folded, empty)", float(got != ref), 0.0)
                    continue
                if np.shape(got) != np.shape(ref):
                    note(f"backbone.{name} shape", float("inf"), 0.0)
                    continue
                scale = max(1.0, float(np.abs(ref).max()) if ref.size else 1.0)
                note(f"backbone.{name}", _max_abs(got, ref), RELATIVE_TOLERANCE[name] * scale)
            operands = [outs[n] for n in OPERAND_NAMES]
            if not cached_form:
                operands[0] = operands[1] = outs["memory"].reshape(1, -1, c.feature_dim)
            got = dict(zip(LAYER_OUTPUTS, layer.run(None, dict(zip(
                ("query_content", "reference_points") + OPERAND_NAMES,
                [query, points] + operands)))))
            with torch.no_grad():
                ref = model.layer(torch.from_numpy(query)[None], torch.from_numpy(points)[None],
                                  memory=tokens)
            form = "cached" if cached_form else "folded"
            logits = ref["logits"][0].numpy()
            top2 = np.sort(logits, -1)[:, -2:]
            clear = (top2[:, 1] - top2[:, 0]) > 1e-3
            for name in LAYER_OUTPUTS:
                r = ref[name][0].numpy()
                if name == "size":
                    diff = float(np.max(np.abs(got[name][clear] / r[clear] - 1), initial=0.0))
                else:
                    diff = _max_abs(got[name], r)
                note(f"layer.{name} ({form})", diff, ABSOLUTE_TOLERANCE[name])
    return report


def failed(report: dict) -> list:
    return [name for name, (diff, tol) in report.items() if not diff <= tol]


def quantization_error(backbone_path, feeds: list, model: PARQ) -> dict:
    """Max abs difference of the (quantized) backbone's memory from the torch model's."""
    session = ort.InferenceSession(str(backbone_path), providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    worst, scale = 0.0, 0.0
    for feed in feeds:
        memory = dict(zip(names, session.run(None, feed)))["memory"]
        with torch.no_grad():
            x = torch.from_numpy(feed["images"]).permute(0, 3, 1, 2)[None].float() / 255.0
            ref = model.memory(model.image_features(x), torch.from_numpy(feed["camera"])[None],
                               torch.from_numpy(feed["T_local_camera"])[None])[0].numpy()
        worst = max(worst, _max_abs(memory, ref))
        scale = max(scale, float(np.abs(ref).max()))
    return {"memory": worst, "memory_relative": worst / max(scale, 1e-12)}
