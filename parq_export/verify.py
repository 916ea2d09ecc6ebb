"""Check exported graphs against the torch model on random inputs.

The check runs at shapes other than the ones the graphs were traced with (other view counts,
query counts, a streaming call with cached levels) and in both forms of the attention.
Tolerances are those of ``../shared/golden/README.md`` for the box parameters; intermediate
tensors are compared relative to their magnitude.
"""
from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch

from parq_runtime import geometry

from . import factored
from .backbone import concat_levels
from .graphs import FACTOR_NAMES, LAYER_OUTPUTS, MEMORY_NAME, OPERAND_NAMES, QUERY_NAMES
from .model import PARQ

# max abs difference allowed, as a fraction of the reference's largest magnitude (at least 1)
RELATIVE_TOLERANCE = {"level_0": 1e-4, "level_1": 1e-4, "level_2": 1e-4, "level_3": 1e-4,
                      "ray_hidden": 1e-4, "memory": 1e-4, "attention_keys": 1e-4,
                      "attention_values": 1e-4}
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


def reference_factors(model: PARQ, images: np.ndarray, camera: np.ndarray,
                      T_local_camera: np.ndarray) -> dict:
    """The torch model's factors of the memory (``parq_export.factored``) for one snippet:
    level_0..3 (N, h_l, w_l, F), ray_hidden (N, h, w, C), and the memory (N, h, w, C)."""
    with torch.no_grad():
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0
        levels = model.backbone.levels(x)
        hidden = model.ray_encoder.hidden(torch.from_numpy(camera),
                                          torch.from_numpy(T_local_camera))
        # the backbone's forward from the same levels (one ResNet-FPN pass, not two)
        memory = model.memory(concat_levels(levels)[None], torch.from_numpy(camera)[None],
                              torch.from_numpy(T_local_camera)[None])[0]
    out = {f"level_{i}": p.permute(0, 2, 3, 1) for i, p in enumerate(levels)}
    return {**out, "ray_hidden": hidden, "memory": memory}


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

    def compare(name, got, ref):
        if np.shape(got) != np.shape(ref):
            note(f"{name} shape", float("inf"), 0.0)
            return
        scale = max(1.0, float(np.abs(ref).max()) if np.size(ref) else 1.0)
        note(name, _max_abs(got, ref), RELATIVE_TOLERANCE[name.split(".")[-1]] * scale)

    # (views encoded earlier, new views, queries); the graphs were traced with 3 views and
    # the learned query count.
    cases = ((0, 2, 7), (1, 3, min(c.num_queries + 44, 1024)))
    for cached_views, new_views, queries in cases:
        views = cached_views + new_views
        images = rng.integers(0, 256, (views, h, w, 3), dtype=np.uint8)
        camera, T_local_camera = random_snippet(rng, views, c)
        ref = reference_factors(model, images, camera, T_local_camera)
        feeds = {"images": images[cached_views:], "camera": camera,
                 "T_local_camera": T_local_camera,
                 **{f"cached_{n}": ref[n][:cached_views].numpy() for n in FACTOR_NAMES[:-1]}}
        tokens = ref["memory"].reshape(1, -1, c.feature_dim)
        query = {"query_features": rng.normal(0, 1, (queries, c.feature_dim)),
                 "query_ray_hidden": np.abs(rng.normal(0, 1, (queries, c.feature_dim))),
                 "query_weight": rng.uniform(0, 1, (queries, 1))}
        query = {k: v.astype(np.float32) for k, v in query.items()}
        points = rng.uniform(0.05, 0.95, (queries, 3)).astype(np.float32)
        with torch.no_grad():
            content = factored.content(*(torch.from_numpy(query[n]) for n in QUERY_NAMES),
                                       model.ray_encoder.mlp[2])
            expected = model.layer(content[None], torch.from_numpy(points)[None],
                                   memory=tokens)
            ref_keys, ref_values, *_ = model.layer.attention_operands(tokens, cached=True,
                                                                       token_bias=False)
        for cached_form in (True, False):
            outs = dict(zip([o.name for o in backbone.get_outputs()],
                            backbone.run(None, {**feeds, "key_value": np.array(cached_form)})))
            for name in FACTOR_NAMES:
                compare(f"backbone.{name}", outs[name], ref[name].numpy())
            layer_query = query
            if cached_form:
                compare("backbone.memory", outs[MEMORY_NAME], ref["memory"].numpy())
                compare("backbone.attention_keys", outs["attention_keys"], ref_keys[0].numpy())
                compare("backbone.attention_values", outs["attention_values"],
                        ref_values[0].numpy())
                # the cached form's content is query_features alone (the sampled memory);
                # the factors stay in the feed, and must be ignored
                layer_query = dict(query, query_features=content.numpy())
            else:
                empty = sum(outs[n].size for n in (MEMORY_NAME,) + OPERAND_NAMES)
                note("backbone.memory, keys, values (folded, empty)", float(empty), 0.0)
            got = dict(zip(LAYER_OUTPUTS, layer.run(None, {
                **layer_query, "reference_points": points, "key_value": np.array(cached_form),
                **{n: outs[n] for n in OPERAND_NAMES + FACTOR_NAMES}})))
            form = "cached" if cached_form else "folded"
            logits = expected["logits"][0].numpy()
            top2 = np.sort(logits, -1)[:, -2:]
            clear = (top2[:, 1] - top2[:, 0]) > 1e-3
            for name in LAYER_OUTPUTS:
                r = expected[name][0].numpy()
                if name == "size":
                    diff = float(np.max(np.abs(got[name][clear] / r[clear] - 1), initial=0.0))
                else:
                    diff = _max_abs(got[name], r)
                note(f"layer.{name} ({form})", diff, ABSOLUTE_TOLERANCE[name])
    return report


def failed(report: dict) -> list:
    return [name for name, (diff, tol) in report.items() if not diff <= tol]


def quantization_error(backbone_path, feeds: list, model: PARQ) -> dict:
    """Max abs difference of the memory formed from the (quantized) backbone's factors from
    the torch model's memory."""
    session = ort.InferenceSession(str(backbone_path), providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    worst, scale = 0.0, 0.0
    for feed in feeds:
        outs = dict(zip(names, session.run(None, feed)))
        with torch.no_grad():
            memory = factored.memory([torch.from_numpy(outs[n]) for n in FACTOR_NAMES[:-1]],
                                     torch.from_numpy(outs["ray_hidden"]),
                                     model.ray_encoder.mlp[2]).numpy()
        ref = reference_factors(model, feed["images"], feed["camera"],
                                feed["T_local_camera"])["memory"].numpy()
        worst = max(worst, _max_abs(memory, ref))
        scale = max(scale, float(np.abs(ref).max()))
    return {"memory": worst, "memory_relative": worst / max(scale, 1e-12)}
