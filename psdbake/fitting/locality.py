"""Which joints can explain a point's corrective: locality read from the asset's own skinning.

A point's corrective is driven by the joints that change how it deforms (``explaining_joints``):

- its influences I(v): the joints whose ``jointWeights`` on it exceed ``tol.INFLUENCE_WEIGHT_MIN``;
- their children: the next joint's bend is what bulges a bone's flesh (the elbow's bend drives the
  biceps, skinned to the shoulder);
- the joints on the hierarchy paths between its influences, below their lowest common ancestor:
  their local rotations change the influences' transforms relative to each other, hence the blend.

Only joints that some example moves count. So the drivers of a corrective grow with the sculpted
region, never with the skeleton.

The rule is a guess from the rig; the sculpts have the last word (``separate``): when two
example poses (the bind pose among them, with no corrective) agree on every joint of a point's
set but its sculpted offsets differ, no function of those joints can reproduce both, so the
joints in which the two poses differ join the point's set, nearest ones in the hierarchy first.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..errors import FitError
from ..model.rig import Skin

Joints = tuple[int, ...]  # sorted skeleton-order joint indices


def influences(skin: Skin, points: NDArray[np.int64], minimum: float = tol.INFLUENCE_WEIGHT_MIN) -> list[Joints]:
    """Per point of ``points``: its influences I(v), the joints weighted above ``minimum``
    (``tol.INFLUENCE_WEIGHT_MIN``; 0 for every joint that moves it at all)."""
    idx = skin.indices[points]
    kept = np.where((skin.weights[points] > minimum) & (idx >= 0), idx, -1)
    kept.sort(axis=1)
    base = len(skin.parents) + 1
    if kept.shape[1] * np.log2(base) < 62:  # one integer key per row: a 1-D unique, no lexsort
        key = ((kept + 1) * base ** np.arange(kept.shape[1], dtype=np.int64)).sum(axis=1)
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        rows = kept[first]
    else:
        rows, inverse = np.unique(kept, axis=0, return_inverse=True)
    sets = [tuple(sorted({int(j) for j in row if j >= 0})) for row in rows]  # points share a few sets
    return [sets[i] for i in np.asarray(inverse).reshape(-1)]


def rows_by_set(sets: Sequence[Joints]) -> dict[Joints, NDArray[np.int64]]:
    """Each distinct set -> the rows holding it, in row order (one pass over the rows, then numpy)."""
    ids: dict[Joints, int] = {}
    key = np.fromiter((ids.setdefault(s, len(ids)) for s in sets), dtype=np.int64, count=len(sets))
    order = np.argsort(key, kind="stable")
    bounds = np.searchsorted(key[order], np.arange(len(ids) + 1))
    return {s: order[bounds[i]:bounds[i + 1]] for s, i in ids.items()}


def explaining_joints(skin: Skin, own: Sequence[Joints], moved: Sequence[int]) -> list[Joints]:
    """Per point: the moved joints that can explain its corrective (sorted), from its
    influences ``own`` (``influences``)."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(skin.parents):
        if p >= 0:
            children.setdefault(int(p), []).append(j)
    moving = set(int(j) for j in moved)
    cache: dict[Joints, Joints] = {}
    out = []
    for mine in own:
        if mine not in cache:
            found = set(mine)
            for j in mine:
                found.update(children.get(j, ()))
            found.update(_between(mine, skin.parents))
            cache[mine] = tuple(sorted(found & moving))
        out.append(cache[mine])
    return out


def ancestors(j: int, parents: NDArray[np.int64]) -> list[int]:
    """j and its ancestors, j first."""
    out = []
    while j >= 0:
        out.append(j)
        j = int(parents[j])
    return out


def _between(influences: Joints, parents: NDArray[np.int64]) -> set[int]:
    """The joints on the paths from each influence up to (not including) their lowest common ancestor."""
    if len(influences) < 2:
        return set()
    chains = [ancestors(j, parents) for j in influences]
    common = set(chains[0]).intersection(*chains[1:])
    return {a for chain in chains for a in chain if a not in common}


def tree_distances(start: Sequence[int], parents: NDArray[np.int64]) -> NDArray[np.int64]:
    """Edges from the nearest joint of ``start`` to every joint of the skeleton (large: unreachable)."""
    count = len(parents)
    near: dict[int, list[int]] = {j: [] for j in range(count)}
    for j, p in enumerate(parents):
        if p >= 0:
            near[j].append(int(p))
            near[int(p)].append(j)
    dist = np.full(count, np.iinfo(np.int64).max // 2, dtype=np.int64)
    queue = deque(int(j) for j in start)
    for j in queue:
        dist[j] = 0
    while queue:
        j = queue.popleft()
        for k in near[j]:
            if dist[k] > dist[j] + 1:
                dist[k] = dist[j] + 1
                queue.append(k)
    return dist


def separate(sets: list[Joints], anchors: Sequence[Joints], coords: NDArray[np.float64], data: NDArray[np.float64],
             parents: NDArray[np.int64], moved: Sequence[int], atol: float, labels: Sequence[str], where_: str
             ) -> list[Joints]:
    """The points' joint sets grown until they tell apart every two poses whose sculpts differ.

    sets: per point (rows of ``data``) its joints, anchors its influences (where the hierarchy
    distance is measured from while its set is empty); coords: (K, J, w) every example's pose
    coordinates; data: (K, n, c) the examples' rest-space offsets at the points. Two poses agree on
    a set when their coordinates on it are within ``tol.DUPLICATE_POSE_ATOL``; the bind pose (zero
    coordinates, zero offsets) is one of them. Where they agree and a point's offsets differ by
    more than atol, the moved joints in which the poses differ, nearest the point's set in the
    hierarchy, join it; repeated until nothing changes."""
    sets = list(sets)
    moving = np.zeros(coords.shape[1], dtype=bool)
    moving[list(moved)] = True
    poses = np.concatenate([np.zeros((1, *coords.shape[1:])), coords])  # bind first
    offsets = np.concatenate([np.zeros((1, *data.shape[1:])), data])
    for _ in range(coords.shape[1] + 1):
        grown = False
        for joints, points in sorted(rows_by_set(sets).items()):
            for members in _agreeing(poses, joints):
                mine = offsets[np.ix_(np.asarray(members, dtype=np.int64), points)]
                spread = np.abs(mine - mine[:1]).max(axis=(0, 2))
                bad = np.nonzero(spread > atol)[0]
                if not len(bad):
                    continue
                differ = np.nonzero(moving & (np.abs(poses[members] - poses[members[0]]).max(axis=(0, 2))
                                              > tol.DUPLICATE_POSE_ATOL))[0]
                if not len(differ):
                    names = [labels[m - 1] if m else "the bind pose" for m in members[:2]]
                    raise FitError(f"{where_}: examples {names[0]} and {names[1]} have the same pose but different "
                                   "sculpts: remove one or merge them")
                start = joints or tuple(sorted({j for b in bad for j in anchors[points[b]]}))
                dist = tree_distances(start, parents)[differ]
                nearest = tuple(int(j) for j in differ[dist == dist.min()])
                grown_to: dict[Joints, Joints] = {}  # the points of a group share a few sets
                for p in points[bad]:
                    now = sets[p]
                    if now not in grown_to:
                        grown_to[now] = tuple(sorted(set(now) | set(nearest)))
                    sets[p] = grown_to[now]
                grown = True
        if not grown:
            return sets
    return sets


def _agreeing(poses: NDArray[np.float64], joints: Joints) -> list[list[int]]:
    """Groups (of two or more) of pose indices whose coordinates on ``joints`` all agree within
    ``tol.DUPLICATE_POSE_ATOL`` (linked pairwise), in index order."""
    x = poses[:, list(joints)].reshape(len(poses), -1)
    seen = np.zeros(len(poses), dtype=bool)
    out = []
    for i in range(len(poses)):
        if seen[i]:
            continue
        members = np.nonzero(~seen & (np.abs(x - x[i]).max(axis=1, initial=0.0) <= tol.DUPLICATE_POSE_ATOL))[0]
        seen[members] = True
        if len(members) > 1:
            out.append([int(m) for m in members])
    return out
