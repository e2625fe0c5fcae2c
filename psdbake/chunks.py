"""Farm chunks for ``psdbake eval``: one layer per chunk of frames, stitched by value clips.

A shot's frames (whole frames of ``--frames A:B``, else the animation's authored time
samples) are cut into consecutive chunks of N. Each chunk is an ordinary WEIGHTS layer
(and points cache) holding only its frames, so chunks can be computed by different
processes or machines; the layer at the ``-o`` path is a *manifest* that stitches the
chunks with USD value clips (``usd/clips.py``), so ASSET + CORRECTIVES + ANIM + manifest
opens as one animation.

Exactness: a frame's weights are computed from that frame alone (``rbf.row_independent_product``),
so chunked and single evaluations give the same bits. The manifest is any chunk without its
time samples plus clips over the plan's chunks: it never depends on sample values, so every
farm task writes the identical manifest atomically and racing writers are harmless.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf

from . import api, atomic
from .errors import InputError, PsdError, where
from .usd import clips
from .usd import write as usdwrite

FORMATS = (".usda", ".usdc", ".usd")


class ChunkUsageError(PsdError):
    """A chunk option that makes no sense (size below 1, chunk number out of range)."""

    exit_code = 2


#: Most chunks one plan may cut: each chunk is a file and a farm task, and the manifest lists
#: every chunk in its value clips, so 10,000 (a 1,000,000-frame range in chunks of 100) is
#: already more than any farm queue or manifest should hold; a larger plan is a typo.
MAX_CHUNKS = 10_000


@dataclass(frozen=True)
class Chunk:
    """One chunk of the shot: consecutive frames (or authored time codes)."""

    index: int  # 1-based, as --chunk
    first: float
    last: float
    count: int  # time codes in the chunk
    samples: NDArray[np.float64] | None = None  # the authored time codes; None: the whole frames first..last

    @property
    def times(self) -> NDArray[np.float64]:
        if self.samples is not None:
            return self.samples
        return self.first + np.arange(self.count, dtype=np.float64)


class _Chunks(Sequence):
    """A plan's chunks, each made when asked for (a chunk's frames follow from its index)."""

    def __init__(self, plan: ChunkPlan) -> None:
        self._plan = plan

    def __len__(self) -> int:
        return self._plan.chunk_count

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(i)
        return self._plan._make(i)


@dataclass(frozen=True)
class ChunkPlan:
    """How a shot is cut: the same in every farm task, whatever chunk it computes.

    Lazy: a plan over whole frames holds the first frame and the count only, and makes each
    chunk's frames from its index, so chunk K of a long range allocates chunk K alone."""

    size: int
    count: int  # time codes in the shot
    frames: tuple[float, float] | None  # --frames, or None for the authored samples
    start: float = 0.0  # the first whole frame (with frames)
    samples: NDArray[np.float64] | None = None  # the authored time codes (without frames)

    @property
    def chunk_count(self) -> int:
        return -(-self.count // self.size)

    @property
    def chunks(self) -> Sequence[Chunk]:
        return _Chunks(self)

    def _time(self, i: int) -> float:
        return float(self.samples[i]) if self.samples is not None else self.start + i

    def _make(self, i: int) -> Chunk:
        lo, hi = i * self.size, min(self.count, (i + 1) * self.size)
        samples = self.samples[lo:hi] if self.samples is not None else None
        return Chunk(i + 1, self._time(lo), self._time(hi - 1), hi - lo, samples)

    @property
    def first(self) -> float:
        return self._time(0)

    @property
    def last(self) -> float:
        return self._time(self.count - 1)

    @property
    def width(self) -> int:
        """Digits of the frame numbers in chunk file names (at least 4), so they sort."""
        if self.samples is not None:
            biggest = float(np.max(np.abs(self.samples)))
        else:
            biggest = max(abs(self.first), abs(self.last))
        return max(4, len(str(int(biggest))))

    def chunk(self, index: int) -> Chunk:
        if not 1 <= index <= self.chunk_count:
            raise ChunkUsageError(
                f"--chunk {index}: out of range: {self.count} frame(s) in chunks of "
                f"{self.size} make {self.chunk_count} chunk(s), numbered 1..{self.chunk_count}"
            )
        return self._make(index - 1)


def whole_frames(frames: tuple[float, float]) -> NDArray[np.float64]:
    """Whole frames A..B inclusive: the rule of ``api.frames_of`` for ``--frames`` (at most
    ``tolerances.MAX_FRAMES``, refused before anything is allocated)."""
    count = api.frame_count(frames)
    return np.ceil(float(frames[0])) + np.arange(count, dtype=np.float64)


def _check_size(size: int, count: int) -> int:
    if int(size) < 1:
        raise ChunkUsageError(f"--chunk-size {size}: must be at least 1 frame")
    size = int(size)
    chunks = -(-count // size)
    if chunks > MAX_CHUNKS:
        raise ChunkUsageError(f"--chunk-size {size}: {count} frame(s) would make {chunks} chunks, more than the "
                              f"limit of {MAX_CHUNKS} (files and farm tasks): give a larger --chunk-size")
    return size


def plan_frames(frames: tuple[float, float], size: int) -> ChunkPlan:
    """The plan of ``--frames A:B --chunk-size N``, by arithmetic: no frame list is made."""
    count = api.frame_count(frames)
    return ChunkPlan(_check_size(size, count), count, frames, start=float(np.ceil(float(frames[0]))))


def plan_chunks(times: Sequence[float] | NDArray[np.float64], size: int,
                frames: tuple[float, float] | None = None) -> ChunkPlan:
    """Consecutive chunks of ``size`` time codes (the last one may be shorter)."""
    if int(size) < 1:
        raise ChunkUsageError(f"--chunk-size {size}: must be at least 1 frame")
    times = np.asarray(times, dtype=np.float64)
    if not len(times):
        raise InputError("no frames to cut into chunks")
    if not np.all(np.isfinite(times)):
        raise InputError(f"time code {times[~np.isfinite(times)][0]!r} is not a finite number: cannot cut it into chunks")
    return ChunkPlan(_check_size(size, len(times)), len(times), frames, samples=times)


def frame_label(t: float, width: int) -> str:
    """A time code in a file name: zero-padded, ``m`` for minus, ``p`` for the decimal point
    (-12.5 -> m0012p5): no characters that shells or USD asset paths treat specially."""
    text = np.format_float_positional(abs(float(t)), trim="-")  # shortest text that reads back exactly
    whole, _, frac = text.partition(".")
    return ("m" if t < 0 else "") + whole.zfill(width) + (f"p{frac}" if frac else "")


def chunk_path(output: str, plan: ChunkPlan, chunk: Chunk) -> str:
    """``weights.usda`` -> ``weights.f0001-0100.usda``, beside the manifest."""
    stem, ext = os.path.splitext(output)
    w = plan.width
    return f"{stem}.f{frame_label(chunk.first, w)}-{frame_label(chunk.last, w)}{ext}"


def clip_manifest_path(output: str) -> str:
    """``weights.usda`` -> ``weights.clipmanifest.usda``: USD's clip manifest, beside the manifest."""
    stem, ext = os.path.splitext(output)
    return f"{stem}.clipmanifest{ext}"


def _relative(path: str, anchor: str) -> str:
    """An asset path relative to the layer at anchor (``./name``), so the folder can move."""
    rel = os.path.relpath(os.path.abspath(path), os.path.dirname(os.path.abspath(anchor)))
    rel = rel.replace(os.sep, "/")
    return rel if rel.startswith("../") else "./" + rel


@dataclass(frozen=True)
class ChunkedWeights:
    """The plan and the weights of the chunks this process computes."""

    asset: str
    correctives: str
    anim: str
    plan: ChunkPlan
    results: tuple[tuple[Chunk, api.WeightsResult], ...]
    animations: tuple[tuple[str, tuple[str, ...]], ...]  # (SkelAnimation, channels), for summaries
    fps: float | None


def _slice(result: api.WeightsResult, chunk: Chunk) -> api.WeightsResult:
    """The frames of one chunk out of a whole-shot evaluation."""
    animations = []
    for a in result.animations:
        keep = (a.times >= chunk.first) & (a.times <= chunk.last)
        animations.append(dataclasses.replace(a, times=a.times[keep], weights=a.weights[keep]))
    return dataclasses.replace(result, animations=tuple(animations))


def _shared_times(result: api.WeightsResult, anim: str) -> NDArray[np.float64]:
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
    progress: api.Progress | None = None,
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
            r = api.evaluate(asset, correctives, anim, frames=(c.first, c.last), progress=progress)
            for a in r.animations:
                if not np.array_equal(a.times, c.times):
                    raise RuntimeError(f"chunk {c.index}: api.evaluate's frames differ from the plan's")
            results.append((c, r))
    else:
        full = api.evaluate(asset, correctives, anim, progress=progress)
        plan = plan_chunks(_shared_times(full, anim), size)
        wanted = [plan.chunk(chunk)] if chunk is not None else list(plan.chunks)
        results = [(c, _slice(full, c)) for c in wanted]
    some = results[0][1]
    animations = tuple((a.animation, tuple(a.channels)) for a in some.animations)
    return ChunkedWeights(asset, correctives, anim, plan, tuple(results), animations, some.fps)


def _doc(what: str) -> str:
    from . import __version__

    return f"psdbake {__version__} eval: {what}, stitched from farm chunks with value clips"


def manifest_layers(template: Sdf.Layer, plan: ChunkPlan, output: str, what: str) -> tuple[Sdf.Layer, Sdf.Layer]:
    """(manifest layer for ``output``, its clip manifest), from one chunk layer written for ``output``:
    that chunk without its time samples, plus clips over every chunk of the plan."""
    assets = [_relative(chunk_path(output, plan, c), output) for c in plan.chunks]
    return clips.stitching_layers(
        template, assets, [c.first for c in plan.chunks], (plan.first, plan.last),
        _relative(clip_manifest_path(output), output), _doc(what),
    )


@dataclass(frozen=True)
class ChunkFiles:
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


def write_chunks(
    ev: ChunkedWeights,
    output: str,
    *,
    points_cache: str | None = None,
    deformers: Sequence[str] = (),
    progress: api.Progress | None = None,
) -> WrittenChunks:
    """Write the computed chunks and the manifests in one commit (``usdwrite.export_all``):
    all checks and all computing (points caches included) happen before the first file is
    written, and a failure leaves every old file in place."""
    inputs = api.files_read([ev.asset, ev.correctives, ev.anim], deformers)
    files = []
    for c, _ in ev.results:
        cache = chunk_path(points_cache, ev.plan, c) if points_cache else None
        files.append(ChunkFiles(c.index, c.first, c.last, len(c.times), chunk_path(output, ev.plan, c), cache))
    targets = [output, clip_manifest_path(output), *(f.weights for f in files)]
    if points_cache:
        targets += [points_cache, clip_manifest_path(points_cache), *(f.points_cache for f in files if f.points_cache)]
    atomic.check_outputs([(t, FORMATS) for t in targets], inputs)
    layers = []
    for (_, result), f in zip(ev.results, files, strict=True):
        layers.append((f.weights, api.weights_layer(result)))
        if f.points_cache:
            layers.append((f.points_cache, api.points_cache_layer(result, deformers, progress=progress)))
    # The manifests from the first chunk computed here: any chunk gives the same bytes.
    manifest, clip_manifest = manifest_layers(layers[0][1], ev.plan, output, "corrective blend-shape weights")
    layers += [(clip_manifest_path(output), clip_manifest), (output, manifest)]
    if points_cache:
        cache_manifest, cache_clip_manifest = manifest_layers(layers[1][1], ev.plan, points_cache,
                                                              "points cache (no UsdSkel needed)")
        layers += [(clip_manifest_path(points_cache), cache_clip_manifest), (points_cache, cache_manifest)]
    usdwrite.export_all(layers, inputs)
    return WrittenChunks(
        manifest=output, clip_manifest=clip_manifest_path(output), points_cache=points_cache,
        points_clip_manifest=clip_manifest_path(points_cache) if points_cache else None,
        chunks=tuple(files), chunk_count=len(ev.plan.chunks),
    )
