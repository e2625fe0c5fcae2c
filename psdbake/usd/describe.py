"""What a USD file holds, for ``psdbake inspect``: skeletons, skinned meshes, animations,
examples and psd: correctives. Works on an asset, an EXAMPLES/ANIM layer or a
CORRECTIVES layer on its own (overs included)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel

from .compose import compose, open_layer
from .read import Scene, hidden_from_usdskel, why_hidden
from .schema import read_groups

#: Two world matrices are the same transform when no entry differs by more than this
#: (relative to the largest entry, at least 1): float32-authored transforms agree to ~1e-7.
_SAME_TRANSFORM = 1e-6


def describe(path: str) -> dict:
    """A JSON-ready summary of path (sorted, deterministic)."""
    layer = open_layer(path)
    stage = compose([path])
    out: dict = {"file": path, "skel_roots": [], "skeletons": [], "meshes": [], "animations": [],
                 "examples": [], "correctives": [], "weights": [], "point_samples": [],
                 "sublayers": [str(p) for p in layer.subLayerPaths]}
    for prim in stage.TraverseAll():
        ppath = str(prim.GetPath())
        if prim.IsA(UsdSkel.Root):
            out["skel_roots"].append(ppath)
        elif prim.IsA(UsdSkel.Skeleton):
            joints = [str(j) for j in UsdSkel.Skeleton(prim).GetJointsAttr().Get() or []]
            anim = UsdSkel.BindingAPI(prim).GetAnimationSourceRel()
            targets = [str(t) for t in anim.GetTargets()] if anim else []
            out["skeletons"].append({"path": ppath, "joints": len(joints), "animation": targets[0] if targets else None,
                                     "joint_paths": joints})
        elif prim.IsA(UsdSkel.Animation):
            anim = UsdSkel.Animation(prim)
            joint_times = set(anim.GetRotationsAttr().GetTimeSamples()) | set(anim.GetTranslationsAttr().GetTimeSamples()) \
                | set(anim.GetScalesAttr().GetTimeSamples())
            shape_times = set(anim.GetBlendShapeWeightsAttr().GetTimeSamples())
            times = sorted(joint_times | shape_times)
            out["animations"].append({
                "path": ppath, "joints": len(anim.GetJointsAttr().Get() or []),
                "blend_shapes": [str(c) for c in anim.GetBlendShapesAttr().Get() or []],
                "samples": len(times), "joint_samples": len(joint_times), "blend_shape_samples": len(shape_times),
                "first": times[0] if times else None, "last": times[-1] if times else None,
            })
        elif prim.HasAttribute("blendShapeWeights"):  # an over (WEIGHTS, chunks through clips): no typed animation
            weights = _weights(prim)
            if weights is not None:
                out["weights"].append(weights)
        if prim.HasAttribute("points"):  # points over time, from this file or its clips (a points cache: overs)
            times = prim.GetAttribute("points").GetTimeSamples()
            if times:
                out["point_samples"].append({"mesh": ppath, "samples": len(times), "first": float(times[0]),
                                             "last": float(times[-1])})
        if prim.IsA(UsdGeom.PointBased) and prim.HasAPI(UsdSkel.BindingAPI):
            binding = UsdSkel.BindingAPI(prim)
            points = UsdGeom.PointBased(prim).GetPointsAttr().Get(Usd.TimeCode.Default())
            indices = binding.GetJointIndicesPrimvar()
            out["meshes"].append({
                "path": ppath,
                "points": len(points) if points is not None else None,
                "influences": indices.GetElementSize() if indices and indices.HasAuthoredValue() else None,
                "skinning_method": binding.GetSkinningMethodAttr().Get() if binding.GetSkinningMethodAttr() else None,
                "blend_shapes": [str(c) for c in binding.GetBlendShapesAttr().Get() or []],
            })
        out["correctives"] += _correctives(prim, path)
    # examples: points time samples this file itself authors (typed or not)
    found: list[tuple[str, list[float]]] = []

    def visit(spec_path: Sdf.Path) -> None:
        if spec_path.IsPropertyPath() and spec_path.name == "points":
            times = layer.ListTimeSamplesForPath(spec_path)
            if times:
                found.append((str(spec_path.GetPrimPath()), [float(t) for t in times]))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    out["examples"] = [{"mesh": m, "time_codes": t} for m, t in sorted(found)]
    out["warnings"] = [f"{path} <{mesh}>: {why_hidden(stage, blocker)}" for mesh, blocker in hidden_from_usdskel(stage)]
    out["warnings"] += client_layout_warnings(stage, path)
    return out


def _weights(prim: Usd.Prim) -> dict | None:
    """Blend-shape weights authored over time on a prim that is not (here) a typed
    SkelAnimation: a WEIGHTS layer's over of the asset's animation, or its chunks' clips."""
    attr = prim.GetAttribute("blendShapeWeights")
    times = attr.GetTimeSamples()
    if not times:
        return None
    channels = prim.GetAttribute("blendShapes").Get() if prim.HasAttribute("blendShapes") else None
    return {"path": str(prim.GetPath()), "channels": len(channels or []), "samples": len(times),
            "first": float(times[0]), "last": float(times[-1])}


def spelled_poses(scene: Scene, times: Sequence[float]) -> list[dict]:
    """Per time code, the joints turned from bind (beyond ``tol.ACTIVE_JOINT_ANGLE``) and by how
    much, largest first: what a TD means by "t=4: L_Elbow 90°". Per skeleton, over its first
    skinned mesh (every mesh it skins shares its pose)."""
    from ..model import posespace
    from ..model.posespace import active_joints

    out = []
    seen: set[str] = set()
    for info in scene.skinned_meshes():
        if info.skeleton in seen or scene.animation_prim(info.path) is None:
            continue
        seen.add(info.skeleton)
        bind = scene.bind_local_transforms(info.path)
        for t in times:
            q = posespace.relative_rotations(bind, scene.joint_local_transforms(info.path, float(t))).as_quat()
            angles = np.degrees(2.0 * np.arctan2(np.linalg.norm(q[:, :3], axis=1), np.abs(q[:, 3])))
            turned = sorted(active_joints(q.reshape(1, -1, 4))[0], key=lambda j: -angles[j])
            out.append({"skeleton": info.skeleton, "time": float(t),
                        "joints": [{"joint": info.joints[j], "degrees": round(float(angles[j]), 1)} for j in turned]})
    return out


def client_layout_warnings(stage: Usd.Stage, label: str) -> list[str]:
    """Skinned meshes that Blender's USD import places elsewhere than UsdSkel does.

    UsdSkel puts a skinned mesh's points at skeleton world x geomBindTransform (the mesh's own
    transforms do not count); Blender (5.0) parents the mesh object to the mesh's USD parent
    with geomBindTransform as its local matrix. The two agree only when that parent's world
    transform is the skeleton's (measured by ``make interop``: the arm fixture, whose /Arm/Geo
    and /Arm/Skel differ, lands 0.48 of its diagonal away in Blender)."""
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    out = []
    for prim in stage.Traverse():
        if not (prim.IsA(UsdGeom.PointBased) and prim.HasAPI(UsdSkel.BindingAPI)):
            continue
        skel = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
        if not skel:
            continue
        parent = np.array(cache.GetParentToWorldTransform(prim), dtype=np.float64)
        skel_world = np.array(cache.GetLocalToWorldTransform(skel.GetPrim()), dtype=np.float64)
        gap = float(np.abs(parent - skel_world).max())
        if gap > _SAME_TRANSFORM * max(1.0, float(np.abs(skel_world).max())):
            out.append(
                f"{label} <{prim.GetPath()}>: Blender's USD import will misplace this mesh (UsdSkel and psdbake do "
                f"not): Blender applies geomBindTransform under the mesh's parent <{prim.GetParent().GetPath()}>, "
                f"whose world transform differs from the skeleton <{skel.GetPrim().GetPath()}>'s (by up to {gap:.3g}); "
                "give that parent the skeleton's world transform"
            )
    return out


def _correctives(prim: Usd.Prim, label: str) -> list[dict]:
    """One entry per correctives group on prim, read and validated by the schema's reader
    (drivers are not checked against a skeleton: the file may be a CORRECTIVES layer alone)."""
    groups = read_groups(prim, label)
    if not groups:
        return []
    binding = UsdSkel.BindingAPI(prim)
    channels = [str(c) for c in binding.GetBlendShapesAttr().Get() or []]
    rel = binding.GetBlendShapeTargetsRel()
    targets = dict(zip(channels, rel.GetTargets() if rel else [], strict=False))
    version = prim.GetAttribute("psd:version").Get()
    out = []
    for group, data in groups:
        offsets = {}
        moved: set[int] = set()
        written = list(data.channels) or list(data.shapes)  # v4 writes channels; before, the shapes
        for channel in written:
            target = prim.GetStage().GetPrimAtPath(targets[channel]) if channel in targets else None
            if target and target.IsA(UsdSkel.BlendShape):
                indices = list(UsdSkel.BlendShape(target).GetPointIndicesAttr().Get() or [])
                offsets[target.GetName()] = len(indices)
                moved.update(indices)
        out.append({
            "mesh": str(prim.GetPath()), "group": group, "version": version, "drivers": list(data.drivers),
            "pose_space": data.pose_space, "kernel": data.kernel, "sigma": data.sigma, "degree": data.degree,
            "shapes": list(data.shapes), "channels": written, "examples": len(data.example_times),
            "offsets": offsets, "points": len(moved), "gate_groups": list(data.gate_groups),
            "ramp_gates": list(data.ramp_gates),
        })
    return out
