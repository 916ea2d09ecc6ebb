"""Which reference points a run starts from, for any number of queries.

* the learned count: the learned points, in their stored order (bit-identical to the authors);
* fewer: farthest-point sampling among the learned points in the normalised decoder box,
  starting from point 0, kept in stored order.  Deterministic, and it spreads the queries over
  the box the way the full set is spread (the first K stored points, by contrast, are an
  arbitrary subset);
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


def reference_points(learned: np.ndarray, queries: int) -> np.ndarray:
    """(queries, 3) normalised reference points from the learned ones (K, 3)."""
    K = len(learned)
    if queries == K:
        return learned.copy()
    if queries < K:
        return learned[farthest_point_sampling(learned, queries)]
    rng = np.random.Generator(np.random.PCG64(EXTRA_POINTS_SEED))
    return np.concatenate([learned, rng.uniform(0.0, 1.0, (queries - K, 3))])
