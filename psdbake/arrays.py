"""Array aliases shared by the pipeline, with their shapes (numpy float64 unless said), and the
row norms the solver takes of them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from . import tolerances as tol

Points = NDArray[np.float64]  # (n, 3) positions or offsets, mesh local space
Matrices = NDArray[np.float64]  # (j, 4, 4) Gf row-vector transforms (p' = p . M)
Quaternions = NDArray[np.float64]  # (j, 4) scalar-last (x, y, z, w), as scipy
Progress = Callable[[int, int, str], None]  # (done, total, what)


def row_norms(a: NDArray[np.float64], b: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Length of each row of ``a - b`` (or of a), (n, k) -> (n,): ``np.linalg.norm(a - b, axis=1)``
    bit for bit, column by column. numpy sums a row of fewer than 8 squares in order,
    ((x^2 + y^2) + z^2), as this does (tests/test_exact_kernels.py holds the two equal), without the
    (n, 3) difference and squares (7 MB of fresh pages at 100k points) or 3-element inner loops."""
    if a.ndim != 2 or not 1 <= a.shape[1] < 8 or a.dtype != np.float64 or (b is not None and b.shape != a.shape):
        return np.linalg.norm(a if b is None else a - b, axis=1)

    def squares(k: int, out: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        if b is None:
            return np.multiply(a[:, k], a[:, k], out=out)
        d = np.subtract(a[:, k], b[:, k], out=out)
        return np.multiply(d, d, out=d)

    total = squares(0)
    term = np.empty_like(total)
    for k in range(1, a.shape[1]):
        total += squares(k, term)
    return np.sqrt(total, out=total)


def is_singular(m: NDArray[np.float64], rcond: float = tol.SINGULAR_RCOND, det: NDArray[np.float64] | None = None
                ) -> NDArray[np.bool_]:
    """Which square matrices (..., n, n) are singular or not finite: |det M| <= rcond |M|_F^n
    (``tol.SINGULAR_RCOND``; the solver passes ``tol.JACOBIAN_RCOND``). No SVD: the determinant
    is zero for a singular M, and n^(-n/2) of |M|_F^n for a rotation. ``det``: already computed."""
    m = np.asarray(m, dtype=np.float64)
    n = m.shape[-1]
    with np.errstate(invalid="ignore", over="ignore"):
        scale = np.einsum("...ab,...ab->...", m, m) ** (n / 2)
        if det is None:
            det = np.linalg.det(np.where(np.isfinite(m), m, 0.0))
        return ~(np.isfinite(scale) & (np.abs(det) > rcond * np.maximum(scale, 1e-300)))
