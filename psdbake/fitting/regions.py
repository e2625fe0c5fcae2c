"""Which examples drive which correctives: local, additive regions by default.

A pose-space corrective exists for the poses between and across the sculpts: one global
RBF over every driver treats a pose where several joints bend as far from every example,
so its correctives fade exactly where a character needs all of them. So by default each
example's corrective is driven only by the joints it moves (turned more than
``tol.ACTIVE_JOINT_ANGLE`` from the bind pose):

- examples that move one joint ``j`` form the region ``j``: an RBF over that joint's pose
  alone (bind pose included, at weight 0), so it is exactly off whenever ``j`` is at bind
  and regions driven by different joints add;
- an example that moves several joints, each of which has single-joint examples, is a
  **combination**: fitted on top of those regions (its corrective carries what they do
  not already give at its pose) and gated by each of its joints, so it vanishes when any
  of them returns to bind (the way combination shapes work in facial rigs);
- when some example moves several joints that are not all covered by single-joint
  examples (an animation frame used as a sculpt, say), local regions cannot be formed:
  every example goes into one global group, ``main``.

``--group`` (one named group) and ``--driver`` (chosen drivers) override this; with
explicit drivers, the group uses exactly the examples that move only those drivers, and
without ``--group`` it is named as the default fit names a group of those joints, so a later
``--group`` fit of the same joint replaces it instead of doubling it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..model import posespace
from ..model.data import DEFAULT_GROUP, RESERVED_GROUP_NAMES


@dataclass(frozen=True)
class Region:
    """One correctives group of one mesh: its name, drivers and examples."""

    group: str
    joints: tuple[int, ...]  # driver joint indices, skeleton order; () = every joint any example rotates
    examples: tuple[int, ...]  # indices into the mesh's examples
    gated: bool = False  # a combination: fitted on top of the regions of its joints, gated by each


def group_name(joints: Sequence[str], chosen: Sequence[int], taken: set[str]) -> str:
    """A readable group identifier from the joints' leaf names (longer paths on a clash)."""
    for depth in (1, 2, 3, 99):
        parts = ["_".join(joints[j].split("/")[-depth:]) for j in chosen]
        name = ("combo_" if len(chosen) > 1 else "") + "_".join(parts)
        name = re.sub(r"[^A-Za-z0-9_]", "_", name).strip("_") or "joint"
        if name[0].isdigit():
            name = "j_" + name
        if name not in taken and name not in RESERVED_GROUP_NAMES:
            return name
    k = 2
    while f"{name}_{k}" in taken:
        k += 1
    return f"{name}_{k}"


def plan_regions(poses: NDArray[np.float64], labels: Sequence[str], joints: Sequence[str], group: str | None,
                 drivers: Sequence[int]) -> tuple[list[Region], list[int], str]:
    """(regions, skipped example indices, why local regions were not formed or "").

    poses: (examples, j, 4), labels name them. group/drivers: the explicit ``--group`` /
    ``--driver`` choice."""
    active = posespace.active_joints(poses)
    everything = tuple(range(len(active)))
    if drivers:  # explicit drivers: the examples that move only those joints (and move one of them)
        chosen = set(drivers)
        used = tuple(i for i, a in enumerate(active) if a and a <= chosen)
        name = group or group_name(joints, sorted(chosen), set())  # the name the default fit gives these drivers
        return [Region(name, tuple(sorted(chosen)), used)], [i for i in everything if i not in used], ""
    if group is not None:
        return [Region(group, (), everything)], [], ""
    singles: dict[int, list[int]] = {}
    for i, a in enumerate(active):
        if len(a) == 1:
            singles.setdefault(next(iter(a)), []).append(i)
    combos: dict[frozenset[int], list[int]] = {}
    uncovered = []
    for i, a in enumerate(active):
        if len(a) > 1 and a <= set(singles):
            combos.setdefault(a, []).append(i)
        elif len(a) != 1:
            uncovered.append(i)
    if uncovered or not singles:
        return [Region(DEFAULT_GROUP, (), everything)], [], _why_global(uncovered, active, singles, labels, joints)
    taken: set[str] = set()
    regions = []
    for j in sorted(singles):
        name = group_name(joints, [j], taken)
        taken.add(name)
        regions.append(Region(name, (j,), tuple(singles[j])))
    for a in sorted(combos, key=sorted):
        name = group_name(joints, sorted(a), taken)
        taken.add(name)
        regions.append(Region(name, tuple(sorted(a)), tuple(combos[a]), gated=True))
    return regions, [], ""


def _why_global(uncovered: list[int], active: list[frozenset[int]], singles: dict[int, list[int]],
                labels: Sequence[str], joints: Sequence[str]) -> str:
    """Why the examples went into one global group (for the fit's notes), naming an example."""
    if not uncovered:
        return ""
    i = uncovered[0]
    if not active[i]:
        return f"example {labels[i]} is at the bind pose"
    missing = [joints[j].split("/")[-1] for j in sorted(active[i] - set(singles))]
    return (f"example {labels[i]} moves {len(active[i])} joints and {', '.join(missing)} "
            f"{'has' if len(missing) == 1 else 'have'} no single-joint example")
