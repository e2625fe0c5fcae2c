"""The RBF driver data of one mesh's correctives group: drivers, pose-space centres, weights.

Chooses the driver joints (``--driver`` or every joint an example rotates), turns each
example's pose into coordinates of the chosen pose space, fits the cardinal RBF
(``rbf.fit_cardinal``) and checks it (self-weights, near-duplicate poses).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from .. import tolerances as tol
from ..errors import FitError, PsdWarning, SettingError, where
from ..lookup import did_you_mean, matches
from ..model import posespace
from ..model.data import DriverData
from ..model.rig import SkinnedMesh
from ..results import Example, MeshFit
from ..settings import FitSettings
from ..solver.inverse import InverseResult
from ..usd.read import Scene, existing_blend_shapes
from . import rbf_fit as rbf
from .regions import Region


def _safe_token(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]", "_", text).strip("_") or "mesh"


def resolve_drivers(requested: Sequence[str], joints: Sequence[str], label: str) -> list[int]:
    """Joint indices for requested driver names: a full joint path or an unambiguous leaf name."""
    out = []
    for name in requested:
        hits = matches(name, joints)
        if len(hits) != 1:
            problem = (f"is not a joint of the skeleton{did_you_mean(name, joints)}" if not hits else
                       f"is ambiguous in the skeleton ({', '.join(hits)}): give its full path")
            raise SettingError("drivers", name, problem, location=label)
        out.append(joints.index(hits[0]))
    return sorted(set(out))


def _drivers(info: SkinnedMesh, examples: Sequence[Example], region: Region) -> list[int]:
    """The region's driver joints, else every joint an example rotates."""
    if region.joints:
        return list(region.joints)
    poses = np.array([e.pose for e in examples])
    found = [int(j) for j in np.nonzero(posespace.rotated_joints(poses, tol.DRIVER_ANGLE_ATOL))[0]]
    if not found:
        files = ", ".join(sorted({e.source for e in examples}))
        raise FitError(
            f"{files} {where(None, info.path)}: every example is at the bind pose, so no joint drives the correctives "
            "(name joints with --driver)"
        )
    return found


def channel_prefix(info: SkinnedMesh, group: str) -> str:
    """``psd_<group>_<mesh path below its SkelRoot>``: unique per mesh and group in a character."""
    base = info.path.split("/")[-1]
    root_rel = os.path.relpath(info.path, info.skel_root) if info.path != info.skel_root else base
    return f"psd_{group}_{_safe_token(root_rel)}"


def noted(notes: list[str], msg: str, stacklevel: int = 3) -> None:
    """A warning for the TD: kept in ``notes`` (the summary, --json and --report) and raised as a
    PsdWarning (stderr, -q included) at ``stacklevel`` (as ``warnings.warn``'s, from here)."""
    notes.append(msg)
    warnings.warn(msg, PsdWarning, stacklevel=stacklevel)


def note_unedited(notes: list[str], example: Example, mesh: str, stacklevel: int) -> None:
    """The warning for an example that equals plain skinning (kept as a zero example)."""
    noted(notes, f"{where(example.source, mesh)}: example at time {example.time:g} equals plain skinning; it is kept "
                 "as a zero example", stacklevel + 1)


def _centers(info: SkinnedMesh, examples: Sequence[Example], inverses: Sequence[InverseResult], driver_idx: list[int],
             settings: FitSettings, region: Region, notes: list[str]
             ) -> tuple[list[NDArray[np.float64]], list[str], list[int], list[str]]:
    """RBF centres (bind pose first when used), their labels, the rows that carry a corrective,
    and each example's channel ("" for an example equal to plain skinning: a zero example)."""

    def coordinates(pose: NDArray[np.float64]) -> NDArray[np.float64]:
        return posespace.features(Rotation.from_quat(pose[driver_idx]), settings.pose_space, settings.twist_axis)

    centers, labels, outputs, channels = [], [], [], []
    if settings.rest_example:
        centers.append(coordinates(np.tile([0.0, 0.0, 0.0, 1.0], (len(info.joints), 1))))
        labels.append("bind")
    prefix = channel_prefix(info, region.group)
    for k, (example, inverse) in enumerate(zip(examples, inverses, strict=True)):
        if len(inverse.indices) == 0:
            note_unedited(notes, example, info.path, 3)
            channels.append("")
        else:
            outputs.append(len(centers))
            channels.append(f"{prefix}_{k:02d}")
        centers.append(coordinates(example.pose))
        labels.append(example.label)
    if not outputs:
        files = ", ".join(sorted({e.source for e in examples}))
        raise FitError(f"{files} {where(None, info.path)}: no example differs from plain skinning: nothing to correct")
    return centers, labels, outputs, channels


def _check_model(model: rbf.CardinalRbf, centers: NDArray[np.float64], outputs: list[int], labels: list[str],
                 where_: str, smoothing: float, notes: list[str]) -> None:
    """Warn when an example does not reach its own pose's weight (smoothing), or two
    examples are nearly the same pose."""
    self_weights = model.weights(centers[outputs])
    for col, row in enumerate(outputs):
        if self_weights[col, col] < tol.SELF_WEIGHT_MIN:
            noted(notes, f"{where_}: example {labels[row]} reaches a weight of only {self_weights[col, col]:.3f} at its "
                         f"own pose (smoothing {smoothing:g})")
    for a, b, d in rbf.check_distinct(centers, labels):
        noted(notes, f"{where_}: examples {a} and {b} are only {d:.3g} rad apart in pose space")


def plan_group(asset: str, info: SkinnedMesh, examples: Sequence[Example], settings: FitSettings, region: Region
               ) -> rbf.RbfPlan:
    """The group's RBF system, built and checked before any example is solved (a bad
    setting fails in a second, not after the inverses). A group driven by one joint starts
    its automatic sigma from ``tol.JOINT_SIGMA``, as the default fit's per-joint groups do, so
    the same joint's group gets the same sigma fitted alone or in a default fit."""
    driver_idx = _drivers(info, examples, region)

    def coordinates(pose: NDArray[np.float64]) -> NDArray[np.float64]:
        return posespace.features(Rotation.from_quat(pose[driver_idx]), settings.pose_space, settings.twist_axis)

    centers, labels = [], []
    if settings.rest_example:
        centers.append(coordinates(np.tile([0.0, 0.0, 0.0, 1.0], (len(info.joints), 1))))
        labels.append("bind")
    centers += [coordinates(e.pose) for e in examples]
    labels += [e.label for e in examples]
    here = f"{where(asset, info.path)} group {region.group!r}"
    start = tol.JOINT_SIGMA if len(driver_idx) == 1 else None
    return rbf.plan_rbf(np.array(centers), None, labels, kernel=settings.kernel, sigma=settings.sigma,
                        degree=settings.degree, smoothing=settings.smoothing, where=here, start=start)


def _model(full_centers: NDArray[np.float64], outputs: list[int], labels: list[str], settings: FitSettings,
           plan: rbf.RbfPlan | None) -> rbf.CardinalRbf:
    """The group's cardinal RBF."""
    return rbf.fit_cardinal(
        full_centers, outputs, labels, kernel=settings.kernel, sigma=settings.sigma,
        degree=settings.degree, smoothing=settings.smoothing, plan=plan,
    )


def model_data(joints: Sequence[str], driver_idx: Sequence[int], bind_local: NDArray[np.float64],
               settings: FitSettings, model: rbf.CardinalRbf, labels: Sequence[str], examples: Sequence[Example],
               shapes: Sequence[str]) -> DriverData:
    """The psd: data of a group driven by ``driver_idx`` whose weights are ``model``, with a
    centre labelled ``labels`` per example of ``examples`` (the bind pose's label first when it
    is a centre): what both a ``--group`` fit and the default fit's groups write."""
    return DriverData(
        drivers=[joints[j] for j in driver_idx],
        bind_rotations=posespace.rotations(bind_local[list(driver_idx)]).as_quat(),
        pose_space=settings.pose_space, twist_axis=settings.twist_axis, clamp_weights=settings.clamp_weights,
        normalize_weights=settings.normalize_weights, kernel=model.kernel, sigma=model.sigma, degree=model.degree,
        smoothing=model.smoothing, centers=model.centers, center_labels=list(labels), shapes=list(shapes),
        coefficients=model.coefficients, powers=model.powers, shift=model.shift, scale=model.scale, dims=model.dims,
        example_times=[e.time for e in examples], example_sources=[os.path.basename(e.source) for e in examples],
    )


def fit_drivers(asset: str, asset_scene: Scene, info: SkinnedMesh, examples: Sequence[Example],
                inverses: Sequence[InverseResult], bind_local: NDArray[np.float64], settings: FitSettings,
                region: Region, notes: list[str], plan: rbf.RbfPlan | None = None) -> MeshFit:
    """One mesh's fit for one group (``region``): its drivers, the RBF over its examples'
    poses, and the MeshFit that carries them with the inverses."""
    driver_idx = _drivers(info, examples, region)
    centers, labels, outputs, channels = _centers(info, examples, inverses, driver_idx, settings, region, notes)
    full_centers = np.array(centers)
    model = _model(full_centers, outputs, labels, settings, plan)
    _check_model(model, full_centers, outputs, labels, where(asset, info.path), settings.smoothing, notes)
    data = model_data(info.joints, driver_idx, bind_local, settings, model, labels, examples,
                      [c for c in channels if c])
    existing, targets = existing_blend_shapes(asset_scene, info.path)
    moved = [inv.indices[np.any(inv.offsets != 0.0, axis=1)] for ch, inv in zip(channels, inverses, strict=True) if ch]
    return MeshFit(
        mesh=info.path, skeleton=info.skeleton, point_count=info.point_count, examples=tuple(examples),
        inverses=tuple(inverses), channels=tuple(channels), drivers=tuple(data.drivers), driver_data=data,
        existing_channels=tuple(existing), existing_targets=tuple(targets), group=region.group,
        joints=tuple(info.joints), condition=float(model.condition),
        vertices=len(np.unique(np.concatenate(moved))) if moved else 0,
    )
