"""One mesh's correctives from sculpts of any frame: per-joint terms, combinations on top.

The default fit, read top to bottom (``fit_mesh``):

1. every example's pose coordinates and the joints it moves; its offsets at the sculpted points;
2. which joints can explain each point (``locality``), grown until they tell apart every two
   poses whose sculpts differ there;
3. a group per such joint, fitted over all examples together (``additive``);
4. what those leave at each example, carried by gated combination groups (``interactions``),
   solved so that every example is reproduced;
5. the groups as the psd: data and BlendShapes fit writes, and per example how much of it the
   per-joint terms explained.

Combination groups over joints that are each sculpted alone are gated as the groups of those
joints grow (their activations, psd: v4 ``gateGroups``: measured 6x better at the worst vertex
than a ramp, docs/decisions/additive-correctives.md); other combinations by a ramp of each joint's
angle (psd: v5 ``rampGates``), which needs no other group and is 1 at every one of its examples.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .. import tolerances as tol
from ..errors import where
from ..model import posespace
from ..model.data import BlendShapeData, DriverData
from ..model.rig import Skin, SkinnedMesh
from ..model.weights import activation, group_weights, pose_coordinates, rbf_weights
from ..normals import CorrectiveNormals
from ..results import Example, ExampleSplit, MeshFit
from ..settings import FitSettings
from ..solver.inverse import InverseResult
from . import additive, interactions, locality
from . import rbf_fit as rbf
from .drivers import channel_prefix, model_data, note_unedited, noted
from .regions import group_name

Solved = tuple[InverseResult, CorrectiveNormals | None]
Joints = tuple[int, ...]

#: MeshFit.role of each kind of group the default fit writes.
JOINT, COMBINATION = "joint", "combination"


class _Mesh:
    """What the fit of one mesh knows about its examples: poses, coordinates, offsets."""

    def __init__(self, info: SkinnedMesh, examples: Sequence[Example], solved: dict[int, Solved],
                 settings: FitSettings) -> None:
        self.info, self.examples, self.settings = info, list(examples), settings
        self.poses = np.array([e.pose for e in examples])  # (K, J, 4)
        self.labels = [e.label for e in examples]
        count, joints = self.poses.shape[:2]
        rotations = Rotation.from_quat(self.poses.reshape(-1, 4))
        self.coords = posespace.features(rotations, settings.pose_space, settings.twist_axis).reshape(count, joints, -1)
        self.active = posespace.active_joints(self.poses)
        self.turned = posespace.active_joints(self.poses, tol.DRIVER_ANGLE_ATOL)
        self.moved = sorted(set().union(*self.active)) if self.active else []
        self.inverses = [solved[k][0] for k in range(count)]
        shapes = [_sparse(*solved[k]) for k in range(count)]
        self.normals = any(s[2] is not None for s in shapes)
        sculpted = np.zeros(info.point_count, dtype=bool)  # a mask, not a sort: linear in the points
        for idx, _, _ in shapes:
            sculpted[idx] = True
        self.points = np.flatnonzero(sculpted)
        row_of = np.full(info.point_count, -1, dtype=np.int64)
        row_of[self.points] = np.arange(len(self.points))
        width = 6 if self.normals else 3
        self.data = np.zeros((count, len(self.points), width))
        for k, (idx, off, nrm) in enumerate(shapes):
            rows = row_of[idx]
            self.data[k, rows, :3] = off
            if nrm is not None:
                self.data[k, rows, 3:] = nrm
        self.diagonal = max((inv.diagonal for inv in self.inverses), default=1.0) or 1.0
        self.atol = max((inv.atol for inv in self.inverses), default=0.0)

    def delta_of(self, data: DriverData) -> Rotation:
        idx = [list(self.info.joints).index(d) for d in data.drivers]
        return Rotation.from_quat(self.poses[:, idx].reshape(-1, 4))


def _sparse(inverse: InverseResult, normals: CorrectiveNormals | None
            ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64] | None]:
    if normals is None:
        return inverse.indices, inverse.offsets, None
    return normals.indices, normals.offsets, normals.normal_offsets


def fit_mesh(asset: str, info: SkinnedMesh, examples: Sequence[Example], solved: dict[int, Solved], skin: Skin,
             bind_local: NDArray[np.float64], settings: FitSettings, notes: list[str], left_out: list[str] | None = None
             ) -> tuple[list[MeshFit], list[ExampleSplit]]:
    """The mesh's groups (before client-safe channels) and each example's split between the
    per-joint terms and the combinations."""
    here = where(asset, info.path)
    mesh = _Mesh(info, examples, solved, settings)
    _warn_unedited(mesh, notes)
    taken: set[str] = set()
    names = {j: _named(group_name(info.joints, [j], taken), taken) for j in range(len(info.joints))}
    named_out = _unedited_sets(asset, mesh, names, taken, notes, left_out)
    if not len(mesh.points):
        return [], []
    # 2. locality
    own = locality.influences(skin, mesh.points)
    skinned = locality.explaining_joints(skin, own, mesh.moved)
    sets = locality.separate(skinned, own, mesh.coords, mesh.data, skin.parents,
                             mesh.moved, mesh.atol, mesh.labels, here)
    _warn_unskinned(mesh, locality.influences(skin, mesh.points, 0.0), skinned, sets, skin.parents, here, notes)
    signatures = {s: r for s, r in sorted(locality.rows_by_set(sets).items()) if s}
    # 3. per-joint terms
    terms: dict[int, additive.JointTerm] = {}
    for j in sorted({j for s in signatures for j in s}):
        term = additive.plan_term(j, mesh.coords, mesh.active, mesh.labels, settings.kernel, settings.sigma,
                                  settings.degree, settings.smoothing, f"{here} group {_leaf(info, j)!r}",
                                  settings.clamp_weights, settings.normalize_weights)
        if term is not None:
            terms[j] = term
    values = {j: np.zeros((len(t.centres), len(mesh.points), mesh.data.shape[2])) for j, t in terms.items()}
    residual = mesh.data.copy()  # what the terms leave
    for joints, rows in signatures.items():
        mine = [terms[j] for j in joints if j in terms]
        if not mine:
            continue
        part, left = additive.fit_signature(mine, mesh.active, mesh.data[:, rows])
        residual[:, rows] = left
        for j, s in part.items():
            values[j][:, rows] = s
    # 4. groups: joints, then combinations on what they leave
    joint_groups = _joint_groups(mesh, terms, values, bind_local, names, named_out, notes, asset, left_out)
    solo = {j for j, t in terms.items() if t.solo}
    keyed = interactions.keys(signatures, mesh.active, mesh.turned, residual,
                              tol.RESIDUAL_NEGLIGIBLE_RTOL * mesh.diagonal, solo, skin.parents)
    centres, column = interactions.centres(keyed, mesh.coords)
    combos = {b: _combination(mesh, b, ks, joint_groups, bind_local, taken, here) for b, ks in centres.items()}
    every = [(g.name, g.data) for g in [*joint_groups.values(), *combos.values()]]
    weights = group_weights(every, mesh.delta_of, len(examples)) if combos else {}
    shapes = interactions.solve(signatures, keyed, column, {b: weights[g.name] for b, g in combos.items()}, residual,
                                here)
    groups = list(joint_groups.values())
    for b, g in combos.items():
        kept = _kept(g.with_values(shapes[b]), tol.RESIDUAL_NEGLIGIBLE_RTOL * mesh.diagonal)
        if kept is not None:
            groups.append(kept)
    fits = [g.mesh_fit(mesh) for g in sorted(groups, key=lambda g: g.name)]
    return fits, _splits(mesh, residual)


def _leaf(info: SkinnedMesh, j: int) -> str:
    return info.joints[j].split("/")[-1]


def _named(name: str, taken: set[str]) -> str:
    taken.add(name)
    return name


# --- the groups --------------------------------------------------------------------------------

class _Group:
    """One group of the decomposition: its psd: data, its column values (L, n, c) over the
    mesh's sculpted points, and the examples whose poses are its columns' centres."""

    def __init__(self, name: str, role: str, data: DriverData, values: NDArray[np.float64], centres: Sequence[int],
                 condition: float) -> None:
        self.name, self.role, self.data, self.values = name, role, data, values
        self.centres, self.condition = list(centres), condition

    def with_values(self, values: NDArray[np.float64]) -> _Group:
        return _Group(self.name, self.role, self.data, values, self.centres, self.condition)

    def mesh_fit(self, mesh: _Mesh) -> MeshFit:
        info = mesh.info
        prefix = channel_prefix(info, self.name)
        channels = [f"{prefix}_{col:02d}" for col in range(len(self.centres))]
        shapes = []
        nonzero = np.any(self.values != 0.0, axis=2)  # (columns, points)
        for col, v in enumerate(self.values):
            keep = np.flatnonzero(nonzero[col])
            shapes.append(BlendShapeData(name=channels[col], channel=channels[col], indices=mesh.points[keep],
                                         offsets=v[keep, :3], normal_offsets=v[keep, 3:] if mesh.normals else None))
        data = dataclasses.replace(self.data, shapes=channels)
        per_example = [""] * len(mesh.examples)
        for col, k in enumerate(self.centres):
            per_example[k] = channels[col]
        moved = int(np.count_nonzero(nonzero.any(axis=0)))
        inv = mesh.inverses
        return MeshFit(
            mesh=info.path, skeleton=info.skeleton, point_count=info.point_count, examples=tuple(mesh.examples),
            inverses=tuple(inv), channels=tuple(per_example), drivers=tuple(data.drivers), driver_data=data,
            existing_channels=(), existing_targets=(), group=self.name, joints=tuple(info.joints),
            shapes=tuple(shapes), condition=self.condition, role=self.role, vertices=moved,
        )


def _kept(group: _Group, negligible: float) -> _Group | None:
    """The group without its columns whose values are negligible everywhere (None: all are)."""
    big = [col for col in range(len(group.centres)) if np.abs(group.values[col]).max(initial=0.0) > negligible]
    if not big:
        return None
    if len(big) == len(group.centres):
        return group
    data = group.data
    coefficients = np.asarray(data.coefficients)[:, big]
    directions = np.asarray(data.gate_directions)
    data = dataclasses.replace(data, coefficients=coefficients,
                               gate_directions=directions[big] if directions.size else directions)
    return _Group(group.name, group.role, data, group.values[big], [group.centres[c] for c in big], group.condition)


def _joint_groups(mesh: _Mesh, terms: dict[int, additive.JointTerm], values: dict[int, NDArray[np.float64]],
                  bind_local: NDArray[np.float64], names: dict[int, str], named_out: set[str], notes: list[str],
                  asset: str, left_out: list[str] | None) -> dict[int, _Group]:
    """joint -> its group, for the joints whose term moves some point (the others named, once)."""
    out = {}
    for j, term in sorted(terms.items()):
        name = names[j]
        if not np.any(values[j]):
            if name not in named_out:
                _left_out(asset, mesh, name, [j], [k for k, a in enumerate(mesh.active) if j in a], notes, left_out)
            continue
        labels = ["bind", *(mesh.labels[k] for k in term.centres)]
        data = model_data(mesh.info.joints, [j], bind_local, mesh.settings, term.model, labels,
                          [mesh.examples[k] for k in term.centres], [])
        out[j] = _Group(name, JOINT, data, values[j], term.centres, term.plan.condition)
    return out


def _combination(mesh: _Mesh, joints: Joints, centres: Sequence[int], joint_groups: dict[int, _Group],
                 bind_local: NDArray[np.float64], taken: set[str], here: str) -> _Group:
    """The combination group over ``joints`` with a centre at each of ``centres`` (example
    indices), gated as the module says; its values are solved later. It interpolates
    (``--smoothing`` smooths the per-joint terms): it carries what they leave at its examples,
    and a smoothed one would have to be inverted at them (T S = R), amplifying its shapes."""
    s = mesh.settings
    x = mesh.coords[list(centres)][:, list(joints)].reshape(len(centres), -1)
    labels = [mesh.labels[k] for k in centres]
    degree = max(0, rbf.default_degree(s.kernel), s.degree if s.degree is not None else 0)
    name = group_name(mesh.info.joints, list(joints), taken) if len(joints) > 1 else _detail_name(mesh, joints[0], taken)
    taken.add(name)
    if len(centres) == 1:  # one pose: no polynomial to fit over it, the gates shape the constant
        model = rbf.constant_one(x)
        condition = float("nan")
    else:
        start = tol.COMBINATION_SIGMA_FRACTION * rbf.auto_sigma(x)
        plan = rbf.plan_rbf(x, list(range(len(x))), labels, kernel=s.kernel, sigma=s.sigma, degree=degree,
                            smoothing=0.0, where=f"{here} group {name!r}", start=start,
                            start_rule=f"{tol.COMBINATION_SIGMA_FRACTION:g} x mean pairwise distance")
        model, condition = plan.model(list(range(len(x)))), plan.condition
    data = model_data(mesh.info.joints, joints, bind_local, s, model, labels, [mesh.examples[k] for k in centres], [])
    gated = _activation_gated(mesh, data, joints, centres, joint_groups)
    if gated is None:
        norms = np.linalg.norm(mesh.coords[list(centres)][:, list(joints)], axis=2)  # (centres, joints)
        gated = dataclasses.replace(data, ramp_gates=list(data.drivers), ramp_radii=norms.min(axis=0))
    return _Group(name, COMBINATION, gated, np.zeros((len(centres), len(mesh.points), mesh.data.shape[2])), centres,
                  condition)


def _detail_name(mesh: _Mesh, joint: int, taken: set[str]) -> str:
    name = "detail_" + group_name(mesh.info.joints, [joint], set())
    k = 2
    out = name
    while out in taken:
        out = f"{name}_{k}"
        k += 1
    return out


def _activation_gated(mesh: _Mesh, data: DriverData, joints: Joints, centres: Sequence[int],
                      joint_groups: dict[int, _Group]) -> DriverData | None:
    """The combination gated by its joints' groups (v4): each column's weight times each
    group's ``activation`` toward that column's example, divided by their product there. Only
    when every joint is sculpted alone (its group defined by those sculpts) and every
    activation at the centres exceeds ``tol.GATE_ACTIVATION_MIN``; else None."""
    gates = [joint_groups.get(j) for j in joints]
    if any(g is None for g in gates) or not all(any(a == {j} for a in mesh.active) for j in joints):
        return None
    product = np.ones(len(centres))
    directions = []
    for g in sorted((g for g in gates if g is not None), key=lambda g: g.name):
        x = pose_coordinates(g.data, mesh.delta_of(g.data), len(mesh.examples))[list(centres)]
        units = x / np.linalg.norm(x, axis=1, keepdims=True)
        act = np.diagonal(activation(rbf_weights(g.data, x), x, units)).copy()
        if not np.all(act > tol.GATE_ACTIVATION_MIN):
            return None
        product *= act
        directions.append(units)
    names = sorted(g.name for g in gates if g is not None)
    return dataclasses.replace(data, gate_groups=names, gate_directions=np.concatenate(directions, axis=1),
                               coefficients=np.asarray(data.coefficients) / product[None, :])


# --- what the TD is told -------------------------------------------------------------------------

def _warn_unskinned(mesh: _Mesh, own: Sequence[Joints], skinned: Sequence[Joints], sets: Sequence[Joints],
                    parents: NDArray[np.int64], here: str, notes: list[str]) -> None:
    """Sculpted points that no joint the examples turn skins or carries, at any weight (``own``:
    every influence). A face edited on a pose where only an arm bends (neither the neck nor any
    joint above it turns) gets the nearest turning joints from ``locality.separate``, so the edit
    comes and goes with that arm: said, with where a pose-independent edit belongs. Points whose
    sculpt is under a hundredth of the mesh's largest (the trace of a rig's own look, as
    dual-quaternion sculpts on a linear rig leave on a still torso) are not counted."""
    moved = set(int(j) for j in mesh.moved)
    size = np.abs(mesh.data[:, :, :3]).max(axis=(0, 2)) if mesh.data.size else np.zeros(len(own))
    floor = 0.01 * float(size.max(initial=0.0))

    def carried(joints: Joints) -> bool:  # a moved joint at or above one of them
        return any(a in moved for j in joints for a in locality.ancestors(j, parents))

    found = [i for i, (was, now) in enumerate(zip(skinned, sets, strict=True))
             if not was and now and size[i] > floor and not carried(own[i])]
    if not found:
        return
    bones = sorted({_leaf(mesh.info, j) for i in found for j in own[i]})
    drivers = sorted({_leaf(mesh.info, j) for i in found for j in sets[i]})
    shown = ", ".join(str(int(mesh.points[i])) for i in found[:5]) + (f" and {len(found) - 5} more" if len(found) > 5 else "")
    noted(notes, f"{here}: {len(found)} sculpted point(s) (vertex {shown}) are skinned by no joint the examples move "
                 f"({', '.join(bones[:4])}{' ...' if len(bones) > 4 else ''}): their sculpt is driven by "
                 f"{', '.join(drivers[:4])}{' ...' if len(drivers) > 4 else ''}, so it comes and goes with those joints; "
                 "an edit that does not depend on the pose belongs in the asset's rest points", 4)


def _warn_unedited(mesh: _Mesh, notes: list[str]) -> None:
    for example, inverse in zip(mesh.examples, mesh.inverses, strict=True):
        if not len(inverse.indices):
            note_unedited(notes, example, mesh.info.path, 4)


def _left_out(asset: str, mesh: _Mesh, name: str, joints: Sequence[int], examples: Sequence[int], notes: list[str],
              left_out: list[str] | None) -> None:
    labels = ", ".join(mesh.labels[k] for k in examples)
    noted(notes, f"{where(asset, mesh.info.path)} group {name!r}: none of its {len(examples)} example(s) ({labels}) "
                 "differs from plain skinning (sculpt them, or mirror the other side's): no corrective written for it",
          4)
    if left_out is not None:
        leaves = ", ".join(_leaf(mesh.info, j) for j in joints)
        left_out.append(f"group {name!r} ({leaves}) on <{mesh.info.path}>: no example differs from plain skinning")


def _unedited_sets(asset: str, mesh: _Mesh, names: dict[int, str], taken: set[str], notes: list[str],
                   left_out: list[str] | None) -> set[str]:
    """Name, with a warning, every joint and every set of joints moved together whose examples
    all equal plain skinning: the groups a sculpt of them would make (a side left for mirror)."""
    edited = [bool(len(inv.indices)) for inv in mesh.inverses]
    named: set[str] = set()
    for j in mesh.moved:
        mine = [k for k, a in enumerate(mesh.active) if j in a]
        if not any(edited[k] for k in mine):
            named.add(names[j])
            _left_out(asset, mesh, names[j], [j], mine, notes, left_out)
    for together in sorted({a for a in mesh.active if len(a) > 1}, key=sorted):
        mine = [k for k, a in enumerate(mesh.active) if a == together]
        if not any(edited[k] for k in mine):
            name = _named(group_name(mesh.info.joints, sorted(together), taken), taken)
            named.add(name)
            _left_out(asset, mesh, name, sorted(together), mine, notes, left_out)
    return named


def _splits(mesh: _Mesh, residual: NDArray[np.float64]) -> list[ExampleSplit]:
    """Per example: the norm of its offsets and the parts the per-joint terms and the combinations carry."""
    out = []
    count = len(mesh.examples)
    totals = np.sqrt(np.square(mesh.data[:, :, :3]).reshape(count, -1).sum(axis=1))
    rests = np.sqrt(np.square(residual[:, :, :3]).reshape(count, -1).sum(axis=1))
    parts = np.sqrt(np.square(mesh.data[:, :, :3] - residual[:, :, :3]).reshape(count, -1).sum(axis=1))
    for k, example in enumerate(mesh.examples):
        total, rest, terms = float(totals[k]), float(rests[k]), float(parts[k])
        out.append(ExampleSplit(mesh=mesh.info.path, label=example.label, source=example.source, time=example.time,
                                norm=total, combination=rest / total if total > 0 else 0.0,
                                terms=terms / total if total > 0 else 0.0))
    return out
