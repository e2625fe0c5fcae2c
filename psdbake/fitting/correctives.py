"""One mesh's correctives: its regions planned, each fitted, combinations on top.

``regions.plan_regions`` decides which examples drive which group; here every group is
fitted (``drivers.fit_drivers``) and each combination's BlendShapes are made to carry only
what the single-joint groups of its joints do not already give at its pose: rest-space
offsets add before skinning, so at a combination's pose the stack's total offset is
sum_g w_g d'_g + 1 * d'_c, and d'_c = d'_total - sum_g w_g d'_g reproduces the sculpt.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .. import tolerances as tol
from ..errors import FitError, InputError, PsdWarning, where
from ..model.channels import channel_scales, plan_channels, split_shapes, weight_range
from ..model.data import BlendShapeData, DriverData
from ..model.rig import SkinnedMesh
from ..model.weights import activation, pose_coordinates, rbf_weights, sampled_ranges, weights_at_pose
from ..normals import CorrectiveNormals
from ..results import Example, MeshFit
from ..settings import FitSettings
from ..solver.inverse import InverseResult
from ..usd.read import Scene
from .drivers import character_scale, fit_drivers, plan_group, resolve_drivers
from .groups import shapes_of
from .rbf_fit import RbfPlan
from .regions import Region, plan_regions

Solved = tuple[InverseResult, CorrectiveNormals | None]


def plan_mesh(asset: str, info: SkinnedMesh, examples: Sequence[Example], settings: FitSettings
              ) -> tuple[list[Region], list[int], str]:
    """The mesh's regions, the examples no region uses, and why regions are global (or "")."""
    drivers = resolve_drivers(settings.drivers, info.joints, where(asset, info.skeleton)) if settings.drivers else []
    regions, skipped, why = plan_regions(np.array([e.pose for e in examples]), [e.label for e in examples],
                                         info.joints, settings.group, drivers)
    if not all(r.examples for r in regions):
        joints = ", ".join(info.joints[j].split("/")[-1] for j in drivers)
        raise InputError(f"{where(asset, info.path)}: no example moves only the drivers {joints} "
                         f"(of {len(examples)} examples): nothing to fit for them")
    return regions, skipped, why


def plan_systems(asset: str, info: SkinnedMesh, examples: Sequence[Example], regions: Sequence[Region],
                 settings: FitSettings, notes: list[str]) -> dict[str, RbfPlan | None]:
    """Every region's RBF system, checked before any inverse is solved; warnings noted."""
    plans = {}
    local = len(regions) > 1 or bool(regions and regions[0].gated)
    joints = sorted({j for r in regions for j in r.joints})
    scale = character_scale(examples, joints, settings) if local and joints else None
    for region in regions:
        plan = plan_group(asset, info, [examples[i] for i in region.examples], settings, region, scale)
        for msg in plan.warnings if plan else ():
            notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=3)
        plans[region.group] = plan
    return plans


def fit_regions(asset: str, asset_scene: Scene, info: SkinnedMesh, examples: Sequence[Example],
                solved: dict[int, Solved], regions: Sequence[Region], settings: FitSettings,
                notes: list[str], systems: dict[str, RbfPlan | None] | None = None,
                left_out: list[str] | None = None) -> list[MeshFit]:
    """Every region of one mesh fitted; combinations (gated) after the groups they sit on. A
    region none of whose examples differs from plain skinning (a side left for ``mirror``) has
    no corrective: it is left out with a warning naming it, as is a combination whose joints'
    groups are left out."""
    bind_local = asset_scene.bind_local_transforms(info.path)
    fits: list[MeshFit] = []
    for region in sorted(regions, key=lambda r: r.gated):
        mine = [solved[i] for i in region.examples]
        why = _unedited(region, [examples[i] for i in region.examples], mine, fits, info)
        if why:
            _left_out(notes, f"{where(asset, info.path)} group {region.group!r}: {why}: no corrective written for it")
            if left_out is not None:
                joints = sorted({info.joints[j].split("/")[-1] for j in region.joints}
                                or {info.joints[j].split("/")[-1] for i in region.examples for j in _moved(examples[i])})
                left_out.append(f"group {region.group!r} ({', '.join(joints) or 'no joint moved'}) on <{info.path}>: no "
                                "example differs from plain skinning")
            continue
        fitted = fit_drivers(asset, asset_scene, info, [examples[i] for i in region.examples], [s[0] for s in mine],
                             bind_local, settings, region, notes, (systems or {}).get(region.group))
        fitted = dataclasses.replace(fitted, normals=tuple(s[1] for s in mine))
        if region.gated:
            below = [f for f in fits if set(f.drivers) <= set(fitted.drivers)]
            fitted = _gated_by(fitted, below, asset)
            fitted = dataclasses.replace(fitted, shapes=tuple(_combination_shapes(fitted, below)))
        fits.append(fitted)
    if not fits:
        return []
    safe = client_safe({f.group: f.driver_data for f in fits}, {f.group: shapes_of(f) for f in fits},
                       _anchors(info, examples))
    return sorted((dataclasses.replace(f, driver_data=safe[f.group][0], shapes=tuple(safe[f.group][1])) for f in fits),
                  key=lambda f: f.group)


def _unedited(region: Region, examples: Sequence[Example], solved: Sequence[Solved], fits: Sequence[MeshFit],
              info: SkinnedMesh) -> str:
    """Why a region gets no corrective ("" when it gets one)."""
    if not any(len(inverse.indices) for inverse, _ in solved):
        labels = ", ".join(e.label for e in examples)
        return (f"none of its {len(examples)} example(s) ({labels}) differs from plain skinning (sculpt them, or "
                "mirror the other side's)")
    if region.gated:
        have = {j for f in fits for j in f.drivers}
        missing = [info.joints[j].split("/")[-1] for j in region.joints if info.joints[j] not in have]
        if missing:
            return f"it sits on the groups of its joints, and {', '.join(missing)} has none (its examples are unedited)"
    return ""


def _moved(example: Example) -> list[int]:
    from ..model.posespace import active_joints

    return sorted(active_joints(example.pose.reshape(1, -1, 4))[0])


def _left_out(notes: list[str], msg: str) -> None:
    notes.append(msg)
    warnings.warn(msg, PsdWarning, stacklevel=3)


def _anchors(info: SkinnedMesh, examples: Sequence[Example]) -> dict[str, NDArray[np.float64]]:
    """joint -> the distinct rotations away from bind the mesh's examples give it, (k, 4)."""
    poses = np.array([e.pose for e in examples])  # (examples, joints, 4)
    return {j: np.unique(np.round(poses[:, i], 12), axis=0) for i, j in enumerate(info.joints)}


def client_safe(groups: Mapping[str, DriverData], columns: Mapping[str, Sequence[BlendShapeData]],
                anchors: Mapping[str, NDArray[np.float64]]) -> dict[str, tuple[DriverData, list[BlendShapeData]]]:
    """group -> its driver data and BlendShapes as client-safe channels (``channels``), for
    each group of ``columns`` (its BlendShapes, one per output column): each column split into
    a positive and a negative channel scaled by the range of its weight (``channel_scales``).
    ``groups``: every group of the mesh (gates and the sampled reach need them all, sampled
    once); ``anchors``: each joint's sculpted rotations (``weights.sampled_ranges``)."""
    sampled = sampled_ranges(sorted(groups.items()), tol.CHANNEL_RANGE_SAMPLES, anchors)
    out = {}
    for group, shapes in columns.items():
        data = groups[group]
        names, cols, scales = plan_channels(list(data.shapes), *channel_scales(weight_range(data, groups),
                                                                                 sampled[group]))
        data = dataclasses.replace(data, channels=names, channel_columns=cols, channel_scales=scales)
        out[group] = (data, split_shapes(shapes, data))
    return out


def _dense(shape: BlendShapeData, n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    offsets, normals = np.zeros((n, 3)), np.zeros((n, 3))
    offsets[shape.indices] = shape.offsets
    if shape.normal_offsets is not None:
        normals[shape.indices] = shape.normal_offsets
    return offsets, normals


def _gated_by(combo: MeshFit, below: Sequence[MeshFit], asset: str) -> MeshFit:
    """The combination gated by the groups it sits on: each shape's weight is the RBF's times
    each group's ``activation`` toward that shape's example (0 when that joint is at bind or
    turned away from the example's side, growing as that joint's own correctives do), and
    each RBF column is divided by the product at its example's pose, so the shape's weight is
    exactly 1 there."""
    data = combo.driver_data
    gates = sorted((f for f in below if not f.driver_data.gate_groups and not len(f.driver_data.gates)),
                   key=lambda f: f.group)
    examples = [e for e, c in zip(combo.examples, combo.channels, strict=True) if c]
    product = np.ones(len(examples))
    directions = []
    for f in gates:
        x = pose_coordinates(f.driver_data, _rotations(examples, combo.joints, f.driver_data), len(examples))
        units = x / np.linalg.norm(x, axis=1, keepdims=True)  # every combination example moves each joint
        act = np.diagonal(activation(rbf_weights(f.driver_data, x), x, units)).copy()
        low = np.nonzero(~(act > tol.GATE_ACTIVATION_MIN))[0]
        if len(low):
            raise FitError(
                f"{where(asset, combo.mesh)}: combination example {examples[low[0]].label}: group {f.group!r}'s "
                f"correctives are off at its pose (activation {float(act[low[0]]):.2g}), so they cannot gate it; "
                f"sculpt {f.group!r} nearer this pose, or fit the combination alone with --group/--driver"
            )
        product *= act
        directions.append(units)
    gated = dataclasses.replace(data, gate_groups=[f.group for f in gates],
                                gate_directions=np.concatenate(directions, axis=1),
                                coefficients=data.coefficients / product[None, :])
    return dataclasses.replace(combo, driver_data=gated)


def _rotations(examples: Sequence[Example], joints: Sequence[str], data: DriverData) -> Rotation:
    """The examples' rotations away from bind of one group's drivers (examples * drivers)."""
    idx = [list(joints).index(d) for d in data.drivers]
    return Rotation.from_quat(np.concatenate([e.pose[idx] for e in examples]))


def _combination_shapes(combo: MeshFit, below: Sequence[MeshFit]) -> list[BlendShapeData]:
    """The combination's BlendShapes minus what the groups below give at each of its poses."""
    n = combo.point_count
    out = []
    for shape, example in zip(shapes_of(dataclasses.replace(combo, shapes=None)),
                              [e for e, c in zip(combo.examples, combo.channels, strict=True) if c], strict=True):
        offsets, normals = _dense(shape, n)
        has_normals = shape.normal_offsets is not None
        weights = weights_at_pose([(f.group, f.driver_data) for f in below], example.pose, combo.joints)
        for group in below:
            for w, other in zip(weights[group.group][0], shapes_of(group), strict=True):
                o, nrm = _dense(other, n)
                offsets -= w * o
                normals -= w * nrm
                has_normals |= other.normal_offsets is not None
        keep = np.nonzero(np.any(offsets != 0, axis=1) | np.any(normals != 0, axis=1))[0]
        out.append(BlendShapeData(name=shape.name, channel=shape.channel, indices=keep, offsets=offsets[keep],
                                  normal_offsets=normals[keep] if has_normals else None))
    return out
