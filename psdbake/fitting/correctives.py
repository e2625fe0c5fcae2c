"""One mesh's correctives: planned, fitted, and made client-safe.

By default a mesh's groups come from all its examples together (``decompose``): per-joint
terms and the combinations on top. ``--driver`` and ``--group`` choose one group instead
(``regions.plan_regions``), fitted by ``drivers.fit_drivers``. Either way every group's columns
then become client-safe channels (``client_safe``).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .. import tolerances as tol
from ..errors import FitError, InputError, PsdWarning, where
from ..model import posespace
from ..model.channels import channel_scales, plan_channels, split_shapes, weight_range
from ..model.data import BlendShapeData, DriverData
from ..model.posespace import active_joints
from ..model.rbf import check_distinct
from ..model.rig import SkinnedMesh
from ..model.weights import sampled_ranges
from ..normals import CorrectiveNormals
from ..results import Example, ExampleSplit, MeshFit
from ..settings import FitSettings
from ..solver.inverse import InverseResult
from ..usd.read import Scene, existing_blend_shapes
from . import additive, decompose
from .drivers import fit_drivers, plan_group, resolve_drivers
from .groups import shapes_of
from .rbf_fit import RbfPlan
from .regions import Region, plan_regions

Solved = tuple[InverseResult, CorrectiveNormals | None]


@dataclass(frozen=True)
class MeshPlan:
    """Who drives what on one mesh: explicit regions, or (none) the default decomposition."""

    regions: tuple[Region, ...]
    unused: tuple[int, ...]  # examples no region uses
    why: str  # why the examples form one global group ("" when they do not)

    @property
    def decomposed(self) -> bool:
        return not self.regions

    def examples(self, count: int) -> list[int]:
        """The examples this plan fits (of the mesh's count)."""
        return list(range(count)) if self.decomposed else sorted({i for r in self.regions for i in r.examples})


def plan_mesh(asset: str, info: SkinnedMesh, examples: Sequence[Example], settings: FitSettings) -> MeshPlan:
    """The mesh's plan: explicit regions (``--driver``, ``--group``) or the decomposition."""
    drivers = resolve_drivers(settings.drivers, info.joints, where(asset, info.skeleton)) if settings.drivers else []
    regions, skipped, why = plan_regions(np.array([e.pose for e in examples]), [e.label for e in examples],
                                         info.joints, settings.group, drivers, settings.rest_example)
    if not all(r.examples for r in regions):
        joints = ", ".join(info.joints[j].split("/")[-1] for j in drivers)
        raise InputError(f"{where(asset, info.path)}: no example moves only the drivers {joints} "
                         f"(of {len(examples)} examples): nothing to fit for them")
    return MeshPlan(tuple(regions), tuple(skipped), why)


def plan_systems(asset: str, info: SkinnedMesh, examples: Sequence[Example], plan: MeshPlan, settings: FitSettings,
                 notes: list[str]) -> dict[str, RbfPlan]:
    """Every region's RBF system, checked before any inverse is solved; warnings noted. For
    the decomposition, whose groups depend on the sculpts, the term of the joint moved in the
    most examples is planned: the settings fail on it in a second if they fail at all."""
    if plan.decomposed:
        poses = np.array([e.pose for e in examples])
        active = active_joints(poses)
        moved = sorted(set().union(*active)) if active else []
        if moved:
            joint = max(moved, key=lambda j: (sum(j in a for a in active), -j))
            coords = posespace.features(Rotation.from_quat(poses.reshape(-1, 4)), settings.pose_space,
                                        settings.twist_axis).reshape(len(examples), len(info.joints), -1)
            _check_poses(coords[:, moved].reshape(len(examples), -1), [e.label for e in examples],
                         where(asset, info.path), notes)
            additive.plan_term(joint, coords, active, [e.label for e in examples], settings.kernel, settings.sigma,
                               settings.degree, settings.smoothing,
                               f"{where(asset, info.path)} group {info.joints[joint].split('/')[-1]!r}")
        return {}
    plans = {}
    for region in plan.regions:
        system = plan_group(asset, info, [examples[i] for i in region.examples], settings, region)
        for msg in system.warnings:
            notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=3)
        plans[region.group] = system
    return plans


def _check_poses(coords: NDArray[np.float64], labels: Sequence[str], where_: str, notes: list[str]) -> None:
    """Refuse two examples (or one and the bind pose) with the same pose over the moved joints;
    warn about nearly equal ones (``rbf.check_distinct``, as a group of explicit drivers does)."""
    try:
        near = check_distinct(np.concatenate([np.zeros((1, coords.shape[1])), coords]), ["the bind pose", *labels])
    except FitError as exc:
        raise FitError(f"{where_}: {exc}") from None
    for a, b, d in near:
        msg = f"{where_}: examples {a} and {b} are only {d:.3g} rad apart in pose space"
        notes.append(msg)
        warnings.warn(msg, PsdWarning, stacklevel=4)


def fit_planned(asset: str, asset_scene: Scene, info: SkinnedMesh, examples: Sequence[Example],
                solved: dict[int, Solved], plan: MeshPlan, settings: FitSettings, notes: list[str],
                systems: dict[str, RbfPlan] | None = None, left_out: list[str] | None = None
                ) -> tuple[list[MeshFit], list[ExampleSplit]]:
    """The mesh's groups, client-safe, and (decomposition) each example's split. A group none of
    whose examples differs from plain skinning (a side left for ``mirror``) has no corrective: it
    is left out with a warning naming it."""
    bind_local = asset_scene.bind_local_transforms(info.path)
    splits: list[ExampleSplit] = []
    if plan.decomposed:
        fits, splits = decompose.fit_mesh(asset, info, examples, solved, asset_scene.skin(info.path), bind_local,
                                          settings, notes, left_out)
        existing, targets = existing_blend_shapes(asset_scene, info.path)
        fits = [dataclasses.replace(f, existing_channels=tuple(existing), existing_targets=tuple(targets)) for f in fits]
    else:
        fits = []
        for region in plan.regions:
            mine = [solved[i] for i in region.examples]
            if not any(len(inverse.indices) for inverse, _ in mine):
                labels = ", ".join(examples[i].label for i in region.examples)
                _left_out(notes, f"{where(asset, info.path)} group {region.group!r}: none of its {len(mine)} example(s) "
                                 f"({labels}) differs from plain skinning (sculpt them, or mirror the other side's): no "
                                 "corrective written for it")
                if left_out is not None:
                    joints = sorted({info.joints[j].split("/")[-1] for j in region.joints}
                                    or {info.joints[j].split("/")[-1] for i in region.examples
                                        for j in active_joints(examples[i].pose[None])[0]})
                    left_out.append(f"group {region.group!r} ({', '.join(joints) or 'no joint moved'}) on "
                                    f"<{info.path}>: no example differs from plain skinning")
                continue
            fitted = fit_drivers(asset, asset_scene, info, [examples[i] for i in region.examples], [s[0] for s in mine],
                                 bind_local, settings, region, notes, (systems or {}).get(region.group))
            fits.append(dataclasses.replace(fitted, normals=tuple(s[1] for s in mine)))
    if not fits:
        return [], splits
    safe = client_safe({f.group: f.driver_data for f in fits}, {f.group: shapes_of(f) for f in fits},
                       _anchors(info, examples))
    return sorted((dataclasses.replace(f, driver_data=safe[f.group][0], shapes=tuple(safe[f.group][1])) for f in fits),
                  key=lambda f: f.group), splits


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
