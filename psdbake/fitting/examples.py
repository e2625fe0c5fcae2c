"""The sculpted examples of a fit: gathered from the EXAMPLES files, each one checked.

Every time code at which an EXAMPLES file authors a skinned mesh's points is one example
(README: File conventions). All of them are checked here — point counts, finite values,
a bound animation, a usable pose, the binding left alone — before any is solved, so a
bad example fails in a second instead of after the long inverses.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from ..errors import FitError, InputError, where
from ..model import posespace
from ..model.rig import SkinnedMesh
from ..results import Example
from ..settings import FitSettings
from ..solver.solve import InverseTask, cached_rest, cached_scene
from ..usd.compose import open_layer
from ..usd.read import Scene, stray_point_prims
from ..usd.validate import check_examples_binding, require_finite_time_samples, validate_animation

Sculpt = tuple[Scene, str, float, NDArray[np.float64]]  # (stage, EXAMPLES file, time code, points (n, 3))


def gather_examples(
    asset: str, asset_scene: Scene, infos: Sequence[SkinnedMesh], meshes: Sequence[str], example_files: Sequence[str],
    settings: FitSettings,
) -> tuple[dict[str, list[Example]], list[InverseTask]]:
    """mesh -> its examples (poses), and one inverse task per example, in mesh then file order."""
    for path in example_files:  # the skinning fit inverts must be the one eval and UsdSkel apply
        check_examples_binding(asset_scene, cached_scene((path, asset)), path)
    found = _sculpts(asset_scene, example_files, meshes)
    for mesh in sorted(m for m in meshes if found[m]):
        asset_scene.require_not_instanced(mesh)  # before any worker starts
    if not any(found.values()):
        raise InputError(
            f"{', '.join(example_files)}: no examples: no points time samples on the skinned meshes "
            f"{', '.join(f'<{m}>' for m in meshes)}"
        )
    per_mesh: dict[str, list[Example]] = {}
    tasks: list[InverseTask] = []
    checked: set[tuple[int, str]] = set()
    for info in infos:
        if info.path not in meshes or not found[info.path]:
            continue
        rest = cached_rest(asset, info.path)  # read once: the solves take the same array
        bind_local = asset_scene.bind_local_transforms(info.path)
        for scene, source, t, sculpt in found[info.path]:
            if (id(scene), info.path) not in checked:
                _check_animation(scene, info, source, t)
                checked.add((id(scene), info.path))
            per_mesh.setdefault(info.path, []).append(_example(scene, info, source, t, sculpt, rest, bind_local))
            tasks.append(InverseTask(asset, source, info.path, t, settings.deformers, settings.rtol, len(rest)))
    return per_mesh, tasks


def _sculpts(asset_scene: Scene, example_files: Sequence[str], meshes: Sequence[str]) -> dict[str, list[Sculpt]]:
    """mesh path -> [(scene, file, time, sculpt)], in file order then time order."""
    found: dict[str, list[Sculpt]] = {m: [] for m in meshes}
    for path in example_files:
        layer = open_layer(path)
        scene = cached_scene((path, asset_scene.files[0]))  # the same stage the serial solves use
        stray = stray_point_prims(layer, {m.path for m in scene.skinned_meshes()})
        if stray:
            raise InputError(
                f"{where(path, stray[0], 'points')}: sculpted points on a prim that is not a skinned mesh "
                f"of {asset_scene.label}"
            )
        for mesh in meshes:
            for t in scene.authored_point_samples(layer, mesh):
                found[mesh].append((scene, path, t, scene.point_sample(layer, mesh, t)))
    return found


def _check_animation(scene: Scene, info: SkinnedMesh, source: str, t: float) -> None:
    anim = scene.animation_prim(info.path)
    if anim is None:
        raise InputError(
            f"{where(source, info.skeleton)}: no SkelAnimation bound (skel:animationSource), "
            f"so the example at time {t:g} has no pose"
        )
    validate_animation(scene, info.path)
    require_finite_time_samples(scene, anim, source)


def _example(scene: Scene, info: SkinnedMesh, source: str, t: float, sculpt: NDArray[np.float64],
             rest: NDArray[np.float64], bind_local: NDArray[np.float64]) -> Example:
    """One example, checked: a finite time code, the mesh's point count, finite points, a pose."""
    mesh = info.path
    if not np.isfinite(t):
        raise InputError(f"{where(source, mesh, 'points')}: example at time code {t!r}: USD accepts a time "
                         "sample at inf, but an example needs a finite time code (its pose is there)")
    if sculpt.shape != rest.shape:
        raise InputError(f"{where(source, mesh, 'points')}: example at time {t:g} has {len(sculpt)} points, "
                         f"the asset's mesh has {len(rest)}")
    if not np.all(np.isfinite(sculpt)):
        raise InputError(f"{where(source, mesh, 'points')}: example at time {t:g} contains NaN or inf")
    local = scene.joint_local_transforms(mesh, t)
    bad = np.nonzero(posespace.undefined_rotations(local))[0]
    if len(bad):  # a zero-scale joint has no rotation: no pose, and skinning through it cannot be inverted
        raise FitError(
            f"{where(scene.label, mesh)}: joint {info.joints[bad[0]]!r} has zero scale (or NaN) at time {t:g}: "
            "its pose is undefined and skinning through it cannot be inverted"
        )
    pose = posespace.relative_rotations(bind_local, local).as_quat().reshape(-1, 4)
    return Example(label=f"{os.path.basename(source)}@{t:g}", source=source, time=t, pose=pose)
