"""Denoising queries (DN-DETR, Li et al. 2022): a training-only addition to the paper's
objective, which PARQ itself does not use.

Each step, every target of a snippet gets one extra query whose reference point is its center
moved by a random offset of up to ``scale`` times its half extent along each local axis
(horizontally the larger of its width and depth, since the box turns about the up axis).  The
query runs through the same recurrent iterations as the learned ones (``PARQ.forward``'s
``extra_points``) and is supervised, at every iteration, with the same losses as a matched
query but against the target it was made from: no matching decides its target, so from the
first step every object teaches the layer to move a point that lies on it to its center and
(unless the class weight is 0) to name it.  The learned queries cannot see these (a self-attention mask) and run time has
none of them: the exported graphs are unchanged.

Shapes: B snippets, D = the most targets of a snippet in the batch; snippets with fewer
targets pad their rows with points that carry no loss (index -1).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from parq_export.ray_encoding import normalize_points

from .loss import WEIGHTS, box_losses


def noised_queries(targets: list, decoder_scale, rng: np.random.Generator,
                   scale: float) -> tuple:
    """targets: per snippet a dict with ``centers`` and ``sizes`` (M, 3), local frame, metres
    -> points (B, D, 3) normalised to [0, 1]^3 by the decoder scale (clipped to [0.02, 0.98],
    like the learned reference points' initial range) and index (B, D) int64: the target each
    point was made from, -1 for padding."""
    B = len(targets)
    D = max([len(t["centers"]) for t in targets] + [1])
    points = torch.from_numpy(rng.uniform(0.02, 0.98, (B, D, 3))).float()
    index = torch.full((B, D), -1, dtype=torch.long)
    for b, t in enumerate(targets):
        M = len(t["centers"])
        if M == 0:
            continue
        sizes = t["sizes"].double()
        half = torch.stack([sizes[:, [0, 2]].amax(1), sizes[:, 1], sizes[:, [0, 2]].amax(1)],
                           -1) / 2                                             # (M, 3)
        offset = torch.from_numpy(rng.uniform(-1.0, 1.0, (M, 3))) * scale * half
        noisy = normalize_points(t["centers"].double() + offset, decoder_scale)
        points[b, :M] = noisy.clamp(0.02, 0.98).float()
        index[b, :M] = torch.arange(M)
    return points, index


def denoise_loss(outputs: list, index: torch.Tensor, targets: list,
                 folds_of_class: torch.Tensor, class_weight: float = 1.0) -> tuple:
    """The matched-query losses of the denoising queries, averaged over iterations and
    snippets with targets, the class term scaled by ``class_weight`` (0: boxes only; see
    docs/demo-experiments.md for why that is the next thing to try).  outputs: per iteration
    a dict of the D denoising queries' outputs ((B, D, ...) each); returns (weighted sum,
    parts as floats, unscaled)."""
    rows = []   # (snippet, its denoising queries that have a target, those targets), once
    for b in range(len(targets)):
        q = torch.nonzero(index[b] >= 0).flatten()
        if len(q):
            rows.append((b, q, index[b, q]))
    parts = {k: 0.0 for k in WEIGHTS}
    n = 0
    for out in outputs:
        for b, q, t in rows:
            target = targets[b]
            losses = box_losses(out, b, q, target, t, folds_of_class)
            losses["class"] = F.cross_entropy(out["logits"][b][q], target["labels"][t])
            for k in WEIGHTS:
                parts[k] = parts[k] + losses[k]
            n += 1
    if n == 0:
        zero = outputs[0]["logits"].sum() * 0
        return zero, {k: 0.0 for k in WEIGHTS}
    parts = {k: v / n for k, v in parts.items()}
    scale = dict(WEIGHTS, **{"class": WEIGHTS["class"] * class_weight})
    total = sum(scale[k] * parts[k] for k in WEIGHTS)
    return total, {k: float(v.detach()) for k, v in parts.items()}


def split(outputs: list, K: int) -> tuple:
    """Per-iteration outputs of K + D queries -> (the K learned queries', the D denoising
    queries'), tensors sliced along the query axis."""
    learned = [{k: v[:, :K] for k, v in out.items()} for out in outputs]
    noised = [{k: v[:, K:] for k, v in out.items()} for out in outputs]
    return learned, noised
