"""The value type of every attribute psdbake reads, checked once per composed stage.

A DCC that retyped an attribute, or a damaged file, would otherwise surface as a Python
error deep inside a fit; refused up front instead, naming the file that authors it.
"""

from __future__ import annotations

import enum

from pxr import Sdf, Usd, UsdGeom, UsdSkel

from ..errors import InputError, where
from .schema import PSD_TYPES


def _types(**names: str) -> dict[str, Sdf.ValueTypeName]:
    """name=TypeName pairs, ``__`` standing for ``:`` in attribute names."""
    return {name.replace("__", ":"): getattr(Sdf.ValueTypeNames, t) for name, t in names.items()}


#: The value type of every attribute psdbake reads, per schema (roles ignored: a float3[]
#: where point3f[] belongs is the same data). An attribute authored with another type (a
#: DCC that retyped it, a damaged file) is refused naming it, before any of it is used.
_SCHEMA_TYPES = {
    "PointBased": _types(points="Point3fArray", normals="Normal3fArray", primvars__normals="Normal3fArray",
                         faceVertexIndices="IntArray", faceVertexCounts="IntArray",
                         primvars__skel__jointIndices="IntArray", primvars__skel__jointWeights="FloatArray",
                         primvars__skel__geomBindTransform="Matrix4d", primvars__skel__skinningMethod="Token",
                         skel__joints="TokenArray", skel__blendShapes="TokenArray"),
    "Skeleton": _types(joints="TokenArray", bindTransforms="Matrix4dArray", restTransforms="Matrix4dArray"),
    "SkelAnimation": _types(joints="TokenArray", translations="Float3Array", rotations="QuatfArray",
                            scales="Half3Array", blendShapes="TokenArray", blendShapeWeights="FloatArray"),
    "BlendShape": _types(offsets="Vector3fArray", normalOffsets="Vector3fArray", pointIndices="IntArray"),
}


#: A BlendShape's attributes that only UsdSkel reads (applying the shape): ``eval``'s weights
#: never do.
SHAPE_VALUES = frozenset({"offsets", "normalOffsets"})


class Checked(enum.Enum):
    """Which attributes a stage's value types are checked for."""

    #: every attribute psdbake or UsdSkel reads
    ALL = "all"
    #: all but the BlendShapes' ``SHAPE_VALUES``: a stage that reads only their pointIndices
    #: (eval's weights: 2 of 3 checks per shape, and a CORRECTIVES holds one shape per channel)
    NO_SHAPE_VALUES = "no shape values"
    #: only the BlendShapes' ``SHAPE_VALUES``: the points cache's stage over the layers eval
    #: has just checked with ``NO_SHAPE_VALUES`` (0.4 ms of a 13k-point, 48-frame cache's 17)
    SHAPE_VALUES = "shape values"


def check_value_types(stage: Usd.Stage, label: str, checked: Checked = Checked.ALL) -> None:
    """Refuse an attribute psdbake reads that is authored with the wrong value type (those
    ``checked`` names). Each type's expected attributes are worked out once per type name, not
    per prim."""
    shape_types = _SCHEMA_TYPES["BlendShape"]
    if checked is Checked.SHAPE_VALUES:
        schemas = [(UsdSkel.BlendShape, {k: v for k, v in shape_types.items() if k in SHAPE_VALUES})]
    else:
        schemas = [(UsdGeom.PointBased, _SCHEMA_TYPES["PointBased"]), (UsdSkel.Skeleton, _SCHEMA_TYPES["Skeleton"]),
                   (UsdSkel.Animation, _SCHEMA_TYPES["SkelAnimation"]), (UsdSkel.BlendShape, shape_types)]
    if checked is Checked.NO_SHAPE_VALUES:
        schemas[-1] = (UsdSkel.BlendShape, {k: v for k, v in shape_types.items() if k not in SHAPE_VALUES})
    psd_attributes = checked is not Checked.SHAPE_VALUES  # psd: driver data on point-based prims
    by_type: dict[str, tuple[dict[str, Sdf.ValueTypeName], bool]] = {}  # type name -> (schema types, point-based)
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        type_name = prim.GetTypeName()
        if type_name not in by_type:  # IsA follows the type name alone (within one stage)
            found: dict[str, Sdf.ValueTypeName] = {}
            for schema, types in schemas:
                if prim.IsA(schema):
                    found.update(types)
            by_type[type_name] = found, psd_attributes and prim.IsA(UsdGeom.PointBased)
        schema_types, point_based = by_type[type_name]
        expected = dict(schema_types)
        if point_based:
            for name in prim.GetPropertyNames():
                if name.startswith("psd:"):
                    leaf = name.rsplit(":", 1)[-1]
                    if leaf in PSD_TYPES:
                        expected[name] = PSD_TYPES[leaf]
        for name, want in expected.items():
            attr = prim.GetAttribute(name)
            # the authored opinions' types: for a schema attribute the composed type name is the schema's
            for spec in attr.GetPropertyStack() if attr else []:
                if isinstance(spec, Sdf.AttributeSpec) and spec.typeName.type != want.type:
                    raise InputError(f"{where(spec.layer.identifier, str(prim.GetPath()), name)}: authored as "
                                     f"{spec.typeName}, where UsdSkel and psdbake read {want}")
