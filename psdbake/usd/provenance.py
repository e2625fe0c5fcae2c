"""Provenance: what every output layer records about how it was made, and the checks it allows.

Each layer psdbake writes carries ``customLayerData["psdbake"]``:

- ``kind``: what the layer is (``outputs.LABELS``), so a later command knows its own earlier
  output from an asset or a sculpt it must not replace, and ``stack`` knows each layer's role;
- ``version`` and ``command`` (the command line, paths relative to the output);
- ``inputs``: each input file typed on the command line, by role, with its path relative to the
  output and the SHA-256 of its bytes;
- ``rig``: per skinned mesh of the asset, its skinning method and digests of what the
  correctives depend on (rest points, influences and geomBindTransform; the skeleton's joints
  and bind/rest transforms), so that ``eval``, ``stack``, ``mirror`` and ``export-gltf`` can
  say when the asset or its skinning is no longer the one the correctives were fitted on;
- ``deformers`` and ``settings`` where the command has them; ``groups`` on CORRECTIVES: how
  each group was made (``fit``, ``fit --group``, ``mirror`` of another group).

Nothing depends on where or when the command ran: paths are relative to the output, and there
is no time stamp, host or user, so the same inputs still give the same bytes.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from pxr import Sdf, Usd, UsdSkel, Vt

from .. import __version__
from .integrity import is_crate, require_readable_crates

if TYPE_CHECKING:
    from .read import Scene

KEY = "psdbake"

#: Layers written before provenance existed are known by their ``doc`` line:
#: "psdbake VERSION COMMAND: what" -> kind.
_DOC_KINDS = (
    (re.compile(r"psdbake (\S+ )?pose: "), "examples"),
    (re.compile(r"psdbake (\S+ )?sculpts: "), "sculpted_examples"),
    (re.compile(r"psdbake (\S+ )?(fit|mirror): "), "correctives"),
    (re.compile(r"psdbake (\S+ )?eval: points cache"), "points_cache"),
    (re.compile(r"psdbake (\S+ )?eval: "), "weights"),
    (re.compile(r"psdbake (\S+ )?stack: "), "stack"),
    (re.compile(r"psdbake clip manifest: "), "clip_manifest"),
)


# --- reading -------------------------------------------------------------------------------

def _metadata(path: str) -> Sdf.Layer | None:
    """The layer's metadata only (no prims read), or None when it is not a readable layer.
    A binary layer is first read whole by the crate probe: a corrupt one must not crash us."""
    try:
        if is_crate(path):
            require_readable_crates([path])
        return Sdf.Layer.OpenAsAnonymous(path, metadataOnly=True)
    except Exception:
        return None


def stamp_of(layer: Sdf.Layer) -> dict[str, Any]:
    """The provenance a layer carries (empty when none)."""
    data = layer.customLayerData.get(KEY)
    return dict(data) if isinstance(data, dict) else {}


def layer_kind(layer: Sdf.Layer) -> str | None:
    """The kind a layer was stamped with, or the kind its ``doc`` line names (older psdbake)."""
    kind = stamp_of(layer).get("kind")
    if isinstance(kind, str):
        return kind
    doc = layer.documentation or ""
    return next((k for pattern, k in _DOC_KINDS if pattern.match(doc)), None)


def existing_kind(path: str) -> str | None:
    """The kind of the psdbake layer at path, or None when it is not one."""
    layer = _metadata(path)
    return layer_kind(layer) if layer is not None else None


def read_stamp(path: str) -> dict[str, Any]:
    """The provenance of the layer file at path (empty when it has none or cannot be read)."""
    layer = _metadata(path)
    return stamp_of(layer) if layer is not None else {}


def describe_foreign(path: str) -> str:
    """What a layer psdbake did not write is, for a refusal: an asset, an animation, other."""
    try:
        if is_crate(path):
            require_readable_crates([path])
        layer = Sdf.Layer.FindOrOpen(path)
    except Exception:
        return "not a readable USD layer"
    if layer is None:
        return "not a readable USD layer"
    found: list[str] = []

    def visit(spec_path: Sdf.Path) -> None:
        if spec_path.IsPrimPath() and not found:
            spec = layer.GetPrimAtPath(spec_path)
            if spec and spec.typeName in ("SkelRoot", "SkelAnimation"):
                found.append(spec.typeName)

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    if found == ["SkelRoot"]:
        return "a USD asset (it defines a SkelRoot)"
    if found == ["SkelAnimation"]:
        return "a USD animation layer (it defines a SkelAnimation)"
    return "a USD layer psdbake did not write"


# --- writing -------------------------------------------------------------------------------

def file_sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def relative(path: str, output: str) -> str:
    """path as seen from the output's folder, with forward slashes (the layer may move with it)."""
    rel = os.path.relpath(os.path.abspath(path), os.path.dirname(os.path.abspath(output)))
    return rel.replace(os.sep, "/")


def inputs_record(inputs: Mapping[str, str | Sequence[str]], output: str) -> dict[str, Any]:
    """{role: {"path": relative path, "sha256": digest}} (a list of them for repeated roles)."""
    out: dict[str, Any] = {}
    for role, value in inputs.items():
        paths = [value] if isinstance(value, str) else list(value)
        entries = [{"path": relative(p, output), "sha256": file_sha256(p)} for p in paths if os.path.isfile(p)]
        if entries:
            out[role] = entries[0] if isinstance(value, str) else entries
    return out


def _digest(*arrays: Any) -> str:
    h = hashlib.sha256()
    for a in arrays:
        arr = np.ascontiguousarray(np.asarray(a))
        h.update(str(arr.dtype).encode() + str(arr.shape).encode())
        h.update(arr.tobytes())
    return h.hexdigest()[:16]


def rig_record(scene: Scene) -> dict[str, dict[str, Any]]:
    """Per skinned mesh: its skinning method and digests of the rig the correctives depend on.

    ``points``: rest points; ``influences``: joint indices, weights and the mesh's joint order;
    ``geomBind``: geomBindTransform; ``skeleton``: joint paths, bind transforms and rest
    transforms. Digests of float32 data as authored, so a re-save that keeps the values keeps them.
    """
    out: dict[str, dict[str, Any]] = {}
    for info in scene.skinned_meshes():
        path = info.path
        query, skel_query = scene.query(path)
        prim = scene.prim(path)
        points = prim.GetAttribute("points").Get(Usd.TimeCode.Default())
        indices, weights = query.ComputeJointInfluences()
        skel = skel_query.GetSkeleton()
        binds = skel.GetBindTransformsAttr().Get() or []
        rests = skel.GetRestTransformsAttr().Get() or []
        out[path] = {
            "skinningMethod": str(query.GetSkinningMethod()),
            "skeleton": str(skel.GetPrim().GetPath()),
            "points": _digest(np.array(points if points is not None else [], dtype=np.float32)),
            "influences": _digest(np.array(indices or [], dtype=np.int32), np.array(weights or [], dtype=np.float32),
                                  np.array([query.GetNumInfluencesPerComponent()]),
                                  np.array([str(j) for j in (query.GetJointOrder() or [])], dtype=str)),
            "geomBind": _digest(np.array(query.GetGeomBindTransform(), dtype=np.float64)),
            "skeletonRig": _digest(np.array([str(j) for j in skel_query.GetJointOrder()], dtype=str),
                                   np.array(binds, dtype=np.float64), np.array(rests, dtype=np.float64)),
        }
    return out


def _vt(value: Any) -> Any:
    """Python data -> what ``customLayerData`` holds (lists become typed arrays)."""
    if isinstance(value, Mapping):
        return {str(k): _vt(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        items = list(value)
        if all(isinstance(v, str) for v in items):
            return Vt.StringArray(items)
        if all(isinstance(v, bool) for v in items):
            return Vt.BoolArray(items)
        if all(isinstance(v, int) and not isinstance(v, bool) for v in items):
            return Vt.IntArray(items)
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            return Vt.DoubleArray([float(v) for v in items])
        if all(isinstance(v, Mapping) for v in items):  # no array of dictionaries in USD: keyed "000", "001", ...
            return {f"{i:03d}": _vt(v) for i, v in enumerate(items)}
        return Vt.StringArray([str(v) for v in items])
    if isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    return str(value)


def stamp(layer: Sdf.Layer, kind: str, record: Mapping[str, Any] | None = None) -> Sdf.Layer:
    """Stamp layer with its kind, psdbake's version and ``record`` (inputs, rig, settings, ...)."""
    data = {"kind": kind, "version": __version__, **(record or {})}
    custom = dict(layer.customLayerData)
    custom[KEY] = _vt(data)
    layer.customLayerData = custom
    return layer


def add_to_stamp(layer: Sdf.Layer, record: Mapping[str, Any]) -> Sdf.Layer:
    """Add ``record``'s entries to the provenance layer already carries (``stamp``)."""
    custom = dict(layer.customLayerData)
    custom[KEY] = {**dict(custom.get(KEY, {})), **_vt(dict(record))}
    layer.customLayerData = custom
    return layer


def plain(value: Any) -> Any:
    """customLayerData values -> plain Python (typed arrays become lists), for comparisons and JSON."""
    if isinstance(value, Mapping):
        keys = sorted(str(k) for k in value)
        if keys and keys == [f"{i:03d}" for i in range(len(keys))]:  # a list of dictionaries, as ``_vt`` keys it
            return [plain(value[k]) for k in keys]
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, str):
        return value
    if hasattr(value, "__len__") and not isinstance(value, (bytes, bytearray)):
        return [plain(v) for v in value]
    return value


# --- checking ------------------------------------------------------------------------------

def rig_differences(recorded: Mapping[str, Any], current: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """What differs between the rig correctives were fitted on (``recorded``, their stamp's
    ``rig``) and the asset now given (``current``, ``rig_record``), mesh by mesh, in words."""
    out = []
    names = {
        "points": "its rest points", "influences": "its skinning influences (joint indices and weights)",
        "geomBind": "its geomBindTransform", "skeletonRig": "its skeleton's joints or bind/rest transforms",
    }
    for mesh in sorted(recorded):
        then, now = plain(recorded[mesh]), current.get(mesh)
        if now is None:
            continue  # a mesh the asset no longer skins is refused by the checks that read it
        if then.get("skinningMethod") != now.get("skinningMethod"):
            out.append(f"<{mesh}> was fitted with {then.get('skinningMethod')} skinning, and is now skinned with "
                       f"{now.get('skinningMethod')}")
            continue
        changed = [names[k] for k in names if then.get(k) is not None and then.get(k) != now.get(k)]
        if changed:
            out.append(f"<{mesh}>: {', '.join(changed)} differ from the rig the correctives were fitted on")
    return out


# --- stack roles -----------------------------------------------------------------------------

#: The roles of a viewable stack's layers, weakest first: the order ``stack`` composes them in.
STACK_ROLES = ("asset", "correctives", "anim", "weights", "points_cache")

_NOT_STACKED = {
    "examples": "an EXAMPLES layer (it authors posed points for sculpting: over the asset they would be skinned "
                "twice)",
    "sculpted_examples": "a sculpted EXAMPLES layer (for fit: over the asset its points would be skinned twice)",
    "stack": "a stack itself (give its layers instead)",
    "clip_manifest": "a value-clip manifest (give the manifest layer eval wrote at -o)",
}


def authors_point_samples(path: str) -> bool:
    """The layer itself authors time-sampled ``points``: sculpted or posed examples (or another
    tool's points cache), whose points UsdSkel would skin again over the asset."""
    layer = Sdf.Layer.FindOrOpen(path)
    found: list[bool] = []

    def visit(spec_path: Sdf.Path) -> None:
        if not found and spec_path.IsPropertyPath() and spec_path.name == "points" and \
                layer.GetNumTimeSamplesForPath(spec_path):
            found.append(True)

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return bool(found)


def layer_role(path: str) -> str:
    """A layer's role in a stack: its psdbake kind, else ``asset`` when it defines a SkelRoot,
    else ``anim`` (an animation or any other layer of the user's). Refuses layers that do not
    belong in a view (EXAMPLES, a stack, a clip manifest)."""
    from ..errors import InputError
    from .compose import compose

    kind = existing_kind(path)
    if kind is None and authors_point_samples(path):
        kind = "examples"
    if kind in _NOT_STACKED:
        raise InputError(f"{path}: is {_NOT_STACKED[kind]}; stack ASSET CORRECTIVES ANIM WEIGHTS")
    if kind in STACK_ROLES:
        return kind
    stage = compose([path])
    defines_root = any(p.IsA(UsdSkel.Root) and p.IsDefined() for p in stage.Traverse())
    return "asset" if defines_root else "anim"
