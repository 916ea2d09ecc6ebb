"""The recurrent loop: numpy samples the query content, layer.onnx runs one PARQ iteration.

Per iteration l, with reference points x_l (K, 3) normalised to the decoder box:
  points_local = denormalise(x_l)                        metres, local frame
  query content = sample(memory or its factors, points_local)   bilinear, averaged over views
  box parameters, x_{l+1} = layer(query content, x_l, attention operands, factors)

backbone.onnx always returns the memory's factors, the FPN levels P2..P5 at their own
resolution and the ray MLP's hidden layer (``parq_export.factored``).  In the folded form the
memory is never formed: the loop samples the factors (``sample_factors``) and the layer applies
the ray MLP's last linear layer to the sampled hidden values.  In the cached form the backbone
forms the memory once anyway, to project the keys and values, and returns it: the loop samples
it directly (``sample_memory``: 4 taps of C channels instead of 52 taps of the factors).
"""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
import onnxruntime as ort

from . import geometry, sessions

OPERAND_NAMES = ("attention_keys", "attention_values")
MEMORY_NAME = "memory"
FACTOR_NAMES = ("level_0", "level_1", "level_2", "level_3", "ray_hidden")
QUERY_NAMES = ("query_features", "query_ray_hidden", "query_weight")
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


@functools.lru_cache(maxsize=32)
def resize_taps(size_out: int, size_in: int) -> tuple:
    """Bilinear resize along one axis, align_corners=False (F.interpolate's rule): output
    index i reads inputs lo[i] and hi[i] with weights 1 - frac[i] and frac[i].  Cached (a
    model has three coarse levels on two axes) and returned read-only."""
    src = np.maximum((np.arange(size_out) + 0.5) * (size_in / size_out) - 0.5, 0.0)
    lo = np.floor(src).astype(np.int64)
    hi = np.minimum(lo + 1, size_in - 1)
    taps = lo, hi, (src - lo).astype(np.float32)
    for a in taps:
        a.flags.writeable = False
    return taps


def _gather(tokens: np.ndarray, view, row, col, weight) -> np.ndarray:
    """sum over taps g of weight[g, k] * tokens[view[g], row[g, k], col[g, k]]: (K, X)."""
    N, h, w, X = tokens.shape
    taps = tokens.reshape(-1, X)[(view * h + row) * w + col]                 # (G, K, X)
    return np.einsum("gk,gkx->kx", weight, taps)


def _taps(points_local: np.ndarray, camera: np.ndarray, T_camera_local: np.ndarray,
          size: tuple) -> tuple:
    """Bilinear taps (align_corners=True, zero padding) on the (h, w) = size feature grid of
    every view where points_local (K, 3) project with the feature-resolution pinholes camera
    (N, 4) and poses T_camera_local (N, 4, 4).  Returns views, rows, cols, weights (4N, K)
    (weight 0 outside the map) and count (K, 1): the number of views where the point is
    valid, at least 1."""
    h, w = size
    N = len(camera)
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
    view = np.broadcast_to(np.arange(N)[:, None], u0.shape)
    rows, cols, weights = [], [], []
    for du, dv, weight in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)),
                           (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = u0 + du, v0 + dv
        inside = (uu >= 0) & (uu <= w - 1) & (vv >= 0) & (vv <= h - 1)
        rows.append(np.clip(vv, 0, h - 1))
        cols.append(np.clip(uu, 0, w - 1))
        weights.append(np.where(inside, weight, 0).astype(np.float32))
    count = np.maximum(valid.sum(0), 1).astype(np.float32)[:, None]
    return (np.concatenate([view] * 4), np.concatenate(rows), np.concatenate(cols),
            np.concatenate(weights), count)


def sample_memory(memory: np.ndarray, points_local: np.ndarray, camera: np.ndarray,
                  T_camera_local: np.ndarray) -> dict:
    """The query content for the cached form: the memory (N, h, w, C) sampled bilinearly
    (align_corners=True, zero padding) where points_local (K, 3) project, summed over all
    views and divided by the number of views where the point is valid (at least 1), as the
    authors do.  Returned as query_features (K, C), all that the cached form of layer.onnx
    reads of the content (:func:`run` feeds zeros for the other factors)."""
    _, h, w, _ = memory.shape
    views, rows, cols, weights, count = _taps(points_local, camera, T_camera_local, (h, w))
    return {"query_features": (_gather(memory, views, rows, cols, weights) / count)
            .astype(np.float32)}


def sample_factors(factors: dict, points_local: np.ndarray, camera: np.ndarray,
                   T_camera_local: np.ndarray) -> dict:
    """The query content's factors for the folded form: the same sample as
    :func:`sample_memory`, taken of each factor.  query_features (K, C) the concatenated
    levels, each coarse level read through its resize to P2's grid; query_ray_hidden (K, C)
    the ray MLP's hidden layer; query_weight (K, 1) the sum of the weights (for the MLP's
    bias)."""
    level_0 = factors["level_0"]
    _, h, w, _ = level_0.shape
    views, rows, cols, weights, count = _taps(points_local, camera, T_camera_local, (h, w))
    features = [_gather(level_0, views, rows, cols, weights)]
    for name in FACTOR_NAMES[1:-1]:
        level = factors[name]
        _, hl, wl, _ = level.shape
        lo_r, hi_r, fr = resize_taps(h, hl)
        lo_c, hi_c, fc = resize_taps(w, wl)
        # each tap on P2's grid reads 2 x 2 taps of the level: (4N, K) -> (16N, K)
        a, b = fr[rows], fc[cols]
        sub_rows = np.concatenate([lo_r[rows], lo_r[rows], hi_r[rows], hi_r[rows]])
        sub_cols = np.concatenate([lo_c[cols], hi_c[cols], lo_c[cols], hi_c[cols]])
        sub_weights = np.concatenate([(1 - a) * (1 - b), (1 - a) * b, a * (1 - b), a * b]) \
            * np.concatenate([weights] * 4)
        features.append(_gather(level, np.concatenate([views] * 4), sub_rows, sub_cols,
                                sub_weights))
    return {"query_features": (np.concatenate(features, -1) / count).astype(np.float32),
            "query_ray_hidden": (_gather(factors["ray_hidden"], views, rows, cols, weights)
                                 / count).astype(np.float32),
            "query_weight": (weights.sum(0)[:, None] / count).astype(np.float32)}


# Inputs of at least this many elements stay on the accelerator for the whole snippet.
DEVICE_RESIDENT_ELEMENTS = 1 << 16


class LayerRunner:
    """layer.onnx over one snippet's iterations.  ``constant``: the inputs that do not change
    between iterations (the factors, the attention keys and values: up to 2 x 59 MB each in
    the authors' configuration).

    On the CPU a plain ``session.run``.  On an accelerator (a session whose first provider is
    not the CPU's), or with ``bind=True``, an onnxruntime IOBinding: the large constant inputs
    are copied to the device once per snippet, not at every iteration (inputs given as
    ``OrtValue`` are on it already: the backbone's keys and values, see Detector.encode), and
    only the queries' inputs (K x C) and outputs cross to and from the host."""

    def __init__(self, session, constant: dict, bind: bool | None = None):
        self.session = session
        device, device_id = sessions.device(session)
        self.binding = None
        if bind is None:
            bind = device != "cpu"
        if not bind:
            self.constant = constant
            return
        self.binding = session.io_binding()
        self.resident = []      # keeps the device copies alive as long as the binding
        for name, value in constant.items():
            if isinstance(value, ort.OrtValue):     # already where the session runs
                self.resident.append(value)
                self.binding.bind_ortvalue_input(name, value)
                continue
            value = np.ascontiguousarray(value)
            if value.size >= DEVICE_RESIDENT_ELEMENTS:
                resident = ort.OrtValue.ortvalue_from_numpy(value, device, device_id)
                self.resident.append(resident)
                self.binding.bind_ortvalue_input(name, resident)
            else:
                self.binding.bind_cpu_input(name, value)
        for name in LAYER_OUTPUTS:
            self.binding.bind_output(name, "cpu")

    def __call__(self, varying: dict) -> dict:
        if self.binding is None:
            return dict(zip(LAYER_OUTPUTS, self.session.run(LAYER_OUTPUTS,
                                                            {**self.constant, **varying})))
        for name, value in varying.items():
            self.binding.bind_cpu_input(name, np.ascontiguousarray(value))
        self.session.run_with_iobinding(self.binding)
        return dict(zip(LAYER_OUTPUTS, self.binding.copy_outputs_to_cpu()))


def run(layer_session, factors: dict, operands: dict, camera: np.ndarray,
        T_camera_local: np.ndarray, reference_points: np.ndarray, iterations: int,
        decoder_scale, cached: bool, timings: list | None = None,
        bind: bool | None = None) -> list:
    """Run ``iterations`` PARQ iterations; returns a list of :class:`Iteration`.

    factors, operands: backbone.onnx's outputs (``FACTOR_NAMES``; ``OPERAND_NAMES`` and
    ``MEMORY_NAME``); cached: the form they were computed for (the keys, values and memory are
    empty in the folded form); bind: see :class:`LayerRunner` (None: on accelerators only)."""
    memory = operands[MEMORY_NAME]                   # numpy: the loop samples it
    constant = {**factors, **{n: operands[n] for n in OPERAND_NAMES},
                "key_value": np.array(cached)}
    ref = np.ascontiguousarray(reference_points, dtype=np.float32)
    if cached:   # inputs the cached form ignores: set once, and no views of the factors
        constant["query_ray_hidden"] = np.zeros((len(ref), memory.shape[-1]), np.float32)
        constant["query_weight"] = np.zeros((len(ref), 1), np.float32)
        constant.update({n: np.zeros((0,) + factors[n].shape[1:], np.float32)
                         for n in FACTOR_NAMES})
    start = time.perf_counter()     # the first iteration's time includes the uploads
    layer = LayerRunner(layer_session, constant, bind)
    out = []
    for i in range(iterations):
        if i > 0:
            start = time.perf_counter()
        points_local = denormalize(ref, decoder_scale)
        if cached:
            feeds = sample_memory(memory, points_local, camera, T_camera_local)
        else:
            feeds = sample_factors(factors, points_local, camera, T_camera_local)
        feeds["reference_points"] = ref
        result = layer(feeds)
        out.append(Iteration(reference=points_local, center=result["center"],
                             size=result["size"], ortho6d=result["ortho6d"],
                             rotation=result["rotation"], logits=result["logits"]))
        ref = result["next_reference_points"]
        if timings is not None:
            timings.append(time.perf_counter() - start)
    return out
