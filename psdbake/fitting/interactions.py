"""What the per-joint terms leave: gated combination terms, solved so that every example is reproduced.

At example k the additive part (``additive``) leaves r_k = d_k - A(x_k): a genuine interaction
of joints, or the ridge's smoothing. For a signature (points sharing the joints J) each example
is keyed by B = the joints of J it moves (``tol.ACTIVE_JOINT_ANGLE``; failing that, the joints
of J it turns at all). A joint sculpted alone is taken as sculpted, so a key made only of such
joints, at an example that moves others too, takes in the nearest of those others in the
hierarchy: what a combination sculpt adds stays off while one joint moves.

Per distinct key B there is one combination group: a cardinal RBF over B's concatenated pose
coordinates with a centre at each distinct pose of B among its examples, multiplied by a gate
that is 1 at those examples and 0 whenever a joint of B is at bind (so it is off while a single
other joint moves). Gates of different groups overlap (a group over
{shoulder, elbow} is on at an example that also bends the wrist), so per signature the
shapes S solve T S = R, T[k, col] the weight of column col at example k (one row and one
column per distinct key pose, ones on the diagonal); then the stack is exact at every example.

A signature whose residual is nowhere above ``tol.RESIDUAL_NEGLIGIBLE_RTOL`` of the diagonal
gets no columns.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..errors import FitError
from .locality import tree_distances

Joints = tuple[int, ...]
Keyed = dict[Joints, list[tuple[int, Joints]]]  # signature -> (example, key B) per keyed example


def keys(signatures: Mapping[Joints, NDArray[np.int64]], active: Sequence[frozenset[int]],
         turned: Sequence[frozenset[int]], residual: NDArray[np.float64], negligible: float, solo: set[int],
         parents: NDArray[np.int64]) -> Keyed:
    """signature -> (example, B) for each example whose key B on it is not empty, for the
    signatures (-> their point rows) whose residual (K, n, c) is not negligible. solo: the
    joints sculpted alone."""
    out: Keyed = {}
    largest = np.abs(residual).max(axis=(0, 2), initial=0.0)  # per point
    for joints, rows in sorted(signatures.items()):
        if not len(rows) or float(largest[rows].max(initial=0.0)) <= negligible:
            continue
        mine = set(joints)
        found = []
        for k in range(len(active)):
            key = tuple(sorted(active[k] & mine)) or tuple(sorted(turned[k] & mine))
            others = sorted(active[k] - set(key))
            if key and set(key) <= solo and others:
                dist = tree_distances(key, parents)[others]
                key = tuple(sorted({*key, *(j for j, d in zip(others, dist, strict=True) if d == dist.min())}))
            if key:
                found.append((k, key))
        if found:
            out[joints] = found
    return out


def centres(keyed: Keyed, coords: NDArray[np.float64]) -> tuple[dict[Joints, list[int]], dict[tuple[Joints, int], int]]:
    """B -> its centre examples (the first example with each distinct pose of B), and
    (B, example) -> the column of that example's pose."""
    found: dict[Joints, list[int]] = {}
    column: dict[tuple[Joints, int], int] = {}
    for _, pairs in sorted(keyed.items()):
        for k, key in pairs:
            if (key, k) in column:
                continue
            mine = found.setdefault(key, [])
            x = coords[k, list(key)].reshape(-1)
            same = [i for i, e in enumerate(mine)
                    if np.abs(coords[e, list(key)].reshape(-1) - x).max() <= tol.DUPLICATE_POSE_ATOL]
            if same:
                column[(key, k)] = same[0]
            else:
                column[(key, k)] = len(mine)
                mine.append(k)
    return {b: found[b] for b in sorted(found, key=lambda b: (len(b), b))}, column


def solve(signatures: Mapping[Joints, NDArray[np.int64]], keyed: Keyed, column: Mapping[tuple[Joints, int], int],
          weights: Mapping[Joints, NDArray[np.float64]], residual: NDArray[np.float64], where_: str
          ) -> dict[Joints, NDArray[np.float64]]:
    """B -> its shapes (L_B, n, c) over every point, solving T S = R per signature.

    weights: B -> (K, L_B) its columns' weights (gates included) at every example."""
    n, c = residual.shape[1:]
    out = {b: np.zeros((w.shape[1], n, c)) for b, w in weights.items()}
    for joints, pairs in sorted(keyed.items()):
        rows = signatures[joints]
        cols: list[tuple[Joints, int]] = []
        examples: list[int] = []
        for k, key in pairs:
            if (key, column[(key, k)]) not in cols:
                cols.append((key, column[(key, k)]))
                examples.append(k)
        t = np.stack([weights[b][examples, col] for b, col in cols], axis=1)
        condition = np.linalg.cond(t)
        if not condition < tol.RBF_COND_MAX:
            raise FitError(f"{where_}: the combination terms over {len(cols)} example poses cannot be solved "
                           f"(condition number {condition:.1e}): examples too alike in the joints they move")
        rhs = residual[np.ix_(np.asarray(examples, dtype=np.int64), rows)].reshape(len(examples), -1)
        shapes = np.linalg.solve(t, rhs).reshape(len(examples), len(rows), c)
        for (b, col), s in zip(cols, shapes, strict=True):
            out[b][col][rows] = s
    return out
