"""The cardinal RBF model over pose space: kernels, the documented formula, the stored weights.

Model. Example poses c_0..c_{k-1} (pose coordinates, see ``posespace``) and, for
each corrective shape s, the cardinal interpolant b_s with b_s(c_i) = [i == s]::

    b_s(x) = sum_i C[i, s] phi(eps |x - c_i|) + sum_m C[k + m, s] prod_d xhat_d ^ P[m, d]
    xhat   = (x - shift) / scale

phi is the kernel (table ``KERNELS``: a new kernel is one entry there), eps = 1/sigma, P
the monomial powers of the polynomial term of degree ``degree`` (-1: none). The corrective
at pose x is then sum_s b_s(x) d'_s: each example's rest-space offsets d'_s are one
UsdSkel BlendShape and b_s(x) its weight. ``CardinalRbf.weights`` is this formula, the one a
third party evaluates from the ``psd:`` attributes; ``rbf`` fits and checks it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from ..errors import FitError

#: phi(r) for r = eps |x - c|, exactly as scipy.interpolate.RBFInterpolator defines them, by
#: name, as SciPy keys its table (``names.KERNEL_NAMES``, checked by tests/test_layering.py).
KERNELS = {
    "gaussian": lambda r: np.exp(-(r**2)),
    "linear": lambda r: -r,
    "thin_plate_spline": lambda r: np.where(r > 0, r**2 * np.log(np.where(r > 0, r, 1.0)), 0.0),
    "cubic": lambda r: r**3,
    "quintic": lambda r: -(r**5),
    "multiquadric": lambda r: -np.sqrt(r**2 + 1.0),
    "inverse_multiquadric": lambda r: 1.0 / np.sqrt(r**2 + 1.0),
    "inverse_quadratic": lambda r: 1.0 / (r**2 + 1.0),
}


#: Kernels that need at least this polynomial degree to be well posed (scipy's rule).
MIN_DEGREE = {"multiquadric": 0, "linear": 0, "thin_plate_spline": 1, "cubic": 1, "quintic": 2}


#: Kernels whose shape does not depend on eps: sigma is meaningless and stored as 1.
SCALE_FREE = frozenset({"linear", "thin_plate_spline", "cubic", "quintic"})


@dataclass(frozen=True)
class CardinalRbf:
    """Everything needed to evaluate the cardinal weights b_s(x)."""

    centers: NDArray[np.float64]  # (k, d) example pose coordinates (bind pose included), over dims
    kernel: str
    sigma: float  # eps = 1 / sigma
    degree: int  # polynomial degree, -1 for none
    smoothing: float
    coefficients: NDArray[np.float64]  # (k + p, s)
    powers: NDArray[np.int64]  # (p, d)
    shift: NDArray[np.float64]  # (d,)
    scale: NDArray[np.float64]  # (d,)
    dims: NDArray[np.int64]  # (d,) indices of the pose coordinates used
    condition: float = float("nan")  # 2-norm condition number of the fitted system (nan: not fitted here)

    @property
    def epsilon(self) -> float:
        return 1.0 / self.sigma

    def weights(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """b(x): (f, D) full pose coordinates -> (f, s) weights, by the documented formula."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))[:, self.dims]
        k = len(self.centers)
        basis = formula_basis(x, self.centers, self.kernel, self.epsilon, self.powers, self.shift, self.scale)
        return row_independent_product(basis, self.coefficients[: k + len(self.powers)])


def formula_basis(x: NDArray[np.float64], centers: NDArray[np.float64], kernel: str, epsilon: float,
                  powers: NDArray[np.int64], shift: NDArray[np.float64], scale: NDArray[np.float64]
                  ) -> NDArray[np.float64]:
    """The documented formula's basis at x (over dims): [phi(eps |x - c_i|) ..., monomials of xhat ...].
    The fit builds its system from this too, so what is checked is what is stored."""
    basis = KERNELS[kernel](epsilon * distances(x, centers))
    if len(powers):
        xhat = (x - shift) / scale
        poly = np.prod(xhat[:, None, :] ** powers[None, :, :], axis=2)
        basis = np.concatenate([basis, poly], axis=1)
    return basis


def distances(x: NDArray[np.float64], centers: NDArray[np.float64]) -> NDArray[np.float64]:
    """|x_i - c_j| (n, k) for x (n, d) and centres (k, d): scipy's ``cdist(x, centers)`` bit for
    bit, its squares summed coordinate by coordinate in order and each sum's root taken once.

    Why not cdist: importing it loads ``scipy.spatial`` whole (~0.3 s, k-d trees, Qhull,
    ``scipy.sparse``), which every ``psdbake eval`` would pay before its first frame. Separate
    multiplies and adds in numpy (never fused) give cdist's bits; tests/test_quaternions.py
    holds the two equal on random input.
    """
    x, centers = np.asarray(x, dtype=np.float64), np.asarray(centers, dtype=np.float64)
    total = np.zeros((x.shape[0], centers.shape[0]))
    for d in range(x.shape[1]):
        diff = x[:, d, None] - centers[None, :, d]
        total += diff * diff
    return np.sqrt(total)


def row_independent_product(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """a @ b summed term by term in a fixed order: each row of the result depends on that row
    of a only, bit for bit.

    Why not BLAS: its kernels round a row differently depending on how many rows come with it
    (gemv for one row, edge kernels for the odd rows of a block; measured on this project's
    machines: 1 row in 3 differs in the last bit for 3-row calls), so a frame's weights
    would depend on how a shot is cut into farm chunks. Separate multiplies and adds (numpy
    never fuses them) give the same bits for any row count, whatever kernel BLAS would pick.
    Cost measured against BLAS: about the same up to 30 examples (~1 us/frame); 17 vs 1.3
    us/frame at 120 examples x 119 shapes (an eval frame costs ~20 us in UsdSkel anyway).
    """
    out = np.zeros((a.shape[0], b.shape[1]), dtype=np.float64)
    step = max(1, 32768 // max(1, b.shape[1]))  # rows per block: the block's sums stay in cache
    for start in range(0, a.shape[0], step):
        rows, acc = a[start : start + step], out[start : start + step]
        for i in range(b.shape[0]):
            acc += rows[:, i, None] * b[i]
    return out


def constant_one(centers: NDArray[np.float64]) -> CardinalRbf:
    """b(x) = 1 everywhere, in the documented formula's terms (degree 0: one constant monomial,
    no kernel weight): a combination corrective with one example, shaped by its gates."""
    dims = np.arange(np.asarray(centers).shape[1], dtype=np.int64)
    return CardinalRbf(
        centers=np.asarray(centers, dtype=np.float64), kernel="gaussian", sigma=tol.DEFAULT_SIGMA, degree=0,
        smoothing=0.0, coefficients=np.array([[0.0], [1.0]]), powers=np.zeros((1, len(dims)), dtype=np.int64),
        shift=np.zeros(len(dims)), scale=np.ones(len(dims)), dims=dims,
    )


def default_degree(kernel: str) -> int:
    """No polynomial term unless the kernel needs one (Gaussian: none)."""
    return MIN_DEGREE.get(kernel, -1)


def auto_sigma(centers: NDArray[np.float64]) -> float:
    """Mean pairwise distance between centres (DEFAULT_SIGMA for one centre): the automatic
    sigma's starting point, sigma0 (``plan_rbf`` shrinks it when the system is ill-conditioned)."""
    if len(centers) < 2:
        return tol.DEFAULT_SIGMA
    d = distances(centers, centers)
    sigma = float(d[np.triu_indices(len(centers), k=1)].mean())
    return sigma if sigma > 0 else tol.DEFAULT_SIGMA


def check_distinct(centers: NDArray[np.float64], labels: Sequence[str]) -> list[tuple[str, str, float]]:
    """Raise on duplicate poses; return near-duplicate pairs (label, label, distance)."""
    d = distances(centers, centers)
    close = np.argwhere(np.triu(d < tol.NEAR_DUPLICATE_POSE_ATOL, k=1))
    near = []
    for i, j in close:
        if d[i, j] < tol.DUPLICATE_POSE_ATOL:
            raise FitError(
                f"examples {labels[i]} and {labels[j]} have the same pose "
                f"(distance {d[i, j]:.2e} rad in pose space): remove one or merge their sculpts"
            )
        near.append((labels[i], labels[j], float(d[i, j])))
    return near


def monomial_powers(ndim: int, degree: int) -> NDArray[np.int64]:
    """The polynomial term's monomials, in scipy's order: (p, ndim) powers, p = C(degree + ndim, ndim)."""
    out = []
    for deg in range(degree + 1):
        for mono in itertools.combinations_with_replacement(range(ndim), deg):
            row = [0] * ndim
            for var in mono:
                row[var] += 1
            out.append(row)
    return np.array(out, dtype=np.int64).reshape(len(out), ndim)
