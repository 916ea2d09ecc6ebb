"""The paper's objective (Sec. 3.4), applied at every iteration.

Matching, per snippet and iteration: the Hungarian algorithm on
0.25 * L1(reference point, target center) - 2 * p(target class), plus every query whose
reference point lies within 0.2 m (L1) of a target's center is matched to that target too (at
most 10 per target, the nearest), a query keeping its Hungarian partner if it has one.  The
reference point is the one the iteration started from, as in the authors' matcher.

Losses on matched queries: L1 on centers and sizes (weight 5 each), L2 on rotation matrices
(weight 5; for symmetric shapes the smallest over the symmetric turns about the up axis),
cross entropy on classes for all queries with the no-object class weighted 0.1 (weight 1).
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

WEIGHTS = {"center": 5.0, "size": 5.0, "rotation": 5.0, "class": 1.0}
NO_OBJECT_WEIGHT = 0.1
PROXIMITY = 0.2
MAX_PROXIMITY_MATCHES = 10


def match(reference: torch.Tensor, prob: torch.Tensor, centers: torch.Tensor,
          labels: torch.Tensor) -> tuple:
    """(query indices, target indices) for one snippet; reference (K, 3) metres, prob
    (K, C + 1), centers (M, 3), labels (M,)."""
    if len(labels) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    with torch.no_grad():
        distance = torch.cdist(reference.double(), centers.double(), p=1)      # (K, M)
        cost = 0.25 * distance - 2.0 * prob[:, labels].double()
    rows, cols = linear_sum_assignment(cost.numpy())
    queries, targets = list(rows), list(cols)
    taken = set(rows.tolist())
    d = distance.numpy()
    for j in range(len(labels)):
        near = np.flatnonzero(d[:, j] < PROXIMITY)
        near = near[np.argsort(d[near, j], kind="stable")][:MAX_PROXIMITY_MATCHES]
        for q in near:
            if q not in taken:
                taken.add(int(q))
                queries.append(int(q))
                targets.append(j)
    return np.asarray(queries, np.int64), np.asarray(targets, np.int64)


def rotation_loss(pred: torch.Tensor, target: torch.Tensor, folds: torch.Tensor) -> torch.Tensor:
    """Mean squared error of rotation matrices (M, 3, 3), minimised over the ``folds``-fold
    symmetric turns of each target about its up (y) axis (folds 1: no symmetry; a round
    object uses 36, as the authors)."""
    n = folds.to(torch.float32)[:, None]                                  # (M, 1)
    k = torch.arange(int(folds.max()), dtype=torch.float32)[None]         # (1, F)
    angle = 2 * math.pi * torch.remainder(k, n) / n                       # (M, F)
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(c), torch.ones_like(c)
    turns = torch.stack([torch.stack([c, zero, s], -1), torch.stack([zero, one, zero], -1),
                         torch.stack([-s, zero, c], -1)], -2)             # (M, F, 3, 3)
    candidates = target[:, None] @ turns
    return ((pred[:, None] - candidates) ** 2).mean((-1, -2)).min(1).values.mean()


def box_losses(out: dict, b: int, q, target: dict, t, folds_of_class: torch.Tensor) -> dict:
    """L1 center, L1 size and rotation loss of batch item b's queries ``q`` against its
    targets ``t`` (index arrays of one length, at least 1)."""
    return {"center": (out["center"][b][q] - target["centers"][t]).abs().mean(),
            "size": (out["size"][b][q] - target["sizes"][t]).abs().mean(),
            "rotation": rotation_loss(out["rotation"][b][q], target["rotations"][t],
                                      folds_of_class[target["labels"][t]])}


def snippet_loss(out: dict, b: int, target: dict, folds_of_class: torch.Tensor,
                 num_classes: int) -> dict:
    """Losses of one iteration's outputs for batch item b."""
    logits = out["logits"][b]
    prob = logits.detach().softmax(-1)
    q, t = match(out["reference"][b].detach(), prob, target["centers"], target["labels"])
    classes = torch.full((logits.shape[0],), num_classes, dtype=torch.long)
    classes[q] = target["labels"][t]
    weight = torch.ones(num_classes + 1)
    weight[num_classes] = NO_OBJECT_WEIGHT
    losses = {"class": F.cross_entropy(logits, classes, weight=weight)}
    if len(q):
        losses.update(box_losses(out, b, q, target, t, folds_of_class))
    else:
        zero = logits.sum() * 0
        losses.update(center=zero, size=zero, rotation=zero)
    return losses


def total_loss(outputs: list, targets: list, folds_of_class: torch.Tensor,
               num_classes: int, weights: dict | None = None) -> tuple:
    """Weighted sum averaged over iterations and snippets; also returns the parts (unweighted).
    ``weights`` replaces some of WEIGHTS (e.g. ``{"center": 10.0}``); the matching is the
    same whatever the weights."""
    weights = dict(WEIGHTS, **(weights or {}))
    parts = {k: 0.0 for k in WEIGHTS}
    n = 0
    for out in outputs:
        for b, target in enumerate(targets):
            losses = snippet_loss(out, b, target, folds_of_class, num_classes)
            for k in WEIGHTS:
                parts[k] = parts[k] + losses[k]
            n += 1
    parts = {k: v / n for k, v in parts.items()}
    total = sum(weights[k] * parts[k] for k in WEIGHTS)
    return total, {k: float(v.detach()) for k, v in parts.items()}
