"""Authoring primitives for psdbake's layers: prim and property specs, and numpy -> Vt.

Every writer builds an anonymous ``Sdf.Layer`` spec by spec (no stage, no composition),
in sorted, deterministic order; these are its building blocks. Values go in as float32 /
int32 / float64 arrays exactly as USD stores them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Gf, Sdf, Vt

#: An in-memory layer, as the library hands it around (for callers outside psdbake.usd).
Layer = Sdf.Layer


def over(layer: Sdf.Layer, path: str) -> Sdf.PrimSpec:
    """An ``over`` for path, its ancestors ``over`` too (Sdf.CreatePrimInLayer)."""
    return Sdf.CreatePrimInLayer(layer, Sdf.Path(path))


def define(layer: Sdf.Layer, path: str, type_name: str) -> Sdf.PrimSpec:
    spec = over(layer, path)
    spec.specifier = Sdf.SpecifierDef
    spec.typeName = type_name
    return spec


def attribute(
    prim: Sdf.PrimSpec, name: str, type_name: Sdf.ValueTypeName, value: Any = None, *, uniform: bool = False,
    custom: bool = False,
) -> Sdf.AttributeSpec:
    variability = Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying
    attr = prim.properties.get(name) if name in prim.properties else None
    if attr is None:
        attr = Sdf.AttributeSpec(prim, name, type_name, variability, custom)
    if value is not None:
        attr.default = value
    return attr


def apply_binding_api(prim: Sdf.PrimSpec) -> None:
    ops = prim.GetInfo("apiSchemas")
    items = list(ops.prependedItems) if ops else []
    if "SkelBindingAPI" not in items:
        prim.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=[*items, "SkelBindingAPI"]))


def relationship(prim: Sdf.PrimSpec, name: str, targets: Sequence[str]) -> None:
    rel = Sdf.RelationshipSpec(prim, name, custom=False)
    rel.targetPathList.explicitItems = [Sdf.Path(t) for t in targets]


def vec3f_array(values: NDArray[np.float64]) -> Vt.Vec3fArray:
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float32).reshape(-1, 3))


def double_array(values: NDArray[np.float64]) -> Vt.DoubleArray:
    return Vt.DoubleArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float64).reshape(-1))


def int_array(values: Any) -> Vt.IntArray:
    return Vt.IntArray.FromNumpy(np.ascontiguousarray(values, dtype=np.int32).reshape(-1))


def quatd_array(xyzw: NDArray[np.float64]) -> Vt.QuatdArray:
    return Vt.QuatdArray([Gf.Quatd(float(q[3]), Gf.Vec3d(float(q[0]), float(q[1]), float(q[2]))) for q in xyzw])
