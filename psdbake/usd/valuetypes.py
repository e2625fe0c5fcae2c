"""The value type of every attribute psdbake reads, checked once per composed stage.

A DCC that retyped an attribute, or a damaged file, would otherwise surface as a Python
error deep inside a fit; refused up front instead, naming the file that authors it.
"""

from __future__ import annotations

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


def check_value_types(stage: Usd.Stage, label: str) -> None:
    """Refuse an attribute psdbake reads that is authored with the wrong value type."""
    schemas = [(UsdGeom.PointBased, _SCHEMA_TYPES["PointBased"]), (UsdSkel.Skeleton, _SCHEMA_TYPES["Skeleton"]),
               (UsdSkel.Animation, _SCHEMA_TYPES["SkelAnimation"]), (UsdSkel.BlendShape, _SCHEMA_TYPES["BlendShape"])]
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        expected: dict[str, Sdf.ValueTypeName] = {}
        for schema, types in schemas:
            if prim.IsA(schema):
                expected.update(types)
        if prim.IsA(UsdGeom.PointBased):
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
