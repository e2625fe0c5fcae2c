"""Is the rig mirror-symmetric? The joint map, the reflection and the partner checks of
``psdbake mirror``.

Joints pair by name (``--joints REGEX=REPLACEMENT`` rules); vertices pair by position (the
vertex nearest to each one's mirror image, ``scipy.spatial.cKDTree``), both in the
skeleton's bind space, reflected through the plane x = 0 (or y, z) there. A rig whose
partners are not mirror images within ``tolerances.MIRROR_JOINT_RTOL`` /
``MIRROR_VERTEX_RTOL`` is refused naming the joints or vertices: mirrored correctives would
silently miss the other side's shape.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from .. import tolerances as tol
from ..errors import InputError, SettingError
from ..lookup import did_you_mean
from ..model.rig import BindSpace

#: Index of each mirror plane's normal axis.
AXES = {"x": 0, "y": 1, "z": 2}


class JointMap:
    """Joint paths (and group names) to their partners: a name takes the first rule whose
    REGEX it contains (``re.search``) and is rewritten by that rule (``re.sub``); a name no
    rule matches maps to itself (it has no partner)."""

    def __init__(self, rules: Sequence[str]) -> None:
        self.rules = [(re.compile(pattern), repl, rule) for rule in rules
                      for pattern, _, repl in [rule.rpartition("=")]]

    def __call__(self, name: str) -> str:
        for pattern, repl, rule in self.rules:
            if pattern.search(name):
                try:
                    return pattern.sub(repl, name)
                except (re.error, IndexError) as exc:
                    raise SettingError("joints", rule, f"REPLACEMENT cannot rewrite {name!r} ({exc})") from None
        return name

    def shown(self) -> str:
        return " ".join(f"{rule!r}" for _, _, rule in self.rules)


def reflection(plane: str) -> NDArray[np.float64]:
    """M: the reflection through the plane x = 0 (y, z) of skeleton space (its own inverse)."""
    m = np.eye(3)
    m[AXES[plane], AXES[plane]] = -1.0
    return m


def partners(drivers: Sequence[str], joints: Sequence[str], jmap: JointMap, where_: str) -> dict[str, str]:
    """driver -> its partner joint: an existing joint, different from the driver, one per driver."""
    out: dict[str, str] = {}
    for joint in drivers:
        why = partner_problem(joint, joints, jmap)
        if why:
            raise InputError(f"{where_}: {why}")
        out[joint] = jmap(joint)
    seen: dict[str, str] = {}
    for joint, partner in out.items():
        if partner in seen:
            raise InputError(f"{where_}: drivers {seen[partner]!r} and {joint!r} both map to {partner!r} under --joints "
                             f"{jmap.shown()}")
        seen[partner] = joint
    return out


def partner_problem(joint: str, joints: Sequence[str], jmap: JointMap) -> str:
    """Why a driver joint has no partner under the map ("" when it has one)."""
    partner = jmap(joint)
    if partner == joint:
        itself = [rule for pattern, _, rule in jmap.rules if pattern.search(joint)]
        folded = [rule for pattern, _, rule in jmap.rules if re.search(pattern.pattern, joint, re.IGNORECASE)]
        hint = (f": {itself[0]!r} maps it to itself" if itself else
                f": {folded[0]!r} matches it only ignoring case (rules are case-sensitive)" if folded else "")
        return f"driver {joint!r} has no partner under --joints {jmap.shown()} (the map leaves it unchanged{hint})"
    if partner not in set(joints):
        return (f"driver {joint!r} maps to {partner!r} under --joints {jmap.shown()}, which is not a joint of the "
                f"skeleton{did_you_mean(partner, [j for j in joints if j != joint])}")
    return ""


def check_joints(bind: BindSpace, pairs: dict[str, str], jmap: JointMap, plane: str, where_: str) -> float:
    """Refuse partners that are not mirror images: each driver and its partner, walking up
    both chains together, must have parents that the map pairs too, and every pair the map
    renames must sit at mirror images of each other's skeleton-space bind positions within
    ``MIRROR_JOINT_RTOL`` of the skeleton's extent. Returns the worst distance (fraction of it)."""
    m = reflection(plane)
    index = {j: i for i, j in enumerate(bind.joints)}
    positions = bind.bind_world[:, 3, :3]
    extent = tol.bbox_diagonal(positions)
    scale = extent if extent > 0 else 1.0
    checked: dict[tuple[str, str], float] = {}
    for joint, partner in sorted(pairs.items()):
        a, b = index[joint], index[partner]
        while a >= 0:
            name_a, name_b = bind.joints[a], bind.joints[b]
            if name_a != name_b:
                checked[(name_a, name_b)] = float(np.linalg.norm(positions[a] @ m - positions[b])) / scale
            pa, pb = int(bind.parents[a]), int(bind.parents[b])
            expected = jmap(bind.joints[pa]) if pa >= 0 else None
            actual = bind.joints[pb] if pb >= 0 else None
            if expected != actual:
                raise InputError(
                    f"{where_} <{bind.skeleton}>: not a mirror-symmetric skeleton: joint {name_b!r} (partner of "
                    f"{name_a!r}) has parent {actual!r}, but {name_a!r}'s parent {bind.joints[pa] if pa >= 0 else None!r} "
                    f"maps to {expected!r} under --joints {jmap.shown()}"
                )
            a, b = pa, pb
    bad = sorted(((d, pair) for pair, d in checked.items() if d > tol.MIRROR_JOINT_RTOL), reverse=True)
    if bad:
        shown = "; ".join(f"{b!r} is {d:.2g} from the mirror image of {a!r}" for d, (a, b) in bad[:4])
        more = f" (and {len(bad) - 4} more pairs)" if len(bad) > 4 else ""
        raise InputError(
            f"{where_} <{bind.skeleton}>: not mirror-symmetric about the {plane} plane: {shown}{more} (distances as "
            f"fractions of the skeleton's extent {extent:.4g}; tolerance {tol.MIRROR_JOINT_RTOL:g})"
        )
    return max(checked.values(), default=0.0)


def match_vertices(bind: BindSpace, touched: NDArray[np.int64], plane: str, where_: str
                   ) -> tuple[NDArray[np.int64], float]:
    """Each touched vertex's partner: the mesh vertex nearest to its mirror image (skeleton
    space), within ``MIRROR_VERTEX_RTOL`` of the mesh's diagonal, one-to-one. Returns the
    partners (aligned with touched) and the worst distance (fraction of the diagonal)."""
    if len(touched) == 0:
        return np.zeros(0, dtype=np.int64), 0.0
    diagonal = tol.bbox_diagonal(bind.rest) or 1.0
    dist, found = cKDTree(bind.rest).query(bind.rest[touched] @ reflection(plane))
    rel = np.asarray(dist, dtype=np.float64) / diagonal
    found = np.asarray(found, dtype=np.int64)
    bad = np.nonzero(rel > tol.MIRROR_VERTEX_RTOL)[0]
    if len(bad):
        worst = bad[np.argsort(-rel[bad], kind="stable")][:5]
        shown = ", ".join(f"{int(touched[i])} ({rel[i]:.2g})" for i in worst)
        raise InputError(
            f"{where_}: not mirror-symmetric about the {plane} plane: {len(bad)} of the {len(touched)} vertices the "
            f"group moves have no vertex at their mirror image (within {tol.MIRROR_VERTEX_RTOL:g} of the diagonal "
            f"{diagonal:.4g}): worst vertices {shown} (distance to the nearest vertex, fraction of the diagonal)"
        )
    order = np.argsort(found, kind="stable")
    same = np.nonzero(np.diff(found[order]) == 0)[0]
    if len(same):
        a, b = int(touched[order[same[0]]]), int(touched[order[same[0] + 1]])
        raise InputError(
            f"{where_}: vertices {a} and {b} both mirror to vertex {int(found[order[same[0]]])} (coincident vertices): "
            "psdbake pairs vertices by position only, so the pairing must be one-to-one"
        )
    return found, float(rel.max())
