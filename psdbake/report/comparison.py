"""Plain skinning vs forward PSD vs inverse PSD, frame by frame (the paper's analysis).

For each frame x of an animation, with the *same* cardinal RBF weights b_j(x):

- SSD:      SKINNING_x(rest)
- forward:  SKINNING_x(rest) + sum_j b_j(x) delta_j      delta_j = sculpt_j - SKINNING_j(rest)
            (posed-space deltas, interpolated and added after skinning)
- inverse:  SKINNING_x(rest + sum_j b_j(x) d'_j)          d'_j from the black-box inverse (psdbake)

so the comparison isolates the one thing the paper changes: the space in which the
examples are interpolated. The correction vector of a vertex is the result minus SSD.

The eval numerics (``frames_of``, ``driver_weights``, ``check_driver_transforms``) are
the ones ``psdbake eval`` uses, so the weights here are the weights psdbake ships.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .. import api
from .. import tolerances as tol
from ..arrays import Points, Progress
from ..deformers import DeformerFactory, load_deformers
from ..errors import InputError, where
from ..model import posespace
from ..model.data import DEFAULT_GROUP
from ..model.weights import check_driver_transforms, driver_weights
from ..results import FitResult, MeshFit
from ..settings import FitSettings
from ..shot.frames import check_authored, frames_of
from ..usd.blackbox import SkinningBlackBox
from ..usd.compose import open_layer
from ..usd.read import Scene


@dataclass(frozen=True)
class MeshComparison:
    """Per-frame results for one mesh."""

    mesh: str
    times: NDArray[np.float64]  # (f,)
    driver_angles: NDArray[np.float64]  # (f, drivers) rotation angle of each driver, radians
    weights: NDArray[np.float64]  # (f, s) cardinal weights
    ssd: NDArray[np.float64]  # (f, n, 3)
    forward: NDArray[np.float64]  # (f, n, 3)
    inverse: NDArray[np.float64]  # (f, n, 3)
    corrected: NDArray[np.int64]  # vertices with a corrective in any example
    diagonal: float


@dataclass(frozen=True)
class Comparison:
    """A fit and, per fitted mesh, its three results over the animation anim."""

    fit: FitResult
    anim: str
    meshes: tuple[MeshComparison, ...]


def posed_deltas(fit_result: FitResult, mesh_fit: MeshFit) -> list[Points]:
    """delta_j = sculpt_j - SKINNING_j(rest) per example (forward PSD's data), (n, 3) each."""
    asset = fit_result.asset
    rest = Scene([asset]).rest_points(mesh_fit.mesh)
    chain = load_deformers(fit_result.settings.deformers)
    out = []
    for ex in mesh_fit.examples:
        scene = Scene([ex.source, asset], label=ex.source)
        sculpt = scene.point_sample(open_layer(ex.source), mesh_fit.mesh, ex.time)
        out.append(sculpt - SkinningBlackBox(scene, mesh_fit.mesh, ex.time, chain)(rest))
    return out


def compare(
    asset: str,
    example_files: Sequence[str],
    anim: str,
    settings: FitSettings | None = None,
    *,
    frames: tuple[float, float] | None = None,
    fit_result: FitResult | None = None,
    hold: bool = False,
    progress: Progress | None = None,
) -> Comparison:
    """Fit (unless given) and evaluate SSD, forward PSD and inverse PSD at every frame.

    The comparison is the paper's set-up: one RBF over the drivers (one correctives group,
    ``main`` unless ``settings.group`` names another), so forward and inverse PSD share
    exactly the same weights; ``psdbake fit``'s local, additive groups are not used here.
    ``frames`` is checked against ANIM's authored samples before the fit (``hold``)."""
    settings = settings or FitSettings()
    settings = dataclasses.replace(settings, group=settings.group or DEFAULT_GROUP)
    scene = Scene([anim, asset], label=anim)
    infos = {i.path: i for i in scene.skinned_meshes()}
    unbound = sorted({i.skeleton for i in infos.values() if scene.animation_prim(i.path) is None})
    if infos and len(unbound) == len({i.skeleton for i in infos.values()}):  # ANIM poses none of them: another shot's?
        raise InputError(f"{where(anim, unbound[0])}: no SkelAnimation bound (skel:animationSource): {anim} does not "
                         f"animate {asset}'s skeleton (another asset's animation?)")
    if frames is not None:
        for info in infos.values():
            if scene.animation_prim(info.path) is not None:
                check_authored(scene, info.path, frames, anim, hold=hold)
    result = fit_result or api.fit(asset, example_files, settings, progress=progress)
    chain = load_deformers(result.settings.deformers)
    meshes = [_compare_mesh(scene, result, m, infos[m.mesh].joints, anim, frames, chain) for m in result.meshes]
    if not meshes:
        raise InputError(f"{asset}: nothing was fitted, nothing to compare")
    return Comparison(result, anim, tuple(meshes))


def _offsets(result: FitResult, m: MeshFit, rest: Points, outputs: list[int]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Per output channel the rest-space offsets (inverse PSD) and the posed-space deltas
    (forward PSD), (s, n, 3) each, and the vertices psdbake corrects."""
    d_rest = np.zeros((len(outputs), *rest.shape))
    for k, j in enumerate(outputs):
        inv = m.inverses[j]
        d_rest[k, inv.indices] = inv.offsets
    deltas = posed_deltas(result, m)
    d_posed = np.stack([deltas[j] for j in outputs])
    # forward PSD interpolates the same vertices psdbake corrects
    corrected = np.unique(np.concatenate([m.inverses[j].indices for j in outputs]))
    mask = np.zeros(len(rest), dtype=bool)
    mask[corrected] = True
    d_posed[:, ~mask] = 0.0
    return d_rest, d_posed, corrected


def _compare_mesh(scene: Scene, result: FitResult, m: MeshFit, joints: Sequence[str], anim: str,
                  frames: tuple[float, float] | None, chain: Sequence[tuple[str, DeformerFactory]]) -> MeshComparison:
    """SSD, forward and inverse PSD of one fitted mesh at every frame, with the same weights."""
    data = m.driver_data
    idx = [joints.index(d) for d in data.drivers]
    times = frames_of(scene, m.mesh, frames, hold=True)  # checked by compare
    rest = scene.rest_points(m.mesh)
    outputs = [j for j, ch in enumerate(m.channels) if ch]
    d_rest, d_posed, corrected = _offsets(result, m, rest, outputs)
    f = len(times)
    ssd, fwd, inv_pts = (np.empty((f, *rest.shape)) for _ in range(3))
    weights = np.empty((f, len(outputs)))
    angles = np.empty((f, len(idx)))
    for i, t in enumerate(times):
        local = scene.joint_local_transforms(m.mesh, float(t))[idx]
        check_driver_transforms(local[None], [t], data.drivers, where(anim, m.mesh))
        angles[i] = posespace.relative_from_quaternions(data.bind_rotations, local).magnitude()
        weights[i] = driver_weights(data, local[None])[0]
        box = SkinningBlackBox(scene, m.mesh, float(t), chain)
        ssd[i] = box(rest)
        fwd[i] = ssd[i] + np.tensordot(weights[i], d_posed, axes=1)
        inv_pts[i] = box(rest + np.tensordot(weights[i], d_rest, axes=1))
    # the unit of the fit's tolerances: the skinned mesh's diagonal at the example poses
    # (independent of --frames; rest points may sit in another space, see geomBindTransform)
    diag = max(m.inverses[j].diagonal for j in outputs)
    return MeshComparison(m.mesh, times, angles, weights, ssd, fwd, inv_pts, corrected, diag)


def correction_turn(comparison: MeshComparison, vertex: int, reference: int | None = None
                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """How far the correction vector of one vertex has turned, per frame: the angle
    (radians) between its direction at each frame and at the reference frame (default: the
    frame where the inverse correction is largest). The paper's Figure 3 quantity.

    Returns (forward, inverse), each (f,); NaN where a correction vanishes."""
    fwd = comparison.forward[:, vertex] - comparison.ssd[:, vertex]
    inv = comparison.inverse[:, vertex] - comparison.ssd[:, vertex]
    if reference is None:
        reference = int(np.argmax(np.linalg.norm(inv, axis=1)))
    out = []
    for c in (fwd, inv):
        norms = np.linalg.norm(c, axis=1)
        # below float32 round-off of the points a correction has no direction
        live = norms > tol.float32_floor(comparison.ssd[:, vertex])
        angle = np.full(len(c), np.nan)
        if live[reference]:
            u = c[live] / norms[live, None]
            ref = c[reference] / norms[reference]
            angle[live] = np.arccos(np.clip(u @ ref, -1.0, 1.0))
        out.append(angle)
    return out[0], out[1]


def most_corrected_vertex(comparison: MeshComparison) -> int:
    """The vertex whose inverse-PSD correction is largest over the animation."""
    mag = np.linalg.norm(comparison.inverse - comparison.ssd, axis=2).max(axis=0)
    return int(np.argmax(mag))
