"""Cardinal RBF weights over pose space.

Model. Example poses c_0..c_{k-1} (pose coordinates, see ``posespace``) and, for
each corrective shape s, the cardinal interpolant b_s with b_s(c_i) = [i == s]::

    b_s(x) = sum_i C[i, s] phi(eps |x - c_i|) + sum_m C[k + m, s] prod_d xhat_d ^ P[m, d]
    xhat   = (x - shift) / scale

phi is the kernel (table ``KERNELS``), eps = 1/sigma, P the monomial powers of the
polynomial term of degree ``degree`` (-1: none). The corrective at pose x is then
sum_s b_s(x) d'_s: each example's rest-space offsets d'_s are one UsdSkel BlendShape
and b_s(x) its weight. An implicit bind-pose example (zero corrective) is a centre
with no output column.

Fitting is ``scipy.interpolate.RBFInterpolator`` with the identity as data; its
solved coefficients, shift, scale and powers are copied out so that any program can
evaluate the formula above (``CardinalRbf.weights`` is that evaluation, checked
against scipy at fit time).

Automatic sigma: the mean distance between all pairs of example poses (bind pose
included), the "average distance between nodes" that scipy's classic ``Rbf`` uses
for its default epsilon. Sparse PSD example sets need Gaussians that reach across
the gaps between examples; the nearest-neighbour spacing makes them too narrow and
the weights sag between examples (measured in ``benchmarks/fidelity.py``). Dense sets
need the opposite: with the Gaussians far wider than the spacing the system becomes
singular (condition number 7e8 at 32 bench examples, 2e18 at 128). So the automatic
sigma is the largest sigma0 * 2^(-j/4), j = 0, 1, ..., whose system has a 2-norm
condition number <= ``tol.RBF_COND_TARGET`` (1e8): unchanged for sparse sets (a few
examples: j = 0), shrinking with the spacing as examples grow (``benchmarks/conditioning.py``).

Conditioning is checked before anything is solved (``plan_rbf``): the system is built
from the documented formula and its condition number computed; numerically singular
systems are refused, and a solved system must be exact at the examples
(``tol.CARDINAL_ATOL``) or the fit is refused (``FitError``, exit 4). An exact but
ill-conditioned system (a user's ``--sigma``) is kept with a ``PsdWarning``.

Dimensions: x above is the pose vector restricted to ``dims``. Without a polynomial
term that is every coordinate. With one, coordinates that no example varies (a hinge
joint's two other rotation axes, say) are dropped: their monomials would be constant
columns and make the polynomial system singular.
"""

from __future__ import annotations

import itertools
import warnings as _warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RBFInterpolator
from scipy.spatial.distance import cdist

from . import tolerances as tol
from .errors import FitError, PsdWarning

#: phi(r) for r = eps |x - c|, exactly as scipy.interpolate.RBFInterpolator defines them.
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
    basis = KERNELS[kernel](epsilon * cdist(x, centers))
    if len(powers):
        xhat = (x - shift) / scale
        poly = np.prod(xhat[:, None, :] ** powers[None, :, :], axis=2)
        basis = np.concatenate([basis, poly], axis=1)
    return basis


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
    d = cdist(centers, centers)
    sigma = float(d[np.triu_indices(len(centers), k=1)].mean())
    return sigma if sigma > 0 else tol.DEFAULT_SIGMA


def check_distinct(centers: NDArray[np.float64], labels: Sequence[str]) -> list[tuple[str, str, float]]:
    """Raise on duplicate poses; return near-duplicate pairs (label, label, distance)."""
    d = cdist(centers, centers)
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


@dataclass(frozen=True)
class RbfPlan:
    """The checked RBF system of one group, made before any example is solved.

    ``plan_rbf`` chooses sigma, the pose dimensions and the degree, builds the system from
    the documented formula, computes its condition number and solves it for every centre
    (outputs only select columns, so the plan does not need to know which examples carry a
    corrective). ``problem`` is the one-line reason the fit is refused (``plan_rbf`` raises it
    as a ``FitError`` unless asked not to); ``warnings`` are PsdWarning texts for the fit's notes.
    """

    kernel: str
    degree: int
    smoothing: float
    sigma: float  # radians; 1 for scale-free kernels
    sigma_rule: str  # how sigma was chosen: "--sigma", "mean pairwise distance", "... x 2^(-j/4) ...", "scale-free"
    dims: NDArray[np.int64]  # pose coordinates used
    centers: NDArray[np.float64]  # (k, d) over dims
    labels: tuple[str, ...]
    condition: float  # 2-norm condition number of the system matrix (inf: singular, nan: not built)
    cardinal_error: float = float("nan")  # max |b_i(c_j) - [i == j]| of the stored formula (smoothing: of its system)
    problem: str | None = None
    warnings: tuple[str, ...] = ()
    coefficients: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)))  # (k + p, k): every centre
    powers: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    shift: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    scale: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    @property
    def ok(self) -> bool:
        return self.problem is None

    def model(self, outputs: Sequence[int]) -> CardinalRbf:
        """The cardinal RBF with one weight column per centre index in ``outputs``."""
        if self.problem is not None:
            raise FitError(self.problem)
        return CardinalRbf(
            centers=self.centers, kernel=self.kernel, sigma=self.sigma, degree=self.degree, smoothing=self.smoothing,
            coefficients=np.ascontiguousarray(self.coefficients[:, list(outputs)]), powers=self.powers,
            shift=self.shift, scale=self.scale, dims=self.dims, condition=self.condition,
        )


class _System:
    """The interpolation system [[K + smoothing I, P], [P^T, 0]] over fixed centres, for any sigma."""

    def __init__(self, centers: NDArray[np.float64], kernel: str, degree: int, smoothing: float) -> None:
        self.centers, self.kernel, self.smoothing = centers, kernel, smoothing
        self.dist = cdist(centers, centers)
        self.powers = monomial_powers(centers.shape[1], degree) if degree >= 0 else np.zeros((0, centers.shape[1]),
                                                                                              dtype=np.int64)
        lo, hi = centers.min(axis=0), centers.max(axis=0)
        self.shift = (hi + lo) / 2
        scale = (hi - lo) / 2
        self.scale = np.where(scale == 0.0, 1.0, scale)
        self.poly = np.prod(((centers - self.shift) / self.scale)[:, None, :] ** self.powers[None, :, :], axis=2)

    def matrix(self, sigma: float) -> NDArray[np.float64]:
        k, p = len(self.centers), len(self.powers)
        lhs = np.zeros((k + p, k + p))
        with np.errstate(all="ignore"):
            lhs[:k, :k] = KERNELS[self.kernel](self.dist / sigma)
        lhs[:k, :k] += np.diag(np.full(k, self.smoothing))
        lhs[:k, k:] = self.poly
        lhs[k:, :k] = self.poly.T
        return lhs

    def condition(self, sigma: float) -> float:
        """2-norm condition number (the matrix is symmetric: max |eigenvalue| / min |eigenvalue|)."""
        lhs = self.matrix(sigma)
        if not np.all(np.isfinite(lhs)):
            return float("inf")
        ev = np.abs(np.linalg.eigvalsh(lhs))
        return float(ev.max() / ev.min()) if ev.min() > 0 else float("inf")

    def polynomial_rank(self) -> int:
        return int(np.linalg.matrix_rank(self.poly)) if len(self.powers) else 0


def _adapt_sigma(system: _System, sigma0: float) -> tuple[float, float, int]:
    """The largest sigma0 * STEP^j (j >= 0) whose condition number is <= RBF_COND_TARGET: halving
    first (j += 4), then quarter octaves back up. Stops at RBF_SIGMA_FLOOR_SPACINGS of the closest
    poses' distance (the kernel matrix is then the identity); returns (sigma, condition, j)."""
    k = len(system.centers)
    off = system.dist[np.triu_indices(k, 1)]
    floor = tol.RBF_SIGMA_FLOOR_SPACINGS * float(off.min()) if k > 1 else sigma0
    tried: dict[int, float] = {}

    def cond(j: int) -> float:
        if j not in tried:
            tried[j] = system.condition(sigma0 * tol.RBF_SIGMA_STEP**j)
        return tried[j]

    j = 0
    while cond(j) > tol.RBF_COND_TARGET and sigma0 * tol.RBF_SIGMA_STEP**j > floor:
        j += 4
    if cond(j) <= tol.RBF_COND_TARGET:
        for i in range(max(0, j - 3), j):  # the largest sigma between the last two halvings
            if cond(i) <= tol.RBF_COND_TARGET:
                j = i
                break
    else:  # never reached the target (a polynomial term can limit it): the best one tried
        j = min(tried, key=lambda i: (tried[i], i))
    return sigma0 * tol.RBF_SIGMA_STEP**j, tried[j], j


def _subject(labels: Sequence[str], where_: str) -> str:
    shown = ", ".join(labels) if len(labels) <= 4 else f"{labels[0]}, {labels[1]}, ... {labels[-1]}"
    return f"{where_ + ': ' if where_ else ''}the RBF system over {len(labels)} example poses ({shown})"


def _kernel_sensitivity(kernel: str, r: NDArray[np.float64]) -> NDArray[np.float64]:
    """|r phi'(r)| by central differences: how much a relative rounding of r moves phi."""
    h = 1e-4
    with np.errstate(all="ignore"):
        out = np.abs(KERNELS[kernel](r * (1 + h)) - KERNELS[kernel](r * (1 - h))) / (2 * h)
    return np.where(np.isfinite(out), out, 0.0)


def plan_rbf(
    centers: NDArray[np.float64],
    outputs: Sequence[int] | None,
    labels: Sequence[str],
    *,
    kernel: str = "gaussian",
    sigma: float | None = None,
    degree: int | None = None,
    smoothing: float = 0.0,
    where: str = "",
    raise_problem: bool = True,
) -> RbfPlan:
    """Build and check the RBF system before any example is solved (milliseconds; ~0.2 s at 500 poses).

    centers: (k, D) every centre's full pose coordinates (bind pose included), labels name them;
    outputs: the centre indices that will carry a corrective (None: not known yet; the checks
    cover every centre either way). ``where`` prefixes messages (file <prim>, group).
    Raises ``FitError`` (exit 4) with a one-line cause naming the option to change; with
    ``raise_problem=False`` the plan carries it in ``problem`` instead.
    """
    try:
        return _plan(np.asarray(centers, dtype=np.float64), labels, kernel, sigma, degree, smoothing, where)
    except FitError as exc:
        if raise_problem:
            raise
        full = np.asarray(centers, dtype=np.float64)
        return RbfPlan(kernel=kernel, degree=-1 if degree is None else int(degree), smoothing=float(smoothing),
                       sigma=float("nan") if sigma is None else float(sigma), sigma_rule="", labels=tuple(labels),
                       dims=np.arange(full.shape[1] if full.ndim == 2 else 0, dtype=np.int64), centers=full,
                       condition=float("nan"), problem=str(exc))


def _plan(full: NDArray[np.float64], labels: Sequence[str], kernel: str, sigma: float | None, degree: int | None,
          smoothing: float, where_: str) -> RbfPlan:
    at = f"{where_}: " if where_ else ""
    if kernel not in KERNELS:
        raise FitError(f"{at}unknown kernel {kernel!r}: choose --kernel from {', '.join(sorted(KERNELS))}")
    if full.ndim != 2 or len(full) == 0 or len(labels) != len(full):
        raise FitError(f"{at}no example poses to fit an RBF over")
    if not np.all(np.isfinite(full)):
        raise FitError(f"{at}an example pose has non-finite coordinates")
    check_distinct(full, labels)
    deg = default_degree(kernel) if degree is None else int(degree)
    if deg < -1:
        raise FitError(f"{at}--degree {deg} is not a polynomial degree: use -1 (none), 0, 1, 2, ...")
    if deg < MIN_DEGREE.get(kernel, -1):
        raise FitError(f"{at}kernel {kernel!r} needs a polynomial degree of at least {MIN_DEGREE[kernel]} "
                       f"(got {deg}): raise --degree or choose another --kernel")
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise FitError(f"{at}--smoothing must be a non-negative number (got {smoothing})")
    if sigma is not None and not (np.isfinite(sigma) and sigma > 0):
        raise FitError(f"{at}--sigma must be a positive number of radians (got {sigma})")
    dims = np.nonzero(np.ptp(full, axis=0) > tol.DRIVER_ANGLE_ATOL)[0] if deg >= 0 else np.arange(full.shape[1])
    centers = full[:, dims]
    k, subject = len(centers), _subject(labels, where_)
    system = _System(centers, kernel, deg, float(smoothing))
    p = len(system.powers)
    if p > k:
        raise FitError(f"{subject}: a degree-{deg} polynomial term in {len(dims)} pose dimensions has {p} monomials, "
                       f"more than the {k} poses that must determine it: use a lower --degree or more examples")
    if p and system.polynomial_rank() < p:
        raise FitError(f"{subject}: the poses do not determine a degree-{deg} polynomial term (its {p} monomials are "
                       "linearly dependent at the poses, e.g. poses along a line): use a lower --degree or more "
                       "varied examples")

    warnings: list[str] = []
    if kernel in SCALE_FREE:
        sig, rule = 1.0, "scale-free kernel"
        cond = system.condition(sig)
    elif sigma is not None:
        sig, rule = float(sigma), "--sigma"
        cond = system.condition(sig)
        spacing = float(system.dist[np.triu_indices(k, 1)].min()) if k > 1 else float("inf")
        if kernel == "gaussian" and sig < spacing / 3:
            warnings.append(f"{subject}: --sigma {sig:.3g} rad is far below the closest poses' distance "
                            f"({spacing:.3g} rad): each corrective vanishes before the next example; omit --sigma "
                            "for the automatic one")
    else:
        sigma0 = auto_sigma(centers)
        sig, cond, j = _adapt_sigma(system, sigma0)
        rule = "mean pairwise distance" if j == 0 else f"mean pairwise distance {sigma0:.4g} x 2^(-{j}/4)"

    def advice() -> str:
        if kernel not in SCALE_FREE and sigma is not None:
            auto, auto_cond, _ = _adapt_sigma(system, auto_sigma(centers))  # eigenvalues only: no solve
            if auto_cond < cond:
                return f"use a smaller --sigma (the automatic {auto:.3g} rad gives {auto_cond:.1e}) or omit it"
        if deg >= 0:
            return "use a lower --degree, --smoothing or fewer examples"
        if kernel in SCALE_FREE:
            return "use another --kernel, --smoothing or fewer examples"
        return "use --smoothing, another --kernel or fewer examples"

    at_sigma = f"with sigma {sig:.3g} rad, kernel {kernel}, degree {deg}"
    if not cond < tol.RBF_COND_MAX:
        raise FitError(f"{subject} is numerically singular (condition number {cond:.1e} {at_sigma}): {advice()}")

    try:
        with np.errstate(all="ignore"):
            interp = RBFInterpolator(centers, np.eye(k), kernel=kernel, epsilon=1.0 / sig, degree=deg,
                                     smoothing=float(smoothing))
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FitError(f"{subject} is singular ({str(exc).splitlines()[0]}; condition number {cond:.1e} "
                       f"{at_sigma}): {advice()}") from None
    coefficients = np.array(interp._coeffs, dtype=np.float64)
    powers = np.array(interp.powers, dtype=np.int64)
    powers = powers.reshape(len(powers), centers.shape[1])  # (0, d) or (p, 0) too
    shift = np.array(interp._shift, dtype=np.float64)
    scale = np.array(interp._scale, dtype=np.float64)

    # Exactness of the stored formula at the examples: b(c_i) = delta (with smoothing, of its own system).
    with np.errstate(all="ignore"):
        basis = formula_basis(centers, centers, kernel, 1.0 / sig, powers, shift, scale)
        ours = basis @ coefficients
        theirs = interp(centers)
        target = np.eye(k) - float(smoothing) * coefficients[:k]
        size = np.abs(basis) @ np.abs(coefficients)  # the dot products' magnitudes: their round-off scale
    eps = float(np.finfo(np.float64).eps)
    noise = eps * float(np.max(size)) if size.size else 0.0
    err = float(np.max(np.abs(ours - target))) if np.all(np.isfinite(ours)) else float("inf")
    err_scipy = float(np.max(np.abs(theirs - target))) if np.all(np.isfinite(theirs)) else float("inf")
    if not (err <= tol.CARDINAL_ATOL and noise <= tol.CARDINAL_ATOL):
        if err_scipy <= tol.CARDINAL_ATOL and noise <= tol.CARDINAL_ATOL:
            # scipy is exact and our copy of its solution is not: not conditioning but a changed scipy
            sensitivity = _kernel_sensitivity(kernel, system.dist / sig) @ np.abs(coefficients[:k])
            bound = eps * ((basis.shape[1] + tol.FORMULA_ULPS) * size + tol.FORMULA_ULPS * sensitivity)
            if np.any(np.abs(ours - theirs) > bound):
                raise RuntimeError("scipy RBFInterpolator internals changed: stored coefficients no longer "
                                   "reproduce it")
        raise FitError(f"{subject} is ill-conditioned (condition number {cond:.1e} {at_sigma}): its weights miss "
                       f"the examples by {max(err, noise):.1e} (tolerance {tol.CARDINAL_ATOL:g}): {advice()}")
    if cond > tol.RBF_COND_TARGET:
        warnings.append(f"{subject} is ill-conditioned (condition number {cond:.1e} {at_sigma}, above "
                        f"{tol.RBF_COND_TARGET:.0e}) but exact at the examples (to {err:.1e}); its weights between "
                        f"examples carry round-off of ~{noise:.0e}: {advice()}")
    return RbfPlan(
        kernel=kernel, degree=deg, smoothing=float(smoothing), sigma=sig, sigma_rule=rule, dims=dims.astype(np.int64),
        centers=centers, labels=tuple(labels), condition=cond, cardinal_error=err, warnings=tuple(warnings),
        coefficients=coefficients, powers=powers, shift=shift, scale=scale,
    )


def fit_cardinal(
    centers: NDArray[np.float64],
    outputs: Sequence[int],
    labels: Sequence[str],
    *,
    kernel: str = "gaussian",
    sigma: float | None = None,
    degree: int | None = None,
    smoothing: float = 0.0,
    plan: RbfPlan | None = None,
    where: str = "",
) -> CardinalRbf:
    """Fit cardinal weights: one output column per centre index in ``outputs``.

    centers: (k, d) example poses; labels name them in errors. ``plan``: the ``plan_rbf`` of
    the same centres and settings, made earlier (before the examples were solved); without
    it the plan is made here and its warnings are issued as ``PsdWarning`` (a caller passing
    a plan reports ``plan.warnings`` itself).
    """
    if plan is None:
        plan = plan_rbf(centers, outputs, labels, kernel=kernel, sigma=sigma, degree=degree, smoothing=smoothing,
                        where=where)
        for msg in plan.warnings:
            _warnings.warn(msg, PsdWarning, stacklevel=2)
    return plan.model(outputs)
