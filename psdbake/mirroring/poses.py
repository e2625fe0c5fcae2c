"""A correctives group's pose space reflected onto the partner joints, and its RBF refitted.

Driver J's pose coordinates encode Delta, its local rotation away from its bind local
rotation. With its parents at bind that is the skeleton-space turn D = B_J Delta B_J^-1
(B_J: J's skeleton-space bind rotation). The mirror image of the turn is M D M (M the
reflection), and the partner J' turning by it has

    Delta' = B_J'^-1 M B_J Delta B_J^-1 M B_J' = P Delta P^-1,   P = -B_J'^-1 M B_J,

P a proper rotation (M has determinant -1). A joint's skinning matrix is the product of
such turns down its chain (S_J = S_parent D_J), so mirroring every driver this way mirrors
the skinned mesh whatever the parents do, and the partners' bind orientations need not be
mirror images of the drivers' (only their positions, ``symmetry.check_joints``).

Conjugation by a rotation acts linearly and isometrically on every pose space's
coordinates (``COORDINATE_MAPS``; ``tests/test_mirror.py`` checks each against recovering
Delta from its coordinates, conjugating and recomputing them): the mirrored centres are
that map of the stored ones, distances between poses are unchanged, and the cardinal RBF
refitted over them (same kernel, sigma, degree, smoothing) gives each mirrored pose the
source's weights at the source pose.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import block_diag
from scipy.spatial.transform import Rotation

from .. import tolerances as tol
from ..errors import FitError, InputError
from ..fitting import rbf_fit as rbf
from ..model import posespace
from ..model.data import DriverData
from ..model.rig import BindSpace
from ..model.weights import rbf_from_driver_data


def _rotation_vector(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return p  # rotvec(P Delta P^-1) = P rotvec(Delta)


def _swing_twist(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return block_diag(p, np.eye(1))  # [rotvec(swing), twist] -> [P rotvec(swing), twist], the axis turned by P


def _chordal(p: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.asarray(np.kron(p, p), dtype=np.float64)  # vec(P (R - I) P^T) = (P kron P) vec(R - I), row-major


#: pose space -> the matrix (width x width) taking a driver's coordinates of Delta to those of
#: P Delta P^-1, for a proper rotation P (3 x 3, column convention).
COORDINATE_MAPS: dict[str, Callable[[NDArray[np.float64]], NDArray[np.float64]]] = {
    "rotationVector": _rotation_vector,
    "swingTwist": _swing_twist,
    "quaternion": _chordal,
}


def rotations_of(x: NDArray[np.float64], space: str, twist_axis: Sequence[float] | None) -> Rotation:
    """The rotations (n) whose pose coordinates are x (n, width): every pose space is invertible
    (rotation vectors; swing . twist about the axis; R - I, projected onto the nearest rotation)."""
    x = np.asarray(x, dtype=np.float64).reshape(-1, posespace.POSE_SPACES[space].width)
    if space == "rotationVector":
        return Rotation.from_rotvec(x)
    if space == "swingTwist":
        axis = np.asarray(twist_axis, dtype=np.float64)
        return Rotation.from_rotvec(x[:, :3]) * Rotation.from_rotvec(x[:, 3:4] * (axis / np.linalg.norm(axis)))
    if space == "quaternion":
        return Rotation.from_matrix(x.reshape(-1, 3, 3) + np.eye(3))
    raise InputError(f"pose space {space!r} has no inverse")


def sculpted_rotations(groups: Mapping[str, DriverData]) -> dict[str, NDArray[np.float64]]:
    """joint -> the distinct rotations away from bind (k, 4) its groups' centres give it: the
    anchors of the sampled channel reach (``weights.sampled_ranges``), which a fit takes from
    its examples (``correctives``) and a mirrored layer only has as centres. Coordinates left
    out of ``psd:dimensions`` are taken as 0 (constant across the centres, 0 at bind)."""
    found: dict[str, list[NDArray[np.float64]]] = {}
    for data in groups.values():
        w = posespace.POSE_SPACES[data.pose_space].width
        full = np.zeros((len(data.centers), w * len(data.drivers)))
        full[:, data.dims] = data.centers
        for k, joint in enumerate(data.drivers):
            found.setdefault(joint, []).append(rotations_of(full[:, k * w:(k + 1) * w], data.pose_space,
                                                            data.twist_axis).as_quat().reshape(-1, 4))
    return {j: np.unique(np.round(np.concatenate(q), 12), axis=0) for j, q in sorted(found.items())}


def driver_turns(bind: BindSpace, pairs: dict[str, str], m: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
    """driver -> P = -B_J'^-1 M B_J: the rotation that conjugates its local turns into its partner's."""
    index = {j: i for i, j in enumerate(bind.joints)}
    out = {}
    for joint, partner in pairs.items():
        b, b2 = (posespace.rotations(bind.bind_world[index[j]]).as_matrix().reshape(3, 3) for j in (joint, partner))
        out[joint] = -(b2.T @ m @ b)
    return out


def coordinate_map(space: str, turns: Sequence[NDArray[np.float64]], order: Sequence[int]) -> NDArray[np.float64]:
    """(w d, w d): a group's pose coordinates (drivers in their order, turns[j] each) to the
    mirrored group's (new driver k is old driver order[k])."""
    if space not in COORDINATE_MAPS:
        raise InputError(f"pose space {space!r} has no mirror map")
    w = posespace.POSE_SPACES[space].width
    out = np.zeros((w * len(order), w * len(turns)))
    for k, j in enumerate(order):
        out[k * w:(k + 1) * w, j * w:(j + 1) * w] = COORDINATE_MAPS[space](turns[j])
    return out


def mirrored_twist_axis(data: DriverData, turns: Sequence[NDArray[np.float64]], where_: str
                        ) -> tuple[float, ...] | None:
    """The partners' twist axis (swingTwist): P a, which must be one axis for every driver
    (``psd:twistAxis`` is shared by a group's drivers)."""
    if data.pose_space != "swingTwist" or data.twist_axis is None:
        return data.twist_axis
    axis = np.asarray(data.twist_axis, dtype=np.float64)
    turned = [p @ axis for p in turns]
    if any(np.linalg.norm(t - turned[0]) > 1e-6 * np.linalg.norm(axis) for t in turned):
        raise InputError(f"{where_}: the drivers' twist axis {tuple(axis.tolist())} turns into different axes for "
                         "their partners, and psd:twistAxis is one axis for the group: mirror it driver by driver")
    return tuple(float(v) for v in turned[0])


def _full_centres(data: DriverData, mapping: NDArray[np.float64], where_: str) -> NDArray[np.float64]:
    """The stored centres over every pose coordinate. Coordinates left out of
    ``psd:dimensions`` (no example varies them, ``rbf``) are constant: 0 when the bind pose
    is a centre; otherwise unknown, which is harmless only when the map sends them to
    coordinates of their own (then left out of the refit too)."""
    width = len(mapping)
    full = np.zeros((len(data.centers), width))
    full[:, data.dims] = data.centers
    dropped = np.setdiff1d(np.arange(width), data.dims)
    if not len(dropped) or "bind" in data.center_labels:
        return full
    mixes = np.abs(mapping[:, dropped]).max(axis=1) > 1e-12
    if np.any(np.abs(mapping[np.ix_(mixes, data.dims)]) > 1e-12):
        raise InputError(f"{where_}: its RBF leaves out pose coordinates that no example varies (psd:dimensions) and "
                         "has no bind-pose centre, so the examples' full poses are not stored, and the mirror mixes "
                         "those coordinates with the others: refit the group with the rest example, or fit the other "
                         "side from its own sculpts")
    return full


def mirror_rbf(data: DriverData, mapping: NDArray[np.float64], where_: str) -> DriverData:
    """The group's RBF over the mirrored centres (``mapping``: ``coordinate_map``), refitted with
    its kernel, sigma, degree and smoothing, each column scaled to the source's value at its
    own example (1, or a combination's 1 / gate product). Refused (FitError) when the refit
    does not give the mirrored poses the source's weights (a polynomial term over coordinates
    the mirror mixes)."""
    full = _full_centres(data, mapping, where_)
    new = full @ mapping.T
    source = rbf_from_driver_data(data)
    b_src = source.weights(full)
    outputs = [int(i) for i in np.argmax(np.abs(b_src), axis=0)]
    if len(set(outputs)) != len(outputs):
        raise InputError(f"{where_}: not a cardinal RBF (two correctives peak at one example pose)")
    if len(new) == 1 and data.degree <= 0:  # one centre: a constant (a one-example combination), kept as stored
        width = new.shape[1]
        model = rbf.CardinalRbf(centers=new, kernel=data.kernel, sigma=data.sigma, degree=data.degree,
                                smoothing=data.smoothing, coefficients=data.coefficients,
                                powers=np.zeros((len(data.powers), width), dtype=np.int64), shift=np.zeros(width),
                                scale=np.ones(width), dims=np.arange(width, dtype=np.int64))
        factors = np.ones(len(outputs))
    else:
        plan = rbf.plan_rbf(new, outputs, list(data.center_labels), kernel=data.kernel,
                            sigma=None if data.kernel in rbf.SCALE_FREE else data.sigma, degree=data.degree,
                            smoothing=data.smoothing, where=where_)
        model = plan.model(outputs)
        b_new = model.weights(new)
        factors = np.array([b_src[i, s] / b_new[i, s] for s, i in enumerate(outputs)])
        model = dataclasses.replace(model, coefficients=model.coefficients * factors[None, :])
    some = full[:40]  # the centres, beyond them and between them (pairs of at most 40: milliseconds)
    probe = np.concatenate([full, 1.5 * full, (some[:, None] + some[None, :]).reshape(-1, full.shape[1]) / 2])
    miss = float(np.max(np.abs(model.weights(probe @ mapping.T) - source.weights(probe)), initial=0.0))
    if miss > tol.CARDINAL_ATOL * max(1.0, float(np.max(np.abs(b_src)))):
        raise FitError(f"{where_}: the refitted RBF does not give the mirrored poses the source's weights (off by "
                       f"{miss:.2g}): its polynomial term (psd:degree {data.degree}) is over pose coordinates the "
                       "mirror mixes; fit the other side from its own sculpts")
    return dataclasses.replace(
        data, kernel=model.kernel, sigma=model.sigma, degree=model.degree, smoothing=model.smoothing,
        centers=model.centers, coefficients=model.coefficients, powers=model.powers, shift=model.shift,
        scale=model.scale, dims=model.dims,
    )


def mirror_gate_poses(data: DriverData, turns: dict[str, NDArray[np.float64]], names: Callable[[str], str]) -> dict:
    """v3 joint gates (``psd:gates``, ``psd:gatePoses``) on the partners: their names mapped,
    each gate pose turned by its driver's map."""
    if not len(data.gates):
        return {}
    maps = [COORDINATE_MAPS[data.pose_space](turns[g]) for g in data.gates]
    poses = np.array([m @ p for m, p in zip(maps, np.asarray(data.gate_poses), strict=True)])
    return {"gates": [names(g) for g in data.gates], "gate_poses": poses}
