"""Chunked ``psdbake eval``: evaluate the chunks of a plan, write them and their manifests.

Each chunk is an ordinary WEIGHTS layer (and points cache) holding only its frames, so chunks
can be computed by different processes or machines; the layer at the ``-o`` path is a
*manifest* that stitches the chunks with USD value clips (``usd/clips.py``), so ASSET +
CORRECTIVES + ANIM + manifest opens as one animation.

Exactness: a frame's weights are computed from that frame alone (``rbf.row_independent_product``),
so chunked and single evaluations give the same bits. The manifest is any chunk without its
time samples plus clips over the chunks written so far: it never depends on sample values.

Concurrency: every chunk task adds its chunk to the manifest in a read-modify-write under the
output folders' lock (``api.updating``). The manifest records its *shot* (``shot_id``: the
inputs' bytes, the plan, the points cache, the deformers) and the chunks of that shot written
so far, and stitches only those, so it never stitches chunks of two shots: a task of another
shot is refused (exit 6) while the recorded shot is incomplete, and starts the manifest over
once it is complete (or with ``--force``). Once every task of a shot has run, the manifest is
the same bytes whatever order they ran in, and the same as one run of all the chunks.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import __version__, api, atomic
from ..arrays import Progress
from ..errors import InputError, OutputError, where
from ..outputs import CLIP_MANIFEST, POINTS_CACHE, WEIGHTS
from ..results import WeightsResult
from ..usd import clips, provenance
from ..usd import write as usdwrite
from .plan import Chunk, ChunkPlan, chunk_path, clip_manifest_path, plan_chunks, plan_frames

FORMATS = tuple(usdwrite.FORMATS)


@dataclass(frozen=True)
class ChunkedWeights:
    """The plan and the weights of the chunks this process computes."""

    asset: str
    correctives: str
    anim: str
    plan: ChunkPlan
    results: tuple[tuple[Chunk, WeightsResult], ...]
    animations: tuple[tuple[str, tuple[str, ...]], ...]  # (SkelAnimation, channels), for summaries
    fps: float | None


def _slice(result: WeightsResult, chunk: Chunk) -> WeightsResult:
    """The frames of one chunk out of a whole-shot evaluation."""
    animations = []
    for a in result.animations:
        keep = (a.times >= chunk.first) & (a.times <= chunk.last)
        animations.append(dataclasses.replace(a, times=a.times[keep], weights=a.weights[keep]))
    return dataclasses.replace(result, animations=tuple(animations))


def _shared_times(result: WeightsResult, anim: str) -> NDArray[np.float64]:
    """The authored time codes, which must be the same for every animation: a chunk's points
    cache is computed from that chunk's weights only."""
    first = result.animations[0]
    for other in result.animations[1:]:
        if not np.array_equal(other.times, first.times):
            raise InputError(
                f"{where(anim, other.animation)}: its time samples differ from <{first.animation}>'s: "
                "give --frames to cut the shot into chunks"
            )
    return first.times


def evaluate_chunks(
    asset: str,
    correctives: str,
    anim: str,
    size: int,
    *,
    frames: tuple[float, float] | None = None,
    chunk: int | None = None,
    progress: Progress | None = None,
    strict: bool = False,
    hold: bool = False,
    meshes: Sequence[str] = (),
) -> ChunkedWeights:
    """Weights of every chunk, or of chunk number ``chunk`` (1-based) only.

    With ``frames`` each chunk is evaluated on its own (``api.evaluate`` over its frames), so
    a farm task computes only its chunk. Without, the authored samples are only known after
    reading the animation: the shot is evaluated (cheap: tens of microseconds a frame) and
    cut; the expensive points cache is still per chunk.
    """
    if frames is not None:
        plan = plan_frames(frames, size)
        wanted = [plan.chunk(chunk)] if chunk is not None else list(plan.chunks)
        results = []
        for c in wanted:
            r = api.evaluate(asset, correctives, anim, frames=(c.first, c.last), progress=progress, strict=strict,
                             hold=hold, shot=(plan.first, plan.last), meshes=meshes)
            for a in r.animations:
                if not np.array_equal(a.times, c.times):
                    raise RuntimeError(f"chunk {c.index}: api.evaluate's frames differ from the plan's")
            results.append((c, r))
    else:
        full = api.evaluate(asset, correctives, anim, progress=progress, strict=strict, meshes=meshes)
        plan = plan_chunks(_shared_times(full, anim), size)
        wanted = [plan.chunk(chunk)] if chunk is not None else list(plan.chunks)
        results = [(c, _slice(full, c)) for c in wanted]
    some = results[0][1]
    animations = tuple((a.animation, tuple(a.channels)) for a in some.animations)
    return ChunkedWeights(asset, correctives, anim, plan, tuple(results), animations, some.fps)


def _relative(path: str, anchor: str) -> str:
    """An asset path relative to the layer at anchor (``./name``), so the folder can move."""
    rel = os.path.relpath(os.path.abspath(path), os.path.dirname(os.path.abspath(anchor)))
    rel = rel.replace(os.sep, "/")
    return rel if rel.startswith("../") else "./" + rel


def manifest_layers(template: Any, plan: ChunkPlan, output: str, what: str,
                    stitched: Sequence[int] | None = None) -> tuple[Any, Any]:
    """(manifest layer for ``output``, its clip manifest), from one chunk layer written for ``output``:
    that chunk without its time samples, plus clips over the chunks numbered ``stitched`` (1-based;
    None: every chunk of the plan)."""
    chosen = list(plan.chunks) if stitched is None else [plan.chunks[k - 1] for k in sorted(stitched)]
    assets = [_relative(chunk_path(output, plan, c), output) for c in chosen]
    return clips.stitching_layers(
        template, assets, [c.first for c in chosen], (plan.first, plan.last),
        _relative(clip_manifest_path(output), output),
        f"psdbake {__version__} eval: {what}, stitched from farm chunks with value clips",
    )


def shot_id(ev: ChunkedWeights, points_cache: str | None, output: str, deformers: Sequence[str]) -> str:
    """What makes two chunk tasks parts of one shot: the bytes of the asset, CORRECTIVES and ANIM,
    the plan (chunk size, frames), the animations and channels evaluated (``--mesh`` changes
    them), the points cache beside the manifest and the deformer chain. Every task of one farm job
    gives the same id; another shot, the same files edited, or another choice of meshes, another."""
    plan = ev.plan
    samples = hashlib.sha256(np.ascontiguousarray(plan.samples).tobytes()).hexdigest() if plan.samples is not None \
        else None
    record = {
        "inputs": [provenance.file_sha256(p) for p in (ev.asset, ev.correctives, ev.anim)],
        "plan": [plan.size, plan.count, plan.first, plan.last, samples],
        "animations": [[path, list(channels)] for path, channels in ev.animations],
        "points_cache": provenance.relative(points_cache, output) if points_cache else None,
        "deformers": list(deformers), "version": __version__,
    }
    return hashlib.sha256(json.dumps(record, sort_keys=True).encode()).hexdigest()[:16]


def _stitched(manifest: str, shot: str, count: int, mine: Sequence[int]) -> list[int]:
    """The chunks the manifest at ``manifest`` is to stitch once this task's chunks ``mine`` are
    written: those already recorded for this shot, and mine. Read under the update lock. A
    manifest of another shot that is still incomplete is refused (OutputError, exit 6): adding a
    chunk would stitch two shots; a complete one, or with ``--force``, is started over."""
    record = provenance.plain(provenance.read_stamp(manifest).get("shot", {})) if os.path.isfile(manifest) else {}
    if not record or record.get("id") == shot:
        done = [int(k) for k in record.get("chunks", [])] if record else []
        return sorted(set(done) | set(mine))
    written, total = len(record.get("chunks", [])), int(record.get("count", 0))
    if written < total and not atomic.forced():
        raise OutputError(
            f"{manifest}: the manifest of another shot, {written} of its {total} chunk(s) written so far: this chunk "
            "would stitch two shots into one output; let that eval finish, write elsewhere, or give --force to "
            "start this shot over")
    return sorted(mine)


@dataclass(frozen=True)
class ChunkFiles:
    """The files of one chunk this run wrote."""

    chunk: int
    first: float
    last: float
    frames: int
    weights: str
    points_cache: str | None


@dataclass(frozen=True)
class WrittenChunks:
    """Every file one run wrote (the manifests are written by every run)."""

    manifest: str
    clip_manifest: str
    points_cache: str | None
    points_clip_manifest: str | None
    chunks: tuple[ChunkFiles, ...]
    chunk_count: int
    stitched: tuple[int, ...] = ()  # the chunks the manifest stitches now (this shot's, written so far)


def _targets(ev: ChunkedWeights, output: str, points_cache: str | None) -> tuple[list[ChunkFiles], list[str]]:
    """(the chunks' files, every path this run writes), for checking before anything is computed."""
    files = []
    for c, _ in ev.results:
        cache = chunk_path(points_cache, ev.plan, c) if points_cache else None
        files.append(ChunkFiles(c.index, c.first, c.last, len(c.times), chunk_path(output, ev.plan, c), cache))
    targets = [output, clip_manifest_path(output), *(f.weights for f in files)]
    if points_cache:
        targets += [points_cache, clip_manifest_path(points_cache), *(f.points_cache for f in files if f.points_cache)]
    return files, targets


def write_chunks(
    ev: ChunkedWeights,
    output: str,
    *,
    points_cache: str | None = None,
    deformers: Sequence[str] = (),
    progress: Progress | None = None,
) -> WrittenChunks:
    """Write the computed chunks and the manifests in one commit (``usdwrite.export_all``):
    all checks and all computing (points caches included) happen before the first file is
    written, and a failure leaves every old file in place. The manifests are read, extended
    with this run's chunks and written under the update lock (``_stitched``: exit 6 while
    another shot's chunks are being written there)."""
    inputs = api.files_read([ev.asset, ev.correctives, ev.anim], deformers)
    files, targets = _targets(ev, output, points_cache)
    kinds = {output: WEIGHTS, clip_manifest_path(output): CLIP_MANIFEST, **{f.weights: WEIGHTS for f in files}}
    if points_cache:
        kinds |= {points_cache: POINTS_CACHE, clip_manifest_path(points_cache): CLIP_MANIFEST,
                  **{f.points_cache: POINTS_CACHE for f in files if f.points_cache}}
    atomic.check_outputs([(t, kinds[t]) for t in targets], inputs)
    chunks = []
    for (_, result), f in zip(ev.results, files, strict=True):
        chunks.append((f.weights, api.stamp_weights(api.weights_layer(result), "weights", result, f.weights)))
        if f.points_cache:
            cache = api.points_cache_layer(result, deformers, progress=progress)
            chunks.append((f.points_cache, api.stamp_weights(cache, "points_cache", result, f.points_cache, deformers)))
    shot, count, mine = shot_id(ev, points_cache, output, deformers), len(ev.plan.chunks), [f.chunk for f in files]
    manifests = [output, *([points_cache] if points_cache else [])]
    with api.updating(*manifests):  # read the manifests, add this task's chunks, commit: one step
        earlier = [f for m in manifests for f in clips.stitched_files(m)]
        stitched = _stitched(output, shot, count, mine)
        if points_cache:
            stitched = sorted((set(stitched) & set(_stitched(points_cache, shot, count, mine))) | set(mine))
        record = {"id": shot, "count": count, "chunks": stitched}
        # The manifests from the first chunk computed here, stamped without the command line (which
        # names the chunk): any chunk of the shot gives the same bytes.
        first = ev.results[0][1]
        manifest, clip_manifest = manifest_layers(chunks[0][1], ev.plan, output, "corrective blend-shape weights",
                                                  stitched)
        api.stamp_weights(manifest, "weights", first, output, command=False)
        provenance.add_to_stamp(manifest, {"shot": record})
        layers = [*chunks, (clip_manifest_path(output), provenance.stamp(clip_manifest, "clip_manifest")),
                  (output, manifest)]
        if points_cache:
            cache_manifest, cache_clip_manifest = manifest_layers(chunks[1][1], ev.plan, points_cache,
                                                                  "points cache (no UsdSkel needed)", stitched)
            api.stamp_weights(cache_manifest, "points_cache", first, points_cache, deformers, command=False)
            provenance.add_to_stamp(cache_manifest, {"shot": record})
            layers += [(clip_manifest_path(points_cache), provenance.stamp(cache_clip_manifest, "clip_manifest")),
                       (points_cache, cache_manifest)]
        usdwrite.export_all(layers, inputs)
        every = [chunk_path(m, ev.plan, c) for m in manifests for c in ev.plan.chunks]  # other tasks' chunks too
        clips.remove_unstitched(earlier, [*every, *(path for path, _ in layers), *inputs])
    return WrittenChunks(
        manifest=output, clip_manifest=clip_manifest_path(output), points_cache=points_cache,
        points_clip_manifest=clip_manifest_path(points_cache) if points_cache else None,
        chunks=tuple(files), chunk_count=len(ev.plan.chunks), stitched=tuple(stitched),
    )
