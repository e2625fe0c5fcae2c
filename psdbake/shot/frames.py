"""Which frames an eval covers: ``--frames A:B`` (counted before anything is allocated) or
the animation's own time samples."""

from __future__ import annotations

import re
import warnings
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..errors import InputError, PsdWarning, where

if TYPE_CHECKING:
    from ..usd.read import Scene


def parse_frames(text: str | None) -> tuple[float, float] | None:
    """'A:B' -> (A, B), inclusive whole frames; at most ``tol.MAX_FRAMES`` of them
    (checked by arithmetic: nothing is allocated for a refused range)."""
    if text is None:
        return None
    m = re.fullmatch(r"\s*(-?\d{1,30}(?:\.\d{0,30})?)\s*:\s*(-?\d{1,30}(?:\.\d{0,30})?)\s*", text)
    if not m or float(m.group(1)) > float(m.group(2)):
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise InputError(f"--frames {shown!r}: expected START:END with START <= END (e.g. 1:240)")
    span = float(m.group(1)), float(m.group(2))
    frame_count(span, text.strip())
    return span


def frame_count(frames: tuple[float, float], text: str | None = None) -> int:
    """How many whole frames A..B holds, refusing a range past ``tol.MAX_FRAMES`` frames or
    bounds past ``tol.MAX_FRAME_MAGNITUDE`` (and a range with none) before anything is allocated."""
    start, end = (float(f) for f in frames)
    shown = text if text is not None and len(text) <= 60 else f"{start:g}:{end:g}"
    if not (np.isfinite(start) and np.isfinite(end)) or max(abs(start), abs(end)) > tol.MAX_FRAME_MAGNITUDE:
        raise InputError(f"--frames {shown}: frame numbers must be finite and within "
                         f"+-{tol.MAX_FRAME_MAGNITUDE:.0f} (2**53, where whole frames stop being distinct)")
    count = int(np.floor(end) - np.ceil(start)) + 1
    if count < 1:
        raise InputError(f"--frames {shown}: no whole frame in that range")
    if count > tol.MAX_FRAMES:
        raise InputError(f"--frames {shown}: {count} frames, more than the limit of {tol.MAX_FRAMES} "
                         "(a typo? evaluate a long range in parts)")
    return count


def check_authored(scene: Scene, mesh: str, frames: tuple[float, float], label: str | None = None, *,
                   hold: bool = False) -> None:
    """Refuse ``--frames`` reaching outside the animation's authored time samples: USD holds the
    first and last pose there, so a shot numbered from 1001 evaluated at 1..100 (or the other
    way round) would quietly write the held pose. ``hold`` accepts it knowingly, with a warning."""
    times = scene.animation_times(mesh)
    anim = scene.animation_prim(mesh) or mesh
    shown = f"--frames {float(frames[0]):g}:{float(frames[1]):g}"
    if times and times[0] <= float(frames[0]) and float(frames[1]) <= times[-1]:
        return
    authored = f"authored over {times[0]:g}..{times[-1]:g}" if times else "a static pose (no time samples)"
    what = f"{where(label or scene.label, anim)}: the animation is {authored}"
    if not hold:
        raise InputError(f"{shown}: {what}: frames outside it would all show the held first or last pose; "
                         + (f"give --frames within {times[0]:g}:{times[-1]:g}, or " if times else "give ")
                         + "--hold to evaluate the held pose there")
    warnings.warn(f"{shown} (--hold): {what}: the frames outside it hold its first or last pose", PsdWarning,
                  stacklevel=3)


def frames_of(scene: Scene, mesh: str, frames: tuple[float, float] | None, label: str | None = None, *,
              hold: bool = False) -> NDArray[np.float64]:
    """Whole frames A..B when given (within the animation's authored samples, unless hold), else
    the animation's authored time samples."""
    if frames is not None:
        count = frame_count(frames)  # refuses a huge range before allocating it
        check_authored(scene, mesh, frames, label, hold=hold)
        return np.ceil(float(frames[0])) + np.arange(count, dtype=np.float64)
    times = scene.animation_times(mesh)
    if not times:
        anim = scene.animation_prim(mesh) or mesh
        raise InputError(f"{where(label or scene.label, anim)}: the animation has no time samples; give --frames")
    return np.array(times, dtype=np.float64)


def frame_label(t: float, width: int) -> str:
    """A time code in a file name: zero-padded, ``m`` for minus, ``p`` for the decimal point
    (-12.5 -> m0012p5): no characters that shells or USD asset paths treat specially."""
    text = np.format_float_positional(abs(float(t)), trim="-")  # shortest text that reads back exactly
    whole, _, frac = text.partition(".")
    return ("m" if t < 0 else "") + whole.zfill(width) + (f"p{frac}" if frac else "")
