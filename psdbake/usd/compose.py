"""Input files -> a composed stage: every command's first step.

Every command opens an in-memory root layer whose sublayers are the given files,
strongest first (e.g. ``[EXAMPLES, ASSET]``), so ``POSES``/``EXAMPLES``/``ANIM`` layers
need not reference ASSET. Inputs are opened read-only and never saved; only regular
files are opened, binary ones after a child process has read them whole
(``integrity``), text ones after their nesting is counted (``nesting``), and layer metadata
that would make USD loop is refused.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
from pxr import Sdf, Tf, Usd

from ..errors import InputError
from .dependencies import fresh, layer_files, require_regular
from .diagnostics import first_line as _first_line
from .integrity import require_readable_crates
from .nesting import require_shallow


def open_layer(path: str) -> Sdf.Layer:
    """Open one input file read-only, or raise InputError naming it."""
    if not os.path.exists(path):
        raise InputError(f"{path}: file not found")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a folder, not a USD file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: file is not readable (permission denied)")
    require_regular(path)
    require_readable_crates([path])
    require_shallow(path)
    try:
        layer = fresh(Sdf.Layer.FindOrOpen(path))
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: not a readable USD file ({_first_line(exc)})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a readable USD file (it holds text that is not UTF-8)") from None
    if layer is None:
        raise InputError(f"{path}: not a readable USD file")
    # USD's time-sample queries loop forever on an infinite time-code rate: refuse it here.
    for key in ("timeCodesPerSecond", "framesPerSecond", "startTimeCode", "endTimeCode"):
        if layer.pseudoRoot.HasInfo(key):
            raw = layer.pseudoRoot.GetInfo(key)
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise InputError(f"{path}: layer metadata {key} is {type(raw).__name__} {raw!r}, not a number") from None
            positive = key.endswith("PerSecond")
            if not np.isfinite(value) or (positive and value <= 0):
                raise InputError(f"{path}: layer metadata {key} = {value!r} is not a {'positive ' if positive else ''}number")
    return layer


def reread(path: str) -> None:
    """Make USD's copy of the layer file at path what the file holds now.

    USD keeps one copy of each layer per process: ``Sdf.Layer.FindOrOpen`` returns the copy
    this process already loaded (the command walks its inputs, and keeps them open, before it
    reads them) even after another process has replaced the file. A read-modify-write of an
    output (``fit --group``, ``mirror`` in place) calls this under its update lock, so what it
    reads and merges is the file as the last writer left it, not the copy of minutes ago. The
    new bytes are checked as any input is (regular file, crate probe, text nesting) first."""
    layer = Sdf.Layer.Find(path)
    if layer is None or not os.path.isfile(path):
        return  # not loaded: the next open reads the file; gone: the next open says so
    require_regular(path)
    require_readable_crates([path])
    require_shallow(path)
    try:
        reloaded = layer.Reload(force=True)
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: not a readable USD file ({_first_line(exc)})") from None
    if not reloaded:
        raise InputError(f"{path}: not a readable USD file (USD could not read it again)")


def _time_rates(root: Sdf.Layer, layers: Sequence[Sdf.Layer]) -> None:
    """The root takes the strongest authored timeCodesPerSecond (and framesPerSecond): USD
    scales a sublayer's time codes by the root's rate over its own, so an anonymous root at
    the default 24 would move a 30 fps ANIM's samples to other time codes."""
    for key in ("timeCodesPerSecond", "framesPerSecond"):
        for layer in layers:  # strongest first
            if layer.pseudoRoot.HasInfo(key):
                root.pseudoRoot.SetInfo(key, float(layer.pseudoRoot.GetInfo(key)))
                break


def compose(files: Sequence[str | Sdf.Layer]) -> Usd.Stage:
    """A stage over the given files (or in-memory layers), strongest first; inputs stay untouched."""
    root = Sdf.Layer.CreateAnonymous("psdbake.usda")
    keep: list[Sdf.Layer] = []
    for item in reversed(files):  # weakest first, so a file given twice keeps its weakest place
        layer = item if isinstance(item, Sdf.Layer) else open_layer(item)
        if any(layer.identifier == k.identifier for k in keep):
            continue  # e.g. --anim ASSET: the asset's own animation must stay weaker than CORRECTIVES
        keep.insert(0, layer)
    layer_files(keep)  # every layer the stage will open is a regular file: no FIFO blocks composition
    for layer in keep:
        root.subLayerPaths.append(layer.identifier)
    _time_rates(root, keep)
    try:
        stage = Usd.Stage.Open(root, Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise InputError(f"{files[0]}: cannot compose ({_first_line(exc)})") from None
    errors = stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else []
    if errors:
        raise InputError(f"{files[0]}: composition error: {_first_line(str(errors[0]))}")
    stage.psdbake_layers = keep  # keep in-memory sublayers alive as long as the stage
    return stage
