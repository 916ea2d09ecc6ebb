"""Which reference points a run starts from, for any number of queries.

* the learned count: the learned points, in their stored order (bit-identical to the authors);
* fewer, when the model card ranks its learned queries (``query_order``, written by
  ``parq_train.tune`` from validation scenes): the first K of that ranking, kept in stored
  order.  Learned queries are far from equally useful: on the demo's validation scenes the
  best of its 64 made 51 true and 12 false detections, a dozen made none at all, and its 32
  best at 2 iterations scored F1@0.25 / F1@0.5 0.494 / 0.274 against 0.417 / 0.226 for the
  farthest-point subset below (each with its tuned post-processing);
* fewer, with no ranking (the authors' checkpoints): farthest-point sampling among the
  learned points in the normalised decoder box, starting from point 0, kept in stored order.
  Deterministic, and it spreads the queries over the box the way the full set is spread (the
  first K stored points, by contrast, are an arbitrary subset);
* more: all learned points, then points drawn uniformly in the decoder box (normalised
  [0, 1]^3) from numpy's PCG64 with seed 0.

The order of the queries does not change any box: the layer is permutation-equivariant over
queries (self-attention, and GroupNorm statistics over all of them).
"""
from __future__ import annotations

import numpy as np

EXTRA_POINTS_SEED = 0


def farthest_point_sampling(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of k points (sorted), chosen greedily farthest from those already chosen,
    starting with point 0."""
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=-1)
    for _ in range(1, k):
        i = int(np.argmax(distance))
        chosen.append(i)
        distance = np.minimum(distance, np.linalg.norm(points - points[i], axis=-1))
    return np.sort(np.asarray(chosen, dtype=np.int64))


def reference_points(learned: np.ndarray, queries: int,
                     order: np.ndarray | None = None) -> np.ndarray:
    """(queries, 3) normalised reference points from the learned ones (K, 3); ``order``: the
    learned queries' indices, most useful first (None: farthest-point sampling)."""
    K = len(learned)
    if queries == K:
        return learned.copy()
    if queries < K:
        if order is not None:
            return learned[np.sort(np.asarray(order)[:queries])]
        return learned[farthest_point_sampling(learned, queries)]
    rng = np.random.Generator(np.random.PCG64(EXTRA_POINTS_SEED))
    return np.concatenate([learned, rng.uniform(0.0, 1.0, (queries - K, 3))])
