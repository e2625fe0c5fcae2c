"""Author psdbake's output layers in memory and export each one atomically.

Every writer builds an anonymous ``Sdf.Layer`` (prims and properties authored in
sorted, deterministic order; no time stamps, no absolute paths) and
``export_atomic`` writes it to a temporary file beside the destination, flushes it
to disk and renames it over the destination: a failed or interrupted run leaves
either the old file or the complete new one, never a partial one.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from .. import atomic
from ..errors import InputError, OutputError
from ..outputs import KINDS, OutputKind
from . import provenance
from .author import apply_binding_api, attribute, define, int_array, over, relationship, vec3f_array
from .dependencies import layer_files
from .diagnostics import first_line
from .integrity import verdict_of_written, vouch_written
from .schema import BlendShapeData

#: Output layer formats by extension (``names.LAYER_FORMATS``), with the arguments
#: USD's ``Export`` needs for each (``.usd`` is written as a binary crate).
FORMATS: dict[str, dict[str, str]] = {".usda": {}, ".usdc": {}, ".usd": {"format": "usdc"}}


def files_read(inputs: Iterable[str | Sdf.Layer]) -> list[str]:
    """Every file the given inputs read (themselves and every layer they reach through
    sublayers, references, payloads and clips): what no output may overwrite."""
    return layer_files([p for p in inputs if p])


def export_all(outputs: Sequence[tuple[str, Sdf.Layer | str]], inputs: Iterable[str] = (),
               other_inputs: Iterable[str] = ()) -> list[str]:
    """Write several outputs together: layers (and small text files such as a JSON report,
    given as ``str``), every one to a temporary file first, then all renamed
    (``atomic.Transaction``), so a failure leaves every old output in place. ``inputs``
    are expanded to every file they read; no output may be one of them, nor one of
    ``other_inputs`` (files read that are not layers: ``sculpts``' OBJ files). Each layer
    replaces only an earlier output of the kind it is stamped with (``provenance.stamp``),
    each text file only an earlier report, unless forced (``atomic.forcing``)."""
    written: list[str | None] = []
    with atomic.Transaction([*files_read(inputs), *other_inputs]) as tx:
        for path, layer in outputs:
            if isinstance(layer, str):
                tmp = tx.path(path, kind=report_kind(layer))
                try:
                    with open(tmp, "w", encoding="utf-8") as fh:
                        fh.write(layer)
                except OSError as exc:
                    raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
                continue
            kind = provenance.layer_kind(layer)
            if kind not in KINDS:
                raise RuntimeError(f"{path}: psdbake's layer carries no output kind (provenance.stamp)")
            tmp = tx.path(path, FORMATS, KINDS[kind])
            export_layer(layer, tmp, path)
            written.append(verdict_of_written(tmp))
    vouch_written(written)
    for path, layer in outputs:  # a pipeline reading an output again in this process reads what is there now
        if not isinstance(layer, str):
            _forget_loaded(path)
    return [path for path, _ in outputs]


def _forget_loaded(path: str) -> None:
    """USD keeps one copy of each layer per process: where this process had the file at path
    loaded before replacing it (``fit`` over its earlier output, then ``describe`` of it), bring
    that copy up to the new bytes, or the next open would see the old ones."""
    layer = Sdf.Layer.Find(path)
    if layer is not None:
        try:
            layer.Reload(force=True)
        except Tf.ErrorException:  # the next open reads the file and says what is wrong
            pass


def report_kind(text: str) -> OutputKind:
    """The kind of a JSON side file: the ``--report`` of the command named in it."""
    import json

    command = json.loads(text).get("command", "")
    kind = KINDS.get(f"{command}_report")
    if kind is None:
        raise RuntimeError(f"no output kind for a {command!r} report")
    return kind


def export_layer(layer: Sdf.Layer, tmp: str, path: str) -> None:
    """Write layer to tmp (a temporary path of an ``atomic.Transaction``, in path's format),
    or raise OutputError naming path."""
    args = FORMATS[os.path.splitext(path)[1].lower()]
    try:
        written, detail = layer.Export(tmp, args=args), ""
    except Tf.ErrorException as exc:
        written, detail = False, first_line(exc).replace(tmp, path)
    if not written:
        raise OutputError(f"{path}: cannot write: {_why_not_written(tmp, detail)}")


def _why_not_written(tmp: str, detail: str) -> str:
    """The likely cause when USD fails to write a layer (it reports no errno: "Could not
    close", or a crate-writer exception that speaks of a corrupt value)."""
    import resource

    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY:
        return f"the file-size limit (ulimit -f, RLIMIT_FSIZE) of {limit} bytes was reached"
    try:
        st = os.statvfs(os.path.dirname(tmp) or ".")
        if st.f_bavail * st.f_frsize < 1 << 20:
            return "no space left on the device"
    except OSError:
        pass
    return f"USD could not write the layer{f' ({detail})' if detail else ''}"


def export_atomic(layer: Sdf.Layer, path: str, inputs: Iterable[str] = ()) -> str:
    """Write layer to path via temp file + fsync + rename (``export_all`` of one layer)."""
    export_all([(path, layer)], inputs)
    return path


def asset_metadata(asset: str) -> dict:
    """upAxis, metersPerUnit and defaultPrim of the asset, so each output layer validates
    on its own (UsdGeom's fallbacks when the asset authors none).

    Stage metadata is the root layer's, so it is read there; the asset is composed only when
    its layer names no root prim it holds a spec for (the first defined root prim stands in),
    not for every output layer (0.3 ms of a 48-frame points cache at 13k points)."""
    layer = Sdf.Layer.FindOrOpen(asset)
    info = layer.pseudoRoot
    up = str(info.GetInfo("upAxis")) if info.HasInfo("upAxis") else str(UsdGeom.GetFallbackUpAxis())
    meters = float(info.GetInfo("metersPerUnit")) if info.HasInfo("metersPerUnit") else UsdGeom.LinearUnits.centimeters
    if not (np.isfinite(meters) and meters > 0):
        raise InputError(f"{asset}: metersPerUnit {meters!r} is not a positive number")
    name = layer.defaultPrim
    if not (name and Sdf.Path.IsValidIdentifier(name) and layer.GetPrimAtPath(Sdf.Path.absoluteRootPath.AppendChild(name))):
        stage = Usd.Stage.Open(layer, Usd.Stage.LoadNone)
        default = stage.GetDefaultPrim()
        if not default:
            default = next((p for p in stage.GetPseudoRoot().GetChildren() if p.IsDefined()), None)
        name = default.GetName() if default else None
    return {"upAxis": up, "metersPerUnit": meters, "defaultPrim": name}


def new_layer(doc: str, times: Sequence[float] | None = None, fps: float | None = None,
              metadata: dict | None = None) -> Sdf.Layer:
    layer = Sdf.Layer.CreateAnonymous("psdbake.usda")
    layer.documentation = doc
    if metadata:
        layer.pseudoRoot.SetInfo("upAxis", metadata["upAxis"])
        layer.pseudoRoot.SetInfo("metersPerUnit", metadata["metersPerUnit"])
        if metadata.get("defaultPrim"):
            layer.defaultPrim = metadata["defaultPrim"]
    if times:
        layer.startTimeCode, layer.endTimeCode = float(min(times)), float(max(times))
    if fps:
        layer.timeCodesPerSecond = float(fps)
        layer.framesPerSecond = float(fps)
    return layer


def author_blend_shapes(
    layer: Sdf.Layer,
    mesh: str,
    shapes: Sequence[BlendShapeData],
    existing_channels: Sequence[str],
    existing_targets: Sequence[str],
) -> None:
    """BlendShape prims under mesh plus the mesh's skel:blendShapes/targets (existing kept first)."""
    mesh_spec = over(layer, mesh)
    apply_binding_api(mesh_spec)
    ours = {s.channel for s in shapes}
    keep = [(c, t) for c, t in zip(existing_channels, existing_targets, strict=True) if c not in ours]
    channels = [c for c, _ in keep] + [s.channel for s in shapes]
    targets = [t for _, t in keep] + [f"{mesh}/{s.name}" for s in shapes]
    attribute(mesh_spec, "skel:blendShapes", Sdf.ValueTypeNames.TokenArray, Vt.TokenArray(channels), uniform=True)
    relationship(mesh_spec, "skel:blendShapeTargets", targets)
    for shape in shapes:
        spec = define(layer, f"{mesh}/{shape.name}", "BlendShape")
        attribute(spec, "offsets", Sdf.ValueTypeNames.Vector3fArray, vec3f_array(shape.offsets), uniform=True)
        attribute(spec, "pointIndices", Sdf.ValueTypeNames.IntArray, int_array(shape.indices), uniform=True)
        if shape.normal_offsets is not None:
            attribute(spec, "normalOffsets", Sdf.ValueTypeNames.Vector3fArray, vec3f_array(shape.normal_offsets),
                      uniform=True)


def flattened(layer: Sdf.Layer, asset: str) -> Sdf.Layer:
    """layer over the asset, flattened into one layer with the layer's metadata (a points cache
    that opens on its own: the asset's topology, transforms and materials, the cache's points)."""
    from .compose import compose

    stage = compose([layer, asset])
    flat = stage.Flatten(addSourceFileComment=False)
    out = Sdf.Layer.CreateAnonymous("psdbake.usda")
    out.TransferContent(flat)
    for key in ("documentation", "startTimeCode", "endTimeCode", "timeCodesPerSecond", "framesPerSecond", "defaultPrim"):
        if layer.pseudoRoot.HasInfo(key) or key == "documentation":
            setattr(out, key, getattr(layer, key))
    for key in ("upAxis", "metersPerUnit"):
        if layer.pseudoRoot.HasInfo(key):
            out.pseudoRoot.SetInfo(key, layer.pseudoRoot.GetInfo(key))
    return out


def weights_layer(doc: str, animations, fps: float | None, metadata: dict | None = None) -> Sdf.Layer:
    """WEIGHTS: blendShapes + blendShapeWeights samples on each SkelAnimation.

    animations: iterable of (anim path, channels, times (f,), weights (f, c)).
    """
    animations = list(animations)
    times = [float(t) for _, _, ts, _ in animations for t in ts]
    layer = new_layer(doc, times, fps, metadata)
    t_ = Sdf.ValueTypeNames
    for path, channels, ts, weights in animations:
        spec = over(layer, path)
        attribute(spec, "blendShapes", t_.TokenArray, Vt.TokenArray(list(channels)), uniform=True)
        attr = attribute(spec, "blendShapeWeights", t_.FloatArray)
        rows = np.ascontiguousarray(weights, dtype=np.float32)  # (f, c), to float32 once, not once per frame
        for t, w in zip(np.asarray(ts, dtype=np.float64).tolist(), rows, strict=True):
            layer.SetTimeSample(attr.path, t, Vt.FloatArray.FromNumpy(w))
    return layer


def points_layer(doc: str, skel_roots: Sequence[str], samples, times: Sequence[float], fps: float | None,
                 metadata: dict | None = None, blocked: Iterable[tuple[str, str]] = ()) -> Sdf.Layer:
    """A points cache: SkelRoots become Xforms (no UsdSkel needed), points + extent per time.

    samples: iterable of (mesh path, time, PosedPoints): points and extent as authored
        (``posedpoints``: made there without a per-point conversion, and shared, not copied, here).
    blocked: (mesh, attribute) shading normals of the asset to block: at rest they would
        shade the posed points wrongly; blocked, renderers derive normals from the points.
    """
    layer = new_layer(doc, times, fps, metadata)
    t_ = Sdf.ValueTypeNames
    for root in sorted(skel_roots):
        define(layer, root, "Xform")
    for mesh, name in sorted(blocked):
        attribute(over(layer, mesh), name, t_.Normal3fArray).default = Sdf.ValueBlock()
    paths: dict[str, tuple[Sdf.Path, Sdf.Path]] = {}
    for mesh, t, posed in samples:
        if mesh not in paths:
            spec = over(layer, mesh)
            paths[mesh] = (attribute(spec, "points", t_.Point3fArray).path,
                           attribute(spec, "extent", t_.Float3Array).path)
        points, extent = paths[mesh]
        layer.SetTimeSample(points, float(t), posed.points)
        layer.SetTimeSample(extent, float(t), posed.extent)
    return layer


def examples_layer(doc: str, animations, samples, times: Sequence[float], fps: float | None,
                   metadata: dict | None = None) -> Sdf.Layer:
    """EXAMPLES to sculpt on: the bound animations' samples plus skinned points per time.

    animations: iterable of (skeleton path, anim path, joints, channels, samples) with
        samples [(t, translations, rotations, scales, weights)] (see read.animation_components).
    samples: iterable of (mesh path, time, PosedPoints) (``posedpoints``).
    """
    layer = new_layer(doc, times, fps, metadata)
    t_ = Sdf.ValueTypeNames
    for skeleton, anim, joints, channels, anim_samples in animations:
        skel_spec = over(layer, skeleton)
        apply_binding_api(skel_spec)
        relationship(skel_spec, "skel:animationSource", [anim])
        spec = define(layer, anim, "SkelAnimation")
        attribute(spec, "joints", t_.TokenArray, Vt.TokenArray(joints), uniform=True)
        tr = attribute(spec, "translations", t_.Float3Array)
        ro = attribute(spec, "rotations", t_.QuatfArray)
        sc = attribute(spec, "scales", t_.Half3Array)
        bw = None
        if channels:
            attribute(spec, "blendShapes", t_.TokenArray, Vt.TokenArray(channels), uniform=True)
            bw = attribute(spec, "blendShapeWeights", t_.FloatArray)
        for t, translations, rotations, scales, weights in anim_samples:
            layer.SetTimeSample(tr.path, t, translations)
            layer.SetTimeSample(ro.path, t, rotations)
            layer.SetTimeSample(sc.path, t, scales)
            if bw is not None:
                layer.SetTimeSample(bw.path, t, weights)
    for mesh, t, posed in samples:
        attr = attribute(over(layer, mesh), "points", t_.Point3fArray)
        layer.SetTimeSample(attr.path, float(t), posed.points)
    return layer


def stack_layer(out: str, layers: Sequence[str]) -> Sdf.Layer:
    """A layer that sublayers ``layers`` (given weakest first, stored strongest first),
    with paths relative to ``out`` and the frame range of the strongest timed layer."""
    folder = os.path.dirname(os.path.abspath(out))
    layer = new_layer("psdbake stack: ASSET + CORRECTIVES + ANIM + WEIGHTS", metadata=asset_metadata(layers[0]))
    ordered: list[str] = []
    for path in layers:  # weakest first; a layer listed twice keeps its weakest place
        rel = os.path.relpath(os.path.abspath(path), folder)
        if rel not in ordered:
            ordered.append(rel)
    for rel in reversed(ordered):
        layer.subLayerPaths.append(rel)
    for path in reversed(layers):
        src = Sdf.Layer.FindOrOpen(path)
        if src is not None and src.HasStartTimeCode() and src.HasEndTimeCode():
            layer.startTimeCode, layer.endTimeCode = src.startTimeCode, src.endTimeCode
            if src.HasTimeCodesPerSecond():
                layer.timeCodesPerSecond = src.timeCodesPerSecond
            break
    return layer
