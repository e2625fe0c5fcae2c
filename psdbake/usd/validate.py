"""Checks that refuse what UsdSkel would get silently wrong, before any work.

Each takes the composed ``Scene`` (``read.Scene``) and raises ``InputError`` naming the
file, the prim and the attribute: influences UsdSkel would mis-skin, animations naming
joints the skeleton lacks, EXAMPLES that change the binding fit inverts, time samples
keyed at inf, CORRECTIVES fitted on another asset.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from pxr import Usd, UsdGeom, UsdSkel

from ..arrays import is_singular
from ..errors import InputError, where
from ..model.channels import channel_names
from ..model.data import DriverData
from ..model.rig import SkinnedMesh
from .compose import open_layer
from .inplace import numbers
from .read import Scene, corrective_targets, matrices
from .schema import psd_prims

#: What decides how UsdSkel skins a mesh: the binding (UsdSkelBindingAPI, inherited down
#: namespace), and on Skeleton and BlendShape prims their joints, bind pose and offsets.
_BINDING = frozenset({"skel:joints", "skel:skeleton", "skel:skinningMethod", "skel:blendShapes",
                      "skel:blendShapeTargets"})


_BINDING_ON = {"Skeleton": frozenset({"joints", "bindTransforms"}),
               "BlendShape": frozenset({"offsets", "pointIndices", "normalOffsets", "inbetweens"})}


def check_examples_binding(asset: Scene, examples: Scene, path: str) -> None:
    """Refuse an EXAMPLES file (``examples``: the file composed over the asset) that changes
    the skinning: the binding primvars and relationships of any prim, a Skeleton's joints or
    bindTransforms, a BlendShape's offsets. fit would invert a skinning that eval and UsdSkel
    (reading the asset's binding) never apply, and the correctives would miss the sculpts.
    EXAMPLES may carry only the pose (the bound SkelAnimation) and the sculpted points."""
    for prim in examples.stage.Traverse(Usd.TraverseInstanceProxies()):
        original = asset.stage.GetPrimAtPath(prim.GetPath())
        kinds = [kind for kind in _BINDING_ON if prim.IsA(getattr(UsdSkel, kind))
                 or (original and original.IsA(getattr(UsdSkel, kind)))]
        extra = frozenset().union(*(_BINDING_ON[k] for k in kinds))
        for prop in prim.GetAuthoredProperties():
            name = prop.GetName()
            if not (name.startswith("primvars:skel:") or name in _BINDING or name in extra):
                continue
            before = original.GetProperty(name) if original else None
            if not _same_property(prop, before):
                raise InputError(
                    f"{where(path, str(prim.GetPath()), name)}: the EXAMPLES layer re-authors the asset's skinning "
                    "binding: EXAMPLES may only carry the pose (the bound SkelAnimation) and the sculpted points, "
                    "because eval and UsdSkel skin with the asset's binding (change it in the asset and run "
                    "psdbake pose again)"
                )


def require_finite_time_samples(scene: Scene, path: str, label: str) -> None:
    """Refuse a time sample keyed at inf on the prim at path (in any layer of its prim stack).
    USD lets a layer author one, but its composed queries skip it: a pose or weight keyed
    there would be silently dropped, and no frame or example can live at inf."""
    prim = scene.prim(path)
    for spec in prim.GetPrimStack() if prim else []:
        layer = spec.layer
        file = label if layer.realPath and os.path.realpath(layer.realPath) == os.path.realpath(label) else \
            (layer.realPath or label)
        for attr in spec.attributes:
            bad = [t for t in layer.ListTimeSamplesForPath(attr.path) if not np.isfinite(t)]
            if bad:
                raise InputError(f"{where(file, path, attr.name)}: time sample at time code {float(bad[0])!r}: "
                                 "time codes must be finite numbers (USD's queries skip this one)")


def require_psd_prims_skinned(scene: Scene, correctives: str, asset: str) -> None:
    """Every prim on which the CORRECTIVES file authors psd:version must be a skinned mesh of
    the stage: directly, or through a reference or instance of a corrected asset that
    sublayers CORRECTIVES (the instanced-shot workflow). Anything else (CORRECTIVES fitted on
    another asset) would be silently ignored by eval."""
    layer = open_layer(correctives)
    reached: set[str] = set()
    for info in scene.skinned_meshes():
        reached |= {str(s.path) for s in scene.prim(info.path).GetPrimStack() if s.layer.identifier == layer.identifier}
    stray = [p for p in psd_prims(layer) if p not in reached]
    if stray:
        inside = scene.instance_of(stray[0])
        if inside:
            raise InputError(f"{where(correctives, stray[0])}: has correctives, but in {asset} it is inside instance "
                             f"<{inside[0]}> of {inside[1]}, where USD ignores them: fit that asset itself and reference "
                             "the corrected asset")
        raise InputError(f"{where(correctives, stray[0])}: has correctives but is not a skinned mesh of {asset} "
                         "(CORRECTIVES fitted on another asset?): eval would ignore them")


def check_corrective_indices(scene: Scene, mesh: str, channels: Sequence[str], point_count: int) -> None:
    """The BlendShapes behind channels must index only the mesh's points (a CORRECTIVES layer
    fitted on a denser mesh at the same path would be silently clipped by UsdSkel). Reads
    each shape's pointIndices once, in place (no int64 copy: a 128-example layer's 256
    shapes hold a million indices), and never its offsets."""
    shapes = {str(prim.GetPath()): prim for prim in corrective_targets(scene, mesh, channels)}
    for prim in shapes.values():
        indices = numbers(prim.GetAttribute("pointIndices").Get(), np.int64)  # int32 in place
        if len(indices) and (indices.min() < 0 or indices.max() >= point_count):
            raise InputError(f"{where(scene.label, mesh + '/' + prim.GetName(), 'pointIndices')}: indices outside the "
                             f"{point_count} points of the asset's mesh")


def checked_driver_groups(scene: Scene, info: SkinnedMesh) -> list[tuple[str, DriverData]]:
    """The mesh's correctives groups, each group's BlendShapes checked to index only its points
    (``check_corrective_indices``): what every consumer of a CORRECTIVES layer starts from."""
    groups = scene.driver_groups(info.path)
    for _, data in groups:
        check_corrective_indices(scene, info.path, channel_names(data), info.point_count)
    return groups


def _same_property(prop: Usd.Property, other: Usd.Property | None) -> bool:
    """Same composed value: relationship targets, or attribute default and time samples."""
    if other is None or not other.IsValid():
        return False
    if isinstance(prop, Usd.Relationship) != isinstance(other, Usd.Relationship):
        return False
    if isinstance(prop, Usd.Relationship):
        return list(prop.GetTargets()) == list(other.GetTargets())
    times = list(prop.GetTimeSamples())
    if times != list(other.GetTimeSamples()):
        return False
    return all(_same_value(prop.Get(t), other.Get(t)) for t in [Usd.TimeCode.Default(), *times])


def _same_value(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def _row_sums(w: np.ndarray) -> np.ndarray:
    """``w.sum(axis=1)`` in float64, bit for bit: numpy adds fewer than 8 columns in order,
    which column by column does 8x faster than its k-element inner loops (tests/test_exact_kernels.py
    holds the two equal); 8 columns or more go to numpy itself."""
    if not 2 <= w.shape[1] < 8:
        return w.sum(axis=1, dtype=np.float64)
    sums = np.add(w[:, 0], w[:, 1], dtype=np.float64)
    for j in range(2, w.shape[1]):
        np.add(sums, w[:, j], out=sums)
    return sums


def require_static_rest(scene: Scene, mesh: str) -> None:
    """Refuse an asset whose skinned points are animated (a cached simulation over the rest):
    UsdSkel skins the points at each time, so correctives fitted on one rest would not give
    the sculpts in any client."""
    attr = UsdGeom.PointBased(scene.prim(mesh)).GetPointsAttr()
    count = attr.GetNumTimeSamples()
    if count:
        raise InputError(
            f"{where(scene.label, mesh, 'points')}: the rest points are animated ({count} time sample(s)): UsdSkel "
            "skins the points of each time, so correctives fitted on one rest would not reproduce the sculpts; give "
            "the skinned mesh static points (a default value only) and put any simulation after skinning"
        )


def validate_skinning(scene: Scene, mesh: str) -> list[str]:
    """Refuse influences UsdSkel would mis-skin; return warnings (weights not summing to 1).

    Checks: jointIndices/jointWeights authored, sizes agree with the points and the element
    size, indices inside the joint list the mesh uses, weights finite, >= 0, not all zero."""
    query, skel_query = scene.query(mesh)
    label = where(scene.label, mesh)
    require_static_rest(scene, mesh)
    binding = UsdSkel.BindingAPI(scene.prim(mesh))
    ind_pv, w_pv = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    if not ind_pv or not ind_pv.HasAuthoredValue() or not w_pv or not w_pv.HasAuthoredValue():
        raise InputError(f"{label}: no primvars:skel:jointIndices/jointWeights: the mesh has no skin influences")
    for name, primvar in (("jointIndices", ind_pv), ("jointWeights", w_pv)):
        interpolation = primvar.GetInterpolation()
        if interpolation not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.constant):
            raise InputError(
                f"{where(scene.label, mesh, 'primvars:skel:' + name)}: interpolation {str(interpolation)!r}: UsdSkel "
                "skins with 'vertex' influences (one set per point) or 'constant' ones (one set for every point) only"
            )
    indices = numbers(ind_pv.Get(), np.int64)
    weights = numbers(w_pv.Get(), np.float64)
    k = max(1, int(ind_pv.GetElementSize()))
    k_weights, interp = max(1, int(w_pv.GetElementSize())), (ind_pv.GetInterpolation(), w_pv.GetInterpolation())
    if k_weights != k or interp[0] != interp[1]:
        raise InputError(
            f"{label}: jointWeights has elementSize {k_weights} ({interp[1]}) and jointIndices {k} ({interp[0]}): "
            "UsdSkel needs one weight per joint index, so it cannot skin these points"
        )
    n = scene.point_count(mesh)
    constant = ind_pv.GetInterpolation() == UsdGeom.Tokens.constant
    expected = k if constant else n * k
    if len(indices) != expected or len(weights) != len(indices):
        raise InputError(
            f"{label}: jointWeights has {len(weights)} values and jointIndices {len(indices)}, for {n} points "
            f"with {k} influences each (expected {expected} of each)"
        )
    joints = query.GetJointOrder() or skel_query.GetJointOrder()
    if len(indices) and (indices.min() < 0 or indices.max() >= len(joints)):
        first = int(np.nonzero((indices < 0) | (indices >= len(joints)))[0][0])
        raise InputError(
            f"{label}: joint index {indices[first]} out of range at point {first // k} "
            f"(the mesh uses {len(joints)} joints, indices 0..{len(joints) - 1})"
        )
    w = weights.reshape(-1, k)
    if not np.all(np.isfinite(w)):
        raise InputError(f"{label}: jointWeights contain NaN or inf (point {int(np.nonzero(~np.isfinite(w))[0][0])})")
    if np.any(w < 0):
        raise InputError(f"{label}: negative jointWeights (point {int(np.nonzero(w < 0)[0][0])})")
    sums = _row_sums(w)
    if np.any(sums <= 0):
        raise InputError(f"{label}: all-zero jointWeights at point {int(np.nonzero(sums <= 0)[0][0])}: it follows no joint")
    notes = []
    off = np.abs(sums - 1.0) > 1e-3
    if off.any():
        notes.append(f"{label}: jointWeights of {int(off.sum())} point(s) do not sum to 1 (UsdSkel uses them as they are)")
    _check_skeleton_matrices(scene, skel_query)
    return notes


def _check_skeleton_matrices(scene: Scene, skel_query: UsdSkel.SkeletonQuery) -> None:
    """bindTransforms (and restTransforms when authored): one finite, non-singular matrix per joint."""
    skel = skel_query.GetSkeleton()
    skel_joints = skel_query.GetJointOrder()
    for name, attr in (("bindTransforms", skel.GetBindTransformsAttr()), ("restTransforms", skel.GetRestTransformsAttr())):
        value = attr.Get()
        if value is None and name == "restTransforms":
            continue
        where_attr = where(scene.label, str(skel.GetPrim().GetPath()), name)
        if value is None or len(value) != len(skel_joints):
            raise InputError(f"{where_attr}: {0 if value is None else len(value)} matrices for {len(skel_joints)} joints")
        mats = matrices(value)
        bad = is_singular(mats[:, :3, :3]) | ~np.all(np.isfinite(mats), axis=(1, 2))
        if bad.any():
            raise InputError(f"{where_attr}: joint {str(skel_joints[int(np.argmax(bad))])!r} has a NaN, infinite, "
                             "zero-scale or singular matrix")


def validate_animation(scene: Scene, mesh: str) -> None:
    """The bound animation must name only joints of the skeleton (UsdSkel drops others silently)."""
    _, skel_query = scene.query(mesh)
    anim = skel_query.GetAnimQuery()
    if not anim:
        return
    known = set(str(j) for j in skel_query.GetJointOrder())
    unknown = [str(j) for j in anim.GetJointOrder() if str(j) not in known]
    if unknown:
        raise InputError(
            f"{where(scene.label, str(anim.GetPrim().GetPath()), 'joints')}: joint {unknown[0]!r} is not in skeleton "
            f"<{skel_query.GetSkeleton().GetPrim().GetPath()}>"
        )
