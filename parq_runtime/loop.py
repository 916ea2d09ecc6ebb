"""The recurrent loop: numpy samples the query content, layer.onnx runs one PARQ iteration.

Per iteration l, with reference points x_l (K, 3) normalised to the decoder box:
  points_local = denormalise(x_l)                     metres, local frame
  query_content = pixel_aligned(memory, points_local)  (K, C), bilinear, averaged over views
  box parameters, x_{l+1} = layer(query_content, x_l, attention operands)
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import geometry

OPERAND_NAMES = ("attention_keys", "attention_values", "key_map", "value_map", "value_bias")
LAYER_OUTPUTS = ("center", "size", "ortho6d", "rotation", "logits", "next_reference_points")


@dataclass
class Iteration:
    """Outputs of one iteration for every query, before any filtering, in the local frame:
    reference (K, 3) the point it started from (metres), center (K, 3) metres, size (K, 3)
    full extents in metres, ortho6d (K, 6), rotation (K, 3, 3) = R_local_object, logits
    (K, classes + 1), the last column being no-object."""

    reference: np.ndarray
    center: np.ndarray
    size: np.ndarray
    ortho6d: np.ndarray
    rotation: np.ndarray
    logits: np.ndarray


def denormalize(points: np.ndarray, scale) -> np.ndarray:
    """[0, 1]^3 -> metres in the local frame; scale = [xmin, xmax, ymin, ymax, zmin, zmax]."""
    scale = np.asarray(scale, dtype=np.float32)
    return points * (scale[1::2] - scale[0::2]) + scale[0::2]


def normalize(points: np.ndarray, scale) -> np.ndarray:
    scale = np.asarray(scale, dtype=np.float64)
    return (points - scale[0::2]) / (scale[1::2] - scale[0::2])


def pixel_aligned_features(memory: np.ndarray, points_local: np.ndarray, camera: np.ndarray,
                           T_camera_local: np.ndarray) -> np.ndarray:
    """Query content (K, C) float32: the memory (N, h, w, C) sampled where points_local (K, 3)
    project with the feature-resolution pinholes camera (N, 4) and poses T_camera_local
    (N, 4, 4).  Bilinear with align_corners=True and zero padding, summed over all views and
    divided by the number of views where the point is valid (at least 1), as the authors do."""
    N, h, w, C = memory.shape
    points_camera = (np.einsum("nij,kj->nki", T_camera_local[:, :3, :3], points_local)
                     + T_camera_local[:, None, :3, 3])
    uv, valid = geometry.project(points_camera, camera[:, None, :], (w, h))
    # Beyond one pixel outside the map every tap is zero; clipping keeps the indices small.
    u = np.clip(uv[..., 0], -2.0, w + 1.0)
    v = np.clip(uv[..., 1], -2.0, h + 1.0)
    u0 = np.floor(u)
    v0 = np.floor(v)
    fu = (u - u0).astype(np.float32)
    fv = (v - v0).astype(np.float32)
    u0 = u0.astype(np.int64)
    v0 = v0.astype(np.int64)
    view = np.arange(N)[:, None]
    indices, weights = [], []
    for du, dv, weight in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)),
                           (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = u0 + du, v0 + dv
        inside = (uu >= 0) & (uu <= w - 1) & (vv >= 0) & (vv <= h - 1)
        indices.append((view * h + np.clip(vv, 0, h - 1)) * w + np.clip(uu, 0, w - 1))
        weights.append(np.where(inside, weight, 0).astype(np.float32))
    indices = np.stack(indices).reshape(4 * N, -1)                   # (4N, K)
    weights = np.stack(weights).reshape(4 * N, -1)
    taps = memory.reshape(-1, C)[indices]                             # (4N, K, C)
    content = np.einsum("gk,gkc->kc", weights, taps)
    count = np.maximum(valid.sum(0), 1).astype(np.float32)
    return (content / count[:, None]).astype(np.float32)


def run(layer_session, memory: np.ndarray, operands: dict, camera: np.ndarray,
        T_camera_local: np.ndarray, reference_points: np.ndarray, iterations: int,
        decoder_scale, timings: list | None = None) -> list:
    """Run ``iterations`` PARQ iterations; returns a list of :class:`Iteration`.

    operands: the attention operands from backbone.onnx; in the folded form (empty keys) the
    memory (1, S, C) takes the place of the keys and values.
    """
    feeds = dict(operands)
    if feeds["attention_keys"].size == 0:
        tokens = memory.reshape(1, -1, memory.shape[-1])
        feeds["attention_keys"] = feeds["attention_values"] = tokens
    ref = np.ascontiguousarray(reference_points, dtype=np.float32)
    out = []
    for _ in range(iterations):
        start = time.perf_counter()
        points_local = denormalize(ref, decoder_scale)
        feeds["query_content"] = pixel_aligned_features(memory, points_local, camera,
                                                        T_camera_local)
        feeds["reference_points"] = ref
        result = dict(zip(LAYER_OUTPUTS, layer_session.run(LAYER_OUTPUTS, feeds)))
        out.append(Iteration(reference=points_local, center=result["center"],
                             size=result["size"], ortho6d=result["ortho6d"],
                             rotation=result["rotation"], logits=result["logits"]))
        ref = result["next_reference_points"]
        if timings is not None:
            timings.append(time.perf_counter() - start)
    return out
