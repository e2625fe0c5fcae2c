"""EXAMPLES points in, SCULPTED_EXAMPLES out: the layer side of ``sculpts``.

Why a copy of EXAMPLES: ``pose`` wrote the poses (the bound animations' samples) and the
plain-skinned points; the sculpts replace the points samples and nothing else, so the
layer ``fit`` reads has exactly ``pose``'s layout and poses. Values stay float32 as USD
stores them, so an OBJ read back unedited gives the very bits ``pose`` wrote.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf

from .author import attribute, over, vec3f_array
from .compose import open_layer


def layer_points(layer: Sdf.Layer | str) -> dict[tuple[str, float], NDArray[np.float32]]:
    """(prim path, time code) -> the points time sample the layer itself authors, float32 (n, 3)."""
    layer = layer if isinstance(layer, Sdf.Layer) else open_layer(layer)
    found: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: found.append(p) if p.IsPropertyPath() and p.name == "points" else None)
    out = {}
    for path in sorted(found, key=str):
        for t in layer.ListTimeSamplesForPath(path):
            value = layer.QueryTimeSample(path, t)
            try:
                out[(str(path.GetPrimPath()), float(t))] = np.array(value, dtype=np.float32).reshape(-1, 3)
            except (TypeError, ValueError):
                continue  # not a point array: fit names it; sculpts finds no pose there
    return out


def sculpted_layer(examples: str, doc: str, sculpts: Iterable[tuple[str, float, NDArray[np.float32]]]) -> Sdf.Layer:
    """A copy of the EXAMPLES layer with the points sample of each (mesh, time, points) replaced."""
    layer = Sdf.Layer.CreateAnonymous("psdbake.usda")
    layer.TransferContent(open_layer(examples))
    layer.documentation = doc
    for mesh, t, pts in sculpts:
        attr = attribute(over(layer, mesh), "points", Sdf.ValueTypeNames.Point3fArray)
        layer.SetTimeSample(attr.path, float(t), vec3f_array(pts.astype(np.float64)))  # float32 -> 64 -> 32: exact
    return layer


def pose_only_layer(examples: str) -> Sdf.Layer:
    """A copy of an EXAMPLES layer without its points samples: the example's pose alone, as a
    client composes an ANIM over the asset (over it, the sculpted points would be skinned again)."""
    layer = Sdf.Layer.CreateAnonymous("psdbake.usda")
    layer.TransferContent(open_layer(examples))
    found: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: found.append(p) if p.IsPropertyPath() and p.name == "points" else None)
    for path in found:
        if layer.GetNumTimeSamplesForPath(path):
            prim = layer.GetPrimAtPath(path.GetPrimPath())
            prim.RemoveProperty(prim.properties[path.name])
    return layer
