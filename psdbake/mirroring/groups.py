"""``psdbake mirror``: the other side's correctives groups, made from one side's.

For each group mirrored (one named group, or every group whose drivers all have partners):
its drivers' partners (``symmetry.partners``, ``check_joints``), the partners of the
vertices it moves (``symmetry.match_vertices``), its pose space reflected and its RBF
refitted (``posemirror``), its offsets reflected onto the partner vertices, and its
client-safe channels planned afresh, as fit plans them (``correctives.client_safe``). Works on what
``groups.read_correctives`` and ``usd.bindspace`` read; writes nothing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError, where
from ..fitting.correctives import client_safe
from ..fitting.drivers import channel_prefix
from ..fitting.groups import Groups
from ..model import posespace
from ..model.data import BlendShapeData, DriverData
from ..model.rig import BindSpace, SkinnedMesh
from ..results import MirroredGroup
from ..settings import MirrorSettings, is_group_name
from .poses import coordinate_map, driver_turns, mirror_gate_poses, mirror_rbf, mirrored_twist_axis, sculpted_rotations
from .symmetry import JointMap, check_joints, match_vertices, partner_problem, partners, reflection


def mirror_groups(asset: str, label: str, groups: Groups, binds: Mapping[str, BindSpace],
                  meshes: Mapping[str, SkinnedMesh], settings: MirrorSettings) -> tuple[list[MirroredGroup], list[str]]:
    """The mirrored groups (sorted by mesh and name) and the groups left out, each with why
    (whole-layer mode). label names CORRECTIVES in messages, asset the rig's own refusals."""
    jmap = JointMap(settings.joints)
    jobs, skipped = (_one_group(label, groups, binds, jmap, settings) if settings.group
                     else _every_group(label, groups, binds, jmap))
    out = []
    for mesh in sorted(jobs):
        names = dict(jobs[mesh])  # source -> mirrored name, for gate groups
        final = {g: d for g, (d, _) in groups[mesh].items()}
        made: dict[str, tuple[DriverData, list[BlendShapeData], MirroredGroup]] = {}
        gate_name = jmap if settings.group else _renamed(names, jmap)
        for source, target in sorted(jobs[mesh].items(), key=lambda j: (bool(groups[mesh][j[0]][0].gate_groups), j[0])):
            data, shapes, info = _mirror_one(asset, label, groups[mesh], source, target, binds[mesh], meshes[mesh],
                                             jmap, settings.plane, final, gate_name)
            final[target] = data
            made[target] = (data, shapes, info)
        _check_gates(final, where(label, mesh))
        # client-safe channels as fit plans them
        safe = client_safe(final, {target: made[target][1] for target in made}, sculpted_rotations(final))
        for target in sorted(made):
            data, shapes = safe[target]
            out.append(dataclasses.replace(made[target][2], driver_data=data, shapes=tuple(shapes)))
    return out, skipped


# --- which groups, under which names ---------------------------------------------------------

def _renamed(names: Mapping[str, str], jmap: JointMap) -> Callable[[str], str]:
    """A gate group's name on the other side: its mirror's name when it is mirrored too."""
    return lambda group: names.get(group, jmap(group))


def _one_group(label: str, groups: Groups, binds: Mapping[str, BindSpace], jmap: JointMap, settings: MirrorSettings
               ) -> tuple[dict[str, dict[str, str]], list[str]]:
    source = str(settings.group)
    found = sorted(mesh for mesh, per in groups.items() if source in per)
    if not found:
        names = sorted({g for per in groups.values() for g in per})
        raise InputError(f"{label}: no correctives group {source!r} (groups: {', '.join(names)})")
    for mesh in found:
        partners(groups[mesh][source][0].drivers, binds[mesh].joints, jmap, f"{where(label, mesh)} group {source!r}")
    target = settings.as_name or jmap(source)
    if target == source:
        raise InputError(f"{label}: group {source!r} keeps its name under --joints {jmap.shown()}: name the mirrored "
                         "group with --as")
    if not is_group_name(target):
        raise InputError(f"{label}: group {source!r} maps to {target!r} under --joints {jmap.shown()}, not a group "
                         "name (letters, digits, _): name the mirrored group with --as")
    return {mesh: {source: target} for mesh in found}, []


def _every_group(label: str, groups: Groups, binds: Mapping[str, BindSpace], jmap: JointMap
                 ) -> tuple[dict[str, dict[str, str]], list[str]]:
    """Every group whose drivers all map to other joints (and, for a combination, whose gate
    groups are mirrored too), named by the joint map applied to its name."""
    jobs: dict[str, dict[str, str]] = {}
    skipped = []
    for mesh in sorted(groups):
        why = {}
        for group, (data, _) in sorted(groups[mesh].items()):
            problems = [p for d in data.drivers if (p := partner_problem(d, binds[mesh].joints, jmap))]
            if problems:
                why[group] = problems[0]
        changed = True
        while changed:  # a combination needs its gate groups mirrored
            changed = False
            for group, (data, _) in sorted(groups[mesh].items()):
                missing = [g for g in data.gate_groups if g in why]
                if group not in why and missing:
                    why[group] = f"its gate group {missing[0]!r} is not mirrored"
                    changed = True
        skipped += [f"{where(label, mesh)} group {g!r}: {why[g]}" for g in sorted(why)]
        mine = {g: jmap(g) for g in sorted(groups[mesh]) if g not in why}
        for source, target in mine.items():
            at = f"{where(label, mesh)} group {source!r}"
            if target == source:
                raise InputError(f"{at}: its name is unchanged under --joints {jmap.shown()}, so its mirror would replace "
                                 f"it: mirror it alone with --group {source} --as NAME")
            if not is_group_name(target):
                raise InputError(f"{at}: maps to {target!r} under --joints {jmap.shown()}, not a group name (letters, "
                                 f"digits, _): mirror it alone with --group {source} --as NAME")
            if target in mine:
                raise InputError(f"{at}: its mirror {target!r} would replace group {target!r}, which is mirrored too: "
                                 "mirror one side at a time (--joints rules for one direction)")
            twin = [s for s, t in mine.items() if t == target and s != source]
            if twin:
                raise InputError(f"{at}: groups {source!r} and {twin[0]!r} both mirror to {target!r}")
        if mine:
            jobs[mesh] = mine
    if not jobs:
        raise InputError(f"{label}: nothing to mirror: no group has drivers that all map to other joints under --joints "
                         f"{jmap.shown()}: " + "; ".join(s.removeprefix(f"{label} ") for s in skipped[:4])
                         + (f"; and {len(skipped) - 4} more" if len(skipped) > 4 else ""))
    return jobs, skipped


# --- one group ---------------------------------------------------------------------------------

def _mirror_one(asset: str, label: str, mesh_groups: Mapping[str, tuple[DriverData, list[BlendShapeData]]],
                source: str, target: str, bind: BindSpace, info: SkinnedMesh, jmap: JointMap, plane: str,
                final: Mapping[str, DriverData], gate_name: Callable[[str], str]
                ) -> tuple[DriverData, list[BlendShapeData], MirroredGroup]:
    """The mirrored group without channels, its columns' BlendShapes, and what was matched."""
    data, shapes = mesh_groups[source]
    at = f"{where(label, bind.mesh)} group {source!r}"
    pairs = partners(data.drivers, bind.joints, jmap, at)
    m = reflection(plane)
    worst_joint = check_joints(bind, pairs, jmap, plane, asset)
    turns = driver_turns(bind, pairs, m)
    index = {j: i for i, j in enumerate(bind.joints)}
    drivers = sorted(pairs.values(), key=index.__getitem__)  # skeleton order, as fit writes them
    back = {p: j for j, p in pairs.items()}
    order = [list(data.drivers).index(back[d]) for d in drivers]
    own = [turns[d] for d in data.drivers]
    mirrored = mirror_rbf(data, coordinate_map(data.pose_space, own, order), f"{at} mirrored as {target!r}")
    old_prefix, new_prefix = channel_prefix(info, source), channel_prefix(info, target)
    names = [new_prefix + s[len(old_prefix):] if s.startswith(old_prefix + "_") else f"{new_prefix}_{k:02d}"
             for k, s in enumerate(data.shapes)]
    gated = _gate_groups(data, mesh_groups, final, bind, jmap, gate_name, m, at)
    mirrored = dataclasses.replace(
        mirrored, drivers=drivers, bind_rotations=posespace.rotations(bind.bind_local[[index[d] for d in drivers]]).as_quat(),
        twist_axis=mirrored_twist_axis(data, own, at), shapes=names, channels=(),
        channel_columns=np.zeros(0, dtype=np.int64), channel_scales=np.zeros(0),
        **mirror_gate_poses(data, turns, jmap), **gated,
    )
    columns = column_shapes(data, shapes)
    touched = np.unique(np.concatenate([c.indices for c in columns] or [np.zeros(0, dtype=np.int64)]))
    found, worst_vertex = match_vertices(bind, touched, plane, f"{where(asset, bind.mesh)} (group {source!r})")
    partner = np.full(len(bind.rest), -1, dtype=np.int64)
    partner[touched] = found
    moved = [_reflected(c, partner, bind.geom_bind[:3, :3], m, name) for c, name in zip(columns, names, strict=True)]
    result = MirroredGroup(mesh=bind.mesh, source=source, group=target, driver_data=mirrored, shapes=(),
                           drivers=tuple(sorted(pairs.items())), vertices=len(touched), worst_vertex=worst_vertex,
                           worst_joint=worst_joint)
    return mirrored, moved, result


def column_shapes(data: DriverData, shapes: Sequence[BlendShapeData]) -> list[BlendShapeData]:
    """One BlendShape per corrective (psd:shapes column), unscaled: a channel's offsets divided
    by its scale (``shapes`` are the group's channel BlendShapes, in ``channels.channel_names`` order)."""
    if not len(data.channels):
        return list(shapes)
    out = []
    for s, name in enumerate(data.shapes):
        c = int(np.nonzero(np.asarray(data.channel_columns) == s)[0][0])
        scale, shape = float(data.channel_scales[c]), shapes[c]
        out.append(BlendShapeData(name=name, channel=name, indices=shape.indices, offsets=shape.offsets / scale,
                                  normal_offsets=None if shape.normal_offsets is None else shape.normal_offsets / scale))
    return out


def _reflected(shape: BlendShapeData, partner: NDArray[np.int64], linear: NDArray[np.float64], m: NDArray[np.float64],
               name: str) -> BlendShapeData:
    """Offsets (mesh point space, row vectors) taken to skeleton space by geomBindTransform's
    linear part, reflected, taken back, and put on the partner vertices (indices sorted);
    normal offsets likewise through its inverse transpose, as UsdSkel carries normals."""
    inverse = np.linalg.inv(linear)
    indices = partner[shape.indices]
    order = np.argsort(indices, kind="stable")
    offsets = (shape.offsets @ linear @ m @ inverse)[order]
    normals = None if shape.normal_offsets is None else (shape.normal_offsets @ inverse.T @ m @ linear.T)[order]
    return BlendShapeData(name=name, channel=name, indices=indices[order], offsets=offsets, normal_offsets=normals)


def _gate_groups(data: DriverData, mesh_groups: Mapping[str, tuple[DriverData, list[BlendShapeData]]],
                 final: Mapping[str, DriverData], bind: BindSpace, jmap: JointMap, gate_name: Callable[[str], str],
                 m: NDArray[np.float64], at: str) -> dict:
    """A combination's gate groups on the partners: their mirrored names (sorted) and each
    shape's gate directions turned by each gate group's pose-space map. Each must be a group
    of the layer (mirrored too, or already there) on the partner joints, in the same pose space."""
    if not data.gate_groups:
        return {}
    blocks, start = {}, 0
    directions = np.asarray(data.gate_directions)
    for gate in data.gate_groups:
        src = mesh_groups[gate][0]
        width = posespace.POSE_SPACES[src.pose_space].width * len(src.drivers)
        name = gate_name(gate)
        other = final.get(name)
        pairs = partners(src.drivers, bind.joints, jmap, at)
        if other is None or other.gate_groups or set(other.drivers) != set(pairs.values()) \
                or other.pose_space != src.pose_space:
            raise InputError(f"{at}: gate group {gate!r} maps to {name!r}, which is not a group of the layer on "
                             f"{', '.join(sorted(pairs.values()))} in the {src.pose_space} pose space: mirror "
                             f"{gate!r} first, or the whole layer")
        back = {p: j for j, p in pairs.items()}
        order = [list(src.drivers).index(back[d]) for d in other.drivers]
        turns = driver_turns(bind, pairs, m)
        mapping = coordinate_map(src.pose_space, [turns[d] for d in src.drivers], order)
        blocks[name] = directions[:, start:start + width] @ mapping.T
        start += width
    names = sorted(blocks)
    return {"gate_groups": names, "gate_directions": np.concatenate([blocks[n] for n in names], axis=1)}


def _check_gates(final: Mapping[str, DriverData], at: str) -> None:
    """Every combination of the written layer must find its gate groups (eval refuses it otherwise)."""
    for name, data in sorted(final.items()):
        width = 0
        for gate in data.gate_groups:
            other = final.get(gate)
            if other is None or other.gate_groups:
                raise InputError(f"{at}: combination {name!r} would lose its gate group {gate!r}")
            width += posespace.POSE_SPACES[other.pose_space].width * len(other.drivers)
        if data.gate_groups and np.asarray(data.gate_directions).shape[1] != width:
            raise InputError(f"{at}: combination {name!r}'s gate directions would no longer fit its gate groups "
                             f"{', '.join(data.gate_groups)} (one of them would be replaced by a group on other joints)")
