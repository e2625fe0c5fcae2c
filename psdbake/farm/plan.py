"""How a shot is cut into farm chunks: ``eval --frames A:B --chunk-size N [--chunk K]``.

A shot's frames (whole frames of ``--frames A:B``, else the animation's authored time
samples) are cut into consecutive chunks of N. Each chunk becomes an ordinary WEIGHTS layer
(and points cache) holding only its frames, named after its frames so that every farm task,
whatever chunk it computes, agrees on every chunk's file name (``chunk_path``) and so on the
manifest that stitches them (``chunked``).

Plans are lazy and bounded: a plan over whole frames holds the first frame and the count
only and makes each chunk's frames from its index, and a plan of more than ``MAX_CHUNKS``
chunks is refused, so planning chunk K of a million frames allocates chunk K alone.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import overload

import numpy as np
from numpy.typing import NDArray

from ..errors import ChunkUsageError, InputError
from ..shot.frames import frame_count, frame_label, parse_frames

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


class _Chunks(Sequence[Chunk]):
    """A plan's chunks, each made when asked for (a chunk's frames follow from its index)."""

    def __init__(self, plan: ChunkPlan) -> None:
        self._plan = plan

    def __len__(self) -> int:
        return self._plan.chunk_count

    @overload
    def __getitem__(self, i: int) -> Chunk: ...

    @overload
    def __getitem__(self, i: slice) -> list[Chunk]: ...

    def __getitem__(self, i: int | slice) -> Chunk | list[Chunk]:
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
    count = frame_count(frames)
    return ChunkPlan(_check_size(size, count), count, frames, start=float(np.ceil(float(frames[0]))))


def plan_chunks(times: Sequence[float] | NDArray[np.float64], size: int,
                frames: tuple[float, float] | None = None) -> ChunkPlan:
    """Consecutive chunks of ``size`` time codes (the last one may be shorter)."""
    if int(size) < 1:
        raise ChunkUsageError(f"--chunk-size {size}: must be at least 1 frame")
    codes = np.asarray(times, dtype=np.float64)
    if not len(codes):
        raise InputError("no frames to cut into chunks")
    if not np.all(np.isfinite(codes)):
        raise InputError(f"time code {codes[~np.isfinite(codes)][0]!r} is not a finite number: cannot cut it into chunks")
    return ChunkPlan(_check_size(size, len(codes)), len(codes), frames, samples=codes)


def chunk_path(output: str, plan: ChunkPlan, chunk: Chunk) -> str:
    """``weights.usda`` -> ``weights.f0001-0100.usda``, beside the manifest."""
    stem, ext = os.path.splitext(output)
    w = plan.width
    return f"{stem}.f{frame_label(chunk.first, w)}-{frame_label(chunk.last, w)}{ext}"


def clip_manifest_path(output: str) -> str:
    """``weights.usda`` -> ``weights.clipmanifest.usda``: USD's clip manifest, beside the manifest."""
    stem, ext = os.path.splitext(output)
    return f"{stem}.clipmanifest{ext}"


def eval_chunks(output: str, points_cache: str | None, frames: str, chunk_size: int) -> list[tuple[int, tuple[str, ...]]]:
    """The tasks of ``eval --frames A:B --chunk-size N``: (K, the files ``--chunk K`` writes, as
    paths written like output), cut as ``chunked.evaluate_chunks`` cuts them. Every chunk task also
    writes the manifests, identically, so they are listed with each chunk."""
    span = parse_frames(frames)
    assert span is not None
    plan = plan_frames(span, chunk_size)  # by arithmetic: bounded (MAX_FRAMES, MAX_CHUNKS), no frame list
    manifests = [output, clip_manifest_path(output)]
    if points_cache:
        manifests += [points_cache, clip_manifest_path(points_cache)]
    return [
        (c.index, (chunk_path(output, plan, c), *([chunk_path(points_cache, plan, c)] if points_cache else []),
                   *manifests))
        for c in plan.chunks
    ]
