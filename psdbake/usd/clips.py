"""USD value clips: stitch layers written separately (farm chunks) into one animation.

A value clip supplies **time samples only**: uniform and default values (a SkelAnimation's
``blendShapes`` order, a points cache's SkelRoot->Xform retyping) must be authored in the
layer that holds the clips metadata itself. Everything here is authored at the Sdf level
on in-memory layers, so nothing is opened or resolved while writing and the bytes depend
only on the arguments.

Choices:

- The stitching layer is one chunk with its time samples removed (``stitching_layers``), so
  it carries exactly what the chunk writer authors besides samples, and nothing depends on
  sample values: every farm task writes the same manifest bytes (tested).
- The clip set is named ``psdbake``, not ``default``: clip metadata is a dictionary that
  composes key by key, so a ``default`` set the animation already has (an ANIM stitched from
  its own clips) would mix its keys into ours. Clips anchored in the strongest layer win over
  an ANIM's own ``blendShapeWeights`` samples or clips (checked by hand with both).
- ``times`` is the identity (stage time = the chunk's own time): each chunk keeps the
  frame numbers of the shot, so it is also a valid layer on its own. USD interpolates
  across clip boundaries exactly as within one layer (tested at subframes).
- The clip manifest (``manifestAssetPath``) is a separate small layer declaring the
  time-sampled attributes and nothing else, derived from one chunk because a farm task has
  only its own; it equals ``Usd.ClipsAPI.GenerateClipManifestFromLayers`` over all chunks
  (tested). Without it USD would open every chunk to build one when the stage opens. It is
  not the stitching layer itself so that USD never looks in the clips for the uniform
  ``blendShapes``.
- ``interpolateMissingClipValues``: a clip without samples for an attribute interpolates
  between the neighbouring clips, as one layer with those samples missing would (checked
  by hand: without it USD returns no value there).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Sequence

from pxr import Gf, Sdf, Vt

from .provenance import existing_kind

CLIP_SET = "psdbake"


def stitching_layers(
    template: Sdf.Layer,
    assets: Sequence[str],
    starts: Sequence[float],
    span: tuple[float, float],
    manifest: str,
    doc: str,
) -> tuple[Sdf.Layer, Sdf.Layer]:
    """(stitching layer, clip manifest) for clips shaped like ``template``, one of the chunks.

    The stitching layer is the template without its time samples: everything clips cannot
    carry (uniform and default values, prim types, attribute declarations, layer metadata)
    stays, so it follows whatever the chunk writer authors; each prim that had time samples
    gets the clips metadata. The clip manifest declares each time-sampled attribute. Neither
    depends on the sample values, so every chunk gives the same bytes.
    """
    layer = Sdf.Layer.CreateAnonymous("stitch.usda")
    layer.TransferContent(template)
    layer.documentation = doc
    layer.startTimeCode, layer.endTimeCode = float(span[0]), float(span[1])
    sampled: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: sampled.append(p) if p.IsPropertyPath() and layer.GetNumTimeSamplesForPath(p) else None)
    sampled.sort()
    clip_manifest = Sdf.Layer.CreateAnonymous("clipmanifest.usda")
    clip_manifest.documentation = "psdbake clip manifest: the attributes whose time samples come from value clips"
    for key in ("upAxis", "metersPerUnit"):
        if template.pseudoRoot.HasInfo(key):
            clip_manifest.pseudoRoot.SetInfo(key, template.pseudoRoot.GetInfo(key))
    if template.defaultPrim:
        clip_manifest.defaultPrim = template.defaultPrim
    for path in sampled:
        for t in layer.ListTimeSamplesForPath(path):
            layer.EraseTimeSample(path, t)
        spec = Sdf.CreatePrimInLayer(clip_manifest, path.GetPrimPath())
        Sdf.AttributeSpec(spec, path.name, layer.GetAttributeAtPath(path).typeName, Sdf.VariabilityVarying)
    for prim in sorted({p.GetPrimPath() for p in sampled}):
        author_clips(layer.GetPrimAtPath(prim), assets, starts, span, manifest)
    return layer, clip_manifest


def author_clips(
    spec: Sdf.PrimSpec,
    assets: Sequence[str],
    starts: Sequence[float],
    span: tuple[float, float],
    manifest: str,
    prim_path: str | None = None,
) -> None:
    """Clips metadata on spec: clip i (``assets[i]``, relative to the layer) is active from
    ``starts[i]``; stage time maps to the same clip time over ``span``."""
    if len(assets) != len(starts) or not assets:
        raise ValueError("one start time per clip asset, at least one clip")
    first, last = float(span[0]), float(span[1])
    times = [Gf.Vec2d(first, first)] + ([Gf.Vec2d(last, last)] if last != first else [])
    spec.SetInfo("clips", {
        CLIP_SET: {
            "active": Vt.Vec2dArray([Gf.Vec2d(float(t), float(i)) for i, t in enumerate(starts)]),
            "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(a) for a in assets]),
            "interpolateMissingClipValues": True,
            "manifestAssetPath": Sdf.AssetPath(manifest),
            "primPath": prim_path or str(spec.path),
            "times": Vt.Vec2dArray(times),
        }
    })


def stitched_files(path: str) -> list[str]:
    """The clip layers and clip manifest the layer at ``path`` stitches as psdbake's clips
    (``CLIP_SET``), as paths from here, sorted; [] where it stitches none. An earlier chunked
    output's files, found by what its manifest names rather than by file names."""
    if not os.path.isfile(path):
        return []
    try:
        layer = Sdf.Layer.OpenAsAnonymous(path)
    except Exception:  # not a layer: it stitches nothing
        return []
    found: set[str] = set()

    def visit(spec_path: Sdf.Path) -> None:
        spec = layer.GetPrimAtPath(spec_path) if spec_path.IsPrimPath() else None
        clips = spec.GetInfo("clips").get(CLIP_SET) if spec is not None and spec.HasInfo("clips") else None
        if not clips:
            return
        named = [*clips.get("assetPaths", []), clips.get("manifestAssetPath")]
        found.update(os.path.normpath(os.path.join(os.path.dirname(path), a.path)) for a in named if a and a.path)

    if layer is not None:
        layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return sorted(found)


def remove_unstitched(earlier: Sequence[str], written: Sequence[str]) -> list[str]:
    """Remove the files of ``earlier`` (``stitched_files`` of an output before it was written
    again) that are not in ``written`` (what this run wrote, and every file it read: an old
    chunk given as ``--anim`` stays), where psdbake wrote them (a WEIGHTS layer, points cache or
    clip manifest; anything else is left alone): the chunks of an earlier cut of the shot,
    stitched by nothing now. Returns what was removed."""
    kept = {os.path.realpath(p) for p in written}
    removed = []
    for path in earlier:
        if os.path.realpath(path) in kept or existing_kind(path) not in ("weights", "points_cache", "clip_manifest"):
            continue
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)
            removed.append(path)
    return removed
