"""The ``psd:`` schema, in one place: names, version, data classes, read and write.

Authored on each corrected mesh of a CORRECTIVES layer, all ``custom uniform``
(docs/reference/psd-schema.md): ``psd:version``, ``psd:groups`` (sorted) and each correctives
group's RBF driver data under ``psd:<group>:``. Version 1 (psdbake 0.1) held one flat group,
read as group ``main``. Readers refuse larger versions and validate every value on read,
naming the attribute, so evaluation never computes NaN weights from a tampered layer.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from math import comb
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Gf, Sdf, Usd, UsdSkel, Vt

from ..errors import InputError, where
from ..model.data import (
    DEFAULT_GROUP,
    PSD_ATTRIBUTES,
    PSD_OPTIONAL_SETS,
    PSD_VERSION,
    READABLE_PSD_VERSIONS,
    BlendShapeData,
    DriverData,
)
from ..model.posespace import POSE_SPACES
from ..model.rbf import KERNELS
from .author import attribute, double_array, int_array, over, quatd_array


def _type_names(names: dict[str, tuple[str, str, bool]]) -> dict[str, Sdf.ValueTypeName]:
    return {name: getattr(Sdf.ValueTypeNames, t) for name, (t, _, _) in names.items()}


#: Every psd: attribute's USD value type (``model.data.PSD_ATTRIBUTES``, the one table).
PSD_TYPES = _type_names(PSD_ATTRIBUTES)


# --- read ----------------------------------------------------------------------------------

def group_prefixes(prim: Usd.Prim, label: str) -> list[tuple[str, str]]:
    """[(group, attribute prefix)] of the correctives groups on prim, sorted by name; empty
    when prim has no psd: data. Refuses versions this psdbake cannot read."""
    mesh = str(prim.GetPath())
    version_attr = prim.GetAttribute("psd:version")
    if not version_attr or not version_attr.HasAuthoredValue():
        return []
    version = version_attr.Get()
    if version not in READABLE_PSD_VERSIONS:
        raise InputError(
            f"{where(label, mesh, 'psd:version')}: version {version} is not supported by this psdbake "
            f"(reads {', '.join(map(str, READABLE_PSD_VERSIONS))}); upgrade psdbake or re-fit"
        )
    if version == 1:
        return [(DEFAULT_GROUP, "psd:")]
    groups_attr = prim.GetAttribute("psd:groups")
    names = [str(g) for g in (groups_attr.Get() if groups_attr else None) or []]
    if not names:
        raise InputError(f"{where(label, mesh, 'psd:groups')}: missing or empty (the CORRECTIVES layer is incomplete)")
    if len(set(names)) != len(names):
        raise InputError(f"{where(label, mesh, 'psd:groups')}: a group is listed twice")
    return [(name, f"psd:{name}:") for name in sorted(names)]


def read_groups(prim: Usd.Prim, label: str, joints: Sequence[str] | None = None, skeleton: str = ""
                ) -> list[tuple[str, DriverData]]:
    """Every correctives group's driver data on prim, validated, sorted by group name.
    With ``joints`` (the bound skeleton's joint order), drivers must be among them."""
    groups = [(g, _GroupReader(prim, label, prefix).read(joints, skeleton)) for g, prefix in group_prefixes(prim, label)]
    return _check_gate_groups(groups, label, str(prim.GetPath()))


def _check_gate_groups(groups: list[tuple[str, DriverData]], label: str, mesh: str) -> list[tuple[str, DriverData]]:
    """The groups, each combination's gate directions shaped (shapes, coordinates). A
    combination's gate groups are other groups of the same mesh, themselves ungated (so the
    weights never depend on an order or a cycle), with one unit direction per shape each."""
    by_name = dict(groups)
    out = []
    for name, data in groups:
        if not data.gate_groups:
            out.append((name, data))
            continue
        at = where(label, mesh, f"psd:{name}:gateDirections")
        widths = []
        for gate in data.gate_groups:
            other = by_name.get(gate)
            why = ("is not one of psd:groups" if other is None else "is the group itself" if gate == name
                   else "is itself gated by groups" if other.gate_groups
                   else "is itself gated (psd:gates or psd:rampGates)" if len(other.gates) or len(other.ramp_gates)
                   else "")
            if why or other is None:
                raise InputError(f"{where(label, mesh, f'psd:{name}:gateGroups')}: gate group {gate!r} {why}")
            widths.append(POSE_SPACES[other.pose_space].width * len(other.drivers))
        flat = np.asarray(data.gate_directions).reshape(-1)
        if flat.size != len(data.shapes) * sum(widths):
            raise InputError(f"{at}: {flat.size} values; expected {len(data.shapes)} shapes x {sum(widths)} "
                             "gate-group pose coordinates")
        directions = flat.reshape(len(data.shapes), sum(widths))
        for gate, part in zip(data.gate_groups, np.split(directions, np.cumsum(widths)[:-1], axis=1), strict=True):
            if np.any(np.abs(np.linalg.norm(part, axis=1) - 1.0) > 1e-6):
                raise InputError(f"{at}: not a unit direction per shape for gate group {gate!r}")
        out.append((name, dataclasses.replace(data, gate_directions=directions)))
    return out


class _GroupReader:
    """Reads one group's attributes, each refusal naming ``FILE <MESH.psd:G:attr>``."""

    def __init__(self, prim: Usd.Prim, label: str, prefix: str) -> None:
        self.prim, self.label, self.prefix, self.mesh = prim, label, prefix, str(prim.GetPath())

    def at(self, name: str) -> str:
        return where(self.label, self.mesh, self.prefix + name)

    def get(self, name: str, required: bool = True) -> Any:
        attr = self.prim.GetAttribute(self.prefix + name)
        value = attr.Get() if attr else None
        if value is None and required:
            raise InputError(f"{self.at(name)}: missing (the CORRECTIVES layer is incomplete)")
        return value

    def numbers(self, name: str, value: Any = None) -> NDArray[np.float64]:
        """An attribute's values as float64 (a scalar becomes one value), or refuse its type."""
        value = self.get(name) if value is None else value
        try:
            return np.array(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"{self.at(name)}: {type(value).__name__} value is not numbers") from None

    def finite(self, name: str, values: NDArray[np.float64], why: str = "NaN or inf would make the weights NaN"
               ) -> NDArray[np.float64]:
        bad = np.nonzero(~np.isfinite(values))[0]
        if len(bad):
            raise InputError(f"{self.at(name)}: value {int(bad[0])} is {float(values[bad[0]])!r}: every value must be "
                             f"finite ({why})")
        return values

    def integers(self, name: str) -> NDArray[np.int64]:
        values = self.numbers(name)
        bad = np.nonzero(~np.isfinite(values) | (values != np.round(values)))[0]
        if len(bad):
            raise InputError(f"{self.at(name)}: value {int(bad[0])} is {float(values[bad[0]])!r}, not an integer")
        return values.astype(np.int64)

    def scalar(self, name: str) -> float:
        values = self.numbers(name)
        if len(values) != 1:
            raise InputError(f"{self.at(name)}: {len(values)} values, expected one number")
        return float(values[0])

    # -- the group ----------------------------------------------------------------------
    def read(self, joints: Sequence[str] | None, skeleton: str) -> DriverData:
        drivers = [str(d) for d in self.get("drivers")]
        space = str(self.get("poseSpace"))
        if space not in POSE_SPACES:
            raise InputError(f"{self.at('poseSpace')}: unknown pose space {space!r}")
        if joints is not None:
            missing = [d for d in drivers if d not in set(joints)]
            if missing:
                raise InputError(f"{self.at('drivers')}: joint {missing[0]!r} is not in skeleton <{skeleton}>")
        if str(self.get("kernel")) not in KERNELS:
            raise InputError(f"{self.at('kernel')}: unknown kernel {self.get('kernel')!r}")
        dims, centers, powers, coefficients, shapes = self._rbf_arrays(drivers, space)
        degree = self._degree(powers, len(dims))
        shift, scale = self._polynomial_frame(len(dims))
        return DriverData(
            drivers=drivers, bind_rotations=self._bind_rotations(drivers), pose_space=space,
            twist_axis=self._twist_axis(space), clamp_weights=bool(self.get("clampWeights", required=False) or False),
            normalize_weights=bool(self.get("normalizeWeights", required=False) or False),
            kernel=str(self.get("kernel")), sigma=self._sigma(), degree=degree, smoothing=self._smoothing(),
            centers=centers, center_labels=[str(s) for s in self.get("centerLabels")], shapes=shapes,
            coefficients=coefficients, powers=powers, shift=shift, scale=scale, dims=dims,
            example_times=[float(t) for t in self.finite("exampleTimes", self.numbers("exampleTimes"),
                                                         "time codes are finite numbers")],
            example_sources=[str(s) for s in self.get("exampleSources")],
            **self._gates(drivers, space), **self._gate_groups(), **self._ramps(drivers), **self._channels(len(shapes)),
        )

    def _rbf_arrays(self, drivers: list[str], space: str):
        """dimensions, centers (k, m), polyPowers (p, m), coefficients (k + p, s), shapes."""
        dims = self.integers("dimensions")
        dim = len(dims)
        shapes = [str(s) for s in self.get("shapes")]
        centers, powers, coefficients = self.numbers("centers"), self.integers("polyPowers"), self.numbers("coefficients")
        width = POSE_SPACES[space].width * len(drivers)
        if dim == 0 or dims.min() < 0 or dims.max() >= width or centers.size % dim or powers.size % dim:
            raise InputError(f"{where(self.label, self.mesh)}: {self.prefix} driver data sizes do not match "
                             f"{len(drivers)} drivers")
        centers, powers = centers.reshape(-1, dim), powers.reshape(-1, dim)
        rows = len(centers) + len(powers)
        if not shapes or coefficients.size != rows * len(shapes):
            raise InputError(f"{self.at('coefficients')}: expected {rows} x {len(shapes)} values, got {coefficients.size}")
        self.finite("centers", centers.reshape(-1))
        self.finite("coefficients", coefficients)
        return dims, centers, powers, coefficients.reshape(rows, len(shapes)), shapes

    def _gates(self, drivers: list[str], space: str) -> dict[str, Any]:
        """psd:gates (driver joints) and psd:gatePoses (g x width): each gate's activation
        clamp(x_j . g_j / g_j . g_j, 0, 1) multiplies the group's weights (docs/reference/psd-schema.md)."""
        gates = self._some_drivers("gates", drivers)
        if not gates:
            return {}
        width = POSE_SPACES[space].width
        poses = self.finite("gatePoses", self.numbers("gatePoses"))
        if poses.size != len(gates) * width:
            raise InputError(f"{self.at('gatePoses')}: {poses.size} values for {len(gates)} gates of {width} "
                             f"{space} coordinates")
        poses = poses.reshape(len(gates), width)
        if np.any(np.einsum("ij,ij->i", poses, poses) <= 0):
            raise InputError(f"{self.at('gatePoses')}: a gate pose is the bind pose (zero): its activation is undefined")
        return {"gates": gates, "gate_poses": poses}

    def _some_drivers(self, name: str, drivers: list[str]) -> list[str]:
        """psd:<name>, an optional list of some of psd:drivers, each listed once (empty if absent)."""
        gates = [str(g) for g in self.get(name, required=False) or []]
        unknown = [g for g in gates if g not in drivers]
        if unknown or len(set(gates)) != len(gates):
            raise InputError(f"{self.at(name)}: {unknown[0] if unknown else 'a gate'!r} is not one of psd:drivers "
                             "(listed once each)")
        return gates

    def _ramps(self, drivers: list[str]) -> dict[str, Any]:
        """psd:rampGates (v5: driver joints, listed once each) and psd:rampRadii (one finite
        radius > 0 each): each gate's min(1, |x_j| / r_j) multiplies the group's weights."""
        gates = self._some_drivers("rampGates", drivers)
        if not gates:
            return {}
        radii = self.finite("rampRadii", self.numbers("rampRadii"))
        if len(radii) != len(gates):
            raise InputError(f"{self.at('rampRadii')}: {len(radii)} values for {len(gates)} ramp gates")
        if np.any(radii <= 0):
            raise InputError(f"{self.at('rampRadii')}: a radius is not > 0 (the ramp divides by it)")
        return {"ramp_gates": gates, "ramp_radii": radii}

    def _channels(self, columns: int) -> dict[str, Any]:
        """psd:channels, psd:channelColumns (each in [0, shapes)) and psd:channelScales (finite,
        non-zero), one each per channel, names unique."""
        names = [str(c) for c in self.get("channels", required=False) or []]
        if not names:
            return {}
        if len(set(names)) != len(names):
            raise InputError(f"{self.at('channels')}: a channel is listed twice")
        cols, scales = self.integers("channelColumns"), self.finite("channelScales", self.numbers("channelScales"))
        for attr, values in (("channelColumns", cols), ("channelScales", scales)):
            if len(values) != len(names):
                raise InputError(f"{self.at(attr)}: {len(values)} values for {len(names)} channels")
        if np.any((cols < 0) | (cols >= columns)):
            raise InputError(f"{self.at('channelColumns')}: a column outside the {columns} psd:shapes")
        if np.any(scales == 0):
            raise InputError(f"{self.at('channelScales')}: a scale is 0 (a channel's weight would be undefined)")
        return {"channels": names, "channel_columns": cols, "channel_scales": scales}

    def _gate_groups(self) -> dict[str, Any]:
        """psd:gateGroups (v4: other groups of this mesh, listed once each) and
        psd:gateDirections (finite; sizes and norms checked by ``_check_gate_groups`` once
        every group is read)."""
        names = [str(g) for g in self.get("gateGroups", required=False) or []]
        if not names:
            return {}
        if len(set(names)) != len(names):
            raise InputError(f"{self.at('gateGroups')}: a group is listed twice")
        return {"gate_groups": names, "gate_directions": self.finite("gateDirections", self.numbers("gateDirections"))}

    def _sigma(self) -> float:
        sigma = self.scalar("sigma")
        if not (np.isfinite(sigma) and sigma > 0):
            raise InputError(f"{self.at('sigma')}: {sigma!r} is not a finite number > 0 (the RBF width in radians)")
        return sigma

    def _smoothing(self) -> float:
        smoothing = self.scalar("smoothing")
        if not (np.isfinite(smoothing) and smoothing >= 0):
            raise InputError(f"{self.at('smoothing')}: {smoothing!r} is not a finite number >= 0")
        return smoothing

    def _degree(self, powers: NDArray[np.int64], dim: int) -> int:
        """psd:degree, consistent with psd:polyPowers: the monomials of total degree <=
        degree in dim variables (scipy's RBFInterpolator's set, in any order), none for -1."""
        values = self.integers("degree")
        if len(values) != 1 or values[0] < -1:
            shown = int(values[0]) if len(values) == 1 else values.tolist()
            raise InputError(f"{self.at('degree')}: {shown!r} is not one integer >= -1 (-1: no polynomial term)")
        degree = int(values[0])
        expected = comb(dim + degree, dim) if degree >= 0 else 0
        sums = powers.sum(axis=1) if len(powers) else np.zeros(0, dtype=np.int64)
        distinct = len({tuple(row) for row in powers.tolist()}) == len(powers)
        if len(powers) != expected or np.any(powers < 0) or np.any(sums > degree) or not distinct:
            raise InputError(
                f"{self.at('polyPowers')}: {len(powers)} monomials do not match psd:degree {degree} in {dim} dimensions "
                f"(expected the {expected} distinct monomials of total degree <= {degree}{', none' if degree < 0 else ''})"
            )
        return degree

    def _polynomial_frame(self, dim: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        shift = self.finite("polyShift", self.numbers("polyShift"))
        scale = self.finite("polyScale", self.numbers("polyScale"))
        for name, values in (("polyShift", shift), ("polyScale", scale)):
            if len(values) != dim:
                raise InputError(f"{self.at(name)}: {len(values)} values for {dim} psd:dimensions (one per dimension)")
        if np.any(scale == 0):
            raise InputError(f"{self.at('polyScale')}: value {int(np.argmax(scale == 0))} is zero (the polynomial term "
                             "divides by it)")
        return shift, scale

    def _bind_rotations(self, drivers: list[str]) -> NDArray[np.float64]:
        quats = self.get("driverBindRotations")
        try:
            bind = np.array([[*q.GetImaginary(), q.GetReal()] for q in quats], dtype=np.float64).reshape(-1, 4)
        except (AttributeError, TypeError, ValueError):
            raise InputError(f"{self.at('driverBindRotations')}: not an array of quaternions") from None
        if len(bind) != len(drivers):
            raise InputError(f"{where(self.label, self.mesh)}: {self.prefix} driver data sizes do not match "
                             f"{len(drivers)} drivers")
        with np.errstate(over="ignore", invalid="ignore"):
            norms = np.linalg.norm(np.nan_to_num(bind, nan=0.0, posinf=0.0, neginf=0.0), axis=1)
        # psdbake writes unit quaternions; 1e-3 leaves room for hand-authored or rounded ones
        bad = np.nonzero(~np.all(np.isfinite(bind), axis=1) | ~(np.abs(norms - 1.0) < 1e-3))[0]
        if len(bad):
            raise InputError(f"{self.at('driverBindRotations')}: quaternion {int(bad[0])} (driver {drivers[bad[0]]!r}) "
                             f"is {tuple(bind[bad[0]][[3, 0, 1, 2]].tolist())!r}: not a unit quaternion (a rotation)")
        return bind

    def _twist_axis(self, space: str) -> tuple[float, ...] | None:
        twist = self.get("twistAxis", required=False)
        if space != "swingTwist":
            return None if twist is None else tuple(float(v) for v in self.numbers("twistAxis", twist))
        if twist is None:
            raise InputError(f"{self.at('twistAxis')}: missing: the swingTwist pose space needs the twist axis")
        axis = self.numbers("twistAxis", twist)
        if len(axis) != 3 or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise InputError(f"{self.at('twistAxis')}: {tuple(axis.tolist())!r} is not a finite non-zero 3-vector")
        return tuple(float(v) for v in axis)


def read_point_indices(prim: Usd.Prim) -> NDArray[np.int64]:
    """A BlendShape prim's pointIndices alone, without reading (for a ``.usdc``, unpacking)
    its offsets."""
    return np.array(UsdSkel.BlendShape(prim).GetPointIndicesAttr().Get() or [], dtype=np.int64)


def read_blend_shape(prim: Usd.Prim, channel: str) -> BlendShapeData:
    """A BlendShape prim's data (to carry groups a fit does not touch into an updated layer)."""
    shape = UsdSkel.BlendShape(prim)
    offsets = np.array(shape.GetOffsetsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
    indices = read_point_indices(prim)
    normals = shape.GetNormalOffsetsAttr().Get()
    return BlendShapeData(
        name=prim.GetName(), channel=channel, indices=indices, offsets=offsets,
        normal_offsets=np.array(normals, dtype=np.float64).reshape(-1, 3) if normals else None,
    )


def psd_prims(layer: Sdf.Layer) -> list[str]:
    """Prims on which layer itself authors psd:version (a CORRECTIVES layer's meshes), sorted."""
    found: list[str] = []

    def visit(path: Sdf.Path) -> None:
        if path.IsPropertyPath() and path.name == "psd:version":
            found.append(str(path.GetPrimPath()))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return sorted(found)


# --- write ---------------------------------------------------------------------------------

Put = Callable[[str, Sdf.ValueTypeName, Any], None]


def author_driver_data(layer: Sdf.Layer, mesh: str, groups: Sequence[tuple[str, DriverData]]) -> None:
    """psd: attributes on the mesh prim, every one uniform and custom: ``psd:version``,
    ``psd:groups`` (sorted names) and each group's data under ``psd:<group>:``, each with the
    type ``PSD_ATTRIBUTES`` gives it."""
    spec = over(layer, mesh)

    def put(name: str, value: Any) -> None:
        attribute(spec, f"psd:{name}", PSD_TYPES[name.rpartition(":")[2]], _value(PSD_ATTRIBUTES[
            name.rpartition(":")[2]][0], value), uniform=True, custom=True)

    put("version", PSD_VERSION)
    ordered = sorted(groups, key=lambda g: g[0])
    put("groups", [name for name, _ in ordered])
    for name, data in ordered:
        _author_group(put, f"{name}:", data)


def _set(value: Any) -> bool:
    """An optional attribute's field is set: not None and not empty."""
    return value is not None and (not hasattr(value, "__len__") or len(value) > 0)


def _author_group(put: Callable[[str, Any], None], prefix: str, data: DriverData) -> None:
    optional = {name: names[0] for names in PSD_OPTIONAL_SETS for name in names}
    for name, (_, field_name, is_optional) in PSD_ATTRIBUTES.items():
        if not field_name:
            continue
        if is_optional and not _set(getattr(data, PSD_ATTRIBUTES[optional[name]][1])):
            continue
        put(f"{prefix}{name}", getattr(data, field_name))


def _value(type_name: str, value: Any) -> Any:
    """A DriverData value as the USD value of its psd: type."""
    if type_name == "TokenArray":
        return Vt.TokenArray([str(v) for v in value])
    if type_name == "StringArray":
        return Vt.StringArray([str(v) for v in value])
    if type_name == "DoubleArray":
        return double_array(np.asarray(value, dtype=np.float64))
    if type_name == "IntArray":
        return int_array(value)
    if type_name == "QuatdArray":
        return quatd_array(value)
    if type_name == "Double3":
        return Gf.Vec3d(*map(float, value))
    return {"Token": str, "Double": float, "Int": int, "Bool": bool}[type_name](value)
