"""Weights over a shot: which correctives each animation drives, and their weights per frame.

``eval`` groups the corrected meshes by the SkelAnimation that poses them (one WEIGHTS
entry per animation), reads each frame's pose through UsdSkel, and evaluates every group's
stored RBF (``weights``) from the ``psd:`` attributes alone. The animation's own blend-shape
channels are kept, in front of psdbake's.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..arrays import Progress
from ..deformers import DeformerFactory
from ..errors import InputError, PsdWarning, where
from ..model.channels import channel_names, channel_weights
from ..model.data import DriverData
from ..model.rig import SkinnedMesh
from ..model.weights import check_driver_transforms, column_weights_of_local
from ..results import AnimWeights
from ..usd.blackbox import FLOAT32_MAX, SkinningBlackBox
from ..usd.posedpoints import PosedPoints, RestPoints
from ..usd.read import Scene
from ..usd.validate import checked_driver_groups, require_finite_time_samples, validate_animation

Corrected = tuple[SkinnedMesh, list[tuple[str, DriverData]]]  # a mesh and its correctives groups


def correctives_by_animation(scene: Scene, anim_scene: Scene, correctives: str, anim: str
                             ) -> dict[str, list[Corrected]]:
    """SkelAnimation path -> the corrected meshes it poses, each with its groups (checked)."""
    per_anim: dict[str, list[Corrected]] = {}
    for info in scene.skinned_meshes():
        groups = checked_driver_groups(scene, info)
        if not groups:
            continue
        anim_prim = scene.animation_prim(info.path)
        if anim_prim is None:
            raise InputError(f"{where(anim, info.skeleton)}: no SkelAnimation bound (skel:animationSource)")
        validate_animation(anim_scene, info.path)
        require_finite_time_samples(scene, anim_prim, anim)
        per_anim.setdefault(anim_prim, []).append((info, groups))
    return per_anim


def animation_weights(scene: Scene, anim_prim: str, entries: Sequence[Corrected], times: NDArray[np.float64],
                      correctives: str, anim: str, tick: Callable[[str], None]) -> AnimWeights:
    """Every channel's weight at every frame on one animation: its own channels, then every
    group's correctives. ``tick(mesh)`` is called once per mesh and frame posed."""
    own_channels, own_weights = scene.blend_shape_weights(entries[0][0].path, times)
    psd_channels: list[str] = []
    columns = []
    for info, groups in entries:
        local = np.empty((len(times), len(info.joints), 4, 4))
        for f, t in enumerate(times):  # UsdSkel's pose per frame: the slow part, so progress per frame
            local[f] = scene.joint_local_transforms(info.path, float(t))
            tick(info.path)
        for _, data in groups:
            idx = [info.joints.index(d) for d in data.drivers]
            check_driver_transforms(local[:, idx], times, data.drivers, where(anim, anim_prim))
        by_group = column_weights_of_local(groups, local, info.joints)
        for group, data in groups:
            b = _finite_weights(by_group[group], data, group, times, correctives, info)
            columns.append(_bounded_channels(b, data, group, times, correctives, info))
            psd_channels += channel_names(data)
    keep = [i for i, c in enumerate(own_channels) if c not in set(psd_channels)]
    channels = tuple([own_channels[i] for i in keep] + psd_channels)
    weights = np.concatenate([own_weights[:, keep], *columns], axis=1)
    return AnimWeights(anim_prim, channels, times, weights, len(psd_channels))


def _finite_weights(w: NDArray[np.float64], data: DriverData, group: str, times: NDArray[np.float64],
                    correctives: str, info: SkinnedMesh) -> NDArray[np.float64]:
    """Finite psd: values can still overflow: refuse rather than write inf into WEIGHTS."""
    bad = ~(np.abs(w) <= FLOAT32_MAX)  # NaN fails the comparison
    if bad.any():
        f, s = (int(i[0]) for i in np.nonzero(bad))
        raise InputError(
            f"{where(correctives, info.path)}: group {group!r} gives corrective {data.shapes[s]} the weight "
            f"{float(w[f, s]):.3g} at time {float(times[f]):g}: beyond float32's range (the psd: values "
            "are corrupt or absurdly large)"
        )
    return w


def _bounded_channels(b: NDArray[np.float64], data: DriverData, group: str, times: NDArray[np.float64],
                      correctives: str, info: SkinnedMesh) -> NDArray[np.float64]:
    """The written channel weights, max(0, b / scale). A weight above 1 (a pose beyond the
    reach the scales were set for) is written as is, so UsdSkel stays exact, and warned
    about once per channel: clients that clamp slider values to [0, 1] under-correct there."""
    if not len(data.channels):
        return b
    w = channel_weights(data, b)
    for c in map(int, np.nonzero(np.any(w > 1.0 + tol.CHANNEL_BOUND_SLACK, axis=0))[0]):
        f = int(np.argmax(w[:, c]))
        warnings.warn(
            f"{where(correctives, info.path)}: group {group!r} drives channel {data.channels[c]} to {w[f, c]:.3g} "
            f"at time {float(times[f]):g}, beyond the [0, 1] its psd:channelScales were set for: written as is "
            "(UsdSkel shows it exactly); clients that clamp shape-key values to [0, 1], as Blender does, "
            "under-correct there", PsdWarning, stacklevel=2)
    return w


def posed_points(rest_scene: Scene, scene: Scene, meshes: Sequence[SkinnedMesh], times: Sequence[float],
                 chain: Sequence[tuple[str, DeformerFactory]], progress: Progress | None
                 ) -> Iterator[tuple[str, float, PosedPoints]]:
    """(mesh, time, points) for every mesh and time: the black box applied to the rest points
    (``pose``'s examples to sculpt, ``eval``'s points cache), as USD stores them. The rest
    points and the work space are made once per mesh, not once per frame."""
    total, done = len(meshes) * len(times), 0
    for info in meshes:
        rest = RestPoints(rest_scene.rest_points(info.path))
        for t in times:
            yield info.path, t, SkinningBlackBox(scene, info.path, t, chain).posed(rest)
            done += 1
            if progress:
                progress(done, total, info.path)
