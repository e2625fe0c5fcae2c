"""USD arrays read as numpy arrays in place, where their element type already serves.

Checks of indices and weights give the same answers on USD's own int32 and float32 arrays as on
64-bit copies, and the copies cost fresh pages (6 MB for a 100k-point mesh's skin influences, a
million indices for a 128-example CORRECTIVES' shapes)."""

from __future__ import annotations

import numpy as np


def numbers(value, dtype: type) -> np.ndarray:
    """A USD array as a 1-D array of numbers of dtype's kind: USD's own array, read in place (not
    writable), when it already is one (int32 indices, float32 weights), else converted to dtype
    (None: an empty array)."""
    if value:
        try:
            view = np.asarray(value)
        except (TypeError, ValueError):
            view = None
        if view is not None and view.ndim == 1 and view.dtype.kind == np.dtype(dtype).kind:
            return view
    return np.array(value if value is not None else [], dtype=dtype)
