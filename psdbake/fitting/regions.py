"""Which examples drive which correctives group, when the fit is told (``--driver``, ``--group``).

By default (neither option) a mesh's correctives are decomposed from all its examples together
(``decompose``): a group per joint that can explain a sculpted point, and combination groups for
what those leave. The two options choose instead:

- ``--driver`` (chosen drivers): one group driven by exactly those joints, over the examples
  that move only those drivers (and move one of them); without ``--group`` it is named as the
  default fit names a group of those joints, so a later ``--group`` fit of the same joint
  replaces it instead of doubling it;
- ``--group`` without ``--driver``: one group over every example, driven by every joint an
  example rotates (psdbake 0.1's global RBF).

``--no-rest-example`` without either also makes one global group ``main``: the per-joint terms
vanish at the bind pose because it is their zero example.
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
                 drivers: Sequence[int], rest_example: bool = True) -> tuple[list[Region], list[int], str]:
    """(regions, skipped example indices, why the examples form one global group or "");
    no regions: the default decomposition (``decompose``).

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
    if not rest_example:
        return [Region(DEFAULT_GROUP, (), everything)], [], ("--no-rest-example: the per-joint groups need the bind "
                                                             "pose as their zero example")
    return [], [], ""
