"""Fitting cardinal RBF weights over pose space, with the system checked first.

The model and its formula are ``rbf_model`` (re-exported here). An implicit bind-pose
example (zero corrective) is a centre with no output column.

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

import warnings as _warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RBFInterpolator
from scipy.spatial.distance import cdist

from .. import tolerances as tol
from ..errors import FitError, PsdWarning
from ..model.rbf import (
    KERNELS,
    MIN_DEGREE,
    SCALE_FREE,
    CardinalRbf,
    auto_sigma,
    check_distinct,
    constant_one,
    default_degree,
    formula_basis,
    monomial_powers,
    row_independent_product,
)

__all__ = [  # the model's names, re-exported: callers import the RBF from one place
    "KERNELS", "MIN_DEGREE", "SCALE_FREE", "CardinalRbf", "RbfPlan", "auto_sigma", "check_distinct", "constant_one",
    "default_degree", "fit_cardinal", "formula_basis", "monomial_powers", "plan_rbf", "row_independent_product",
]


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


class System:
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


def _adapt_sigma(system: System, sigma0: float) -> tuple[float, float, int]:
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
    start: float | None = None,
    start_rule: str = "joint sigma",
) -> RbfPlan:
    """Build and check the RBF system before any example is solved (milliseconds; ~0.2 s at 500 poses).

    start: where the automatic sigma starts (sigma0; default the mean pairwise distance), and
    start_rule what the plan's ``sigma_rule`` calls it.

    centers: (k, D) every centre's full pose coordinates (bind pose included), labels name them;
    outputs: the centre indices that will carry a corrective (None: not known yet; the checks
    cover every centre either way). ``where`` prefixes messages (file <prim>, group).
    Raises ``FitError`` (exit 4) with a one-line cause naming the option to change; with
    ``raise_problem=False`` the plan carries it in ``problem`` instead.
    """
    try:
        return _plan(np.asarray(centers, dtype=np.float64), labels, kernel, sigma, degree, smoothing, where, start,
                     start_rule)
    except FitError as exc:
        if raise_problem:
            raise
        full = np.asarray(centers, dtype=np.float64)
        return RbfPlan(kernel=kernel, degree=-1 if degree is None else int(degree), smoothing=float(smoothing),
                       sigma=float("nan") if sigma is None else float(sigma), sigma_rule="", labels=tuple(labels),
                       dims=np.arange(full.shape[1] if full.ndim == 2 else 0, dtype=np.int64), centers=full,
                       condition=float("nan"), problem=str(exc))


def _check_settings(full: NDArray[np.float64], labels: Sequence[str], kernel: str, sigma: float | None,
                    degree: int | None, smoothing: float, at: str) -> int:
    """Refuse settings no system can satisfy; returns the polynomial degree."""
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
    return deg


def _check_polynomial(system: System, subject: str, deg: int, dims: int) -> None:
    p, k = len(system.powers), len(system.centers)
    if p > k:
        raise FitError(f"{subject}: a degree-{deg} polynomial term in {dims} pose dimensions has {p} monomials, "
                       f"more than the {k} poses that must determine it: use a lower --degree or more examples")
    if p and system.polynomial_rank() < p:
        raise FitError(f"{subject}: the poses do not determine a degree-{deg} polynomial term (its {p} monomials are "
                       "linearly dependent at the poses, e.g. poses along a line): use a lower --degree or more "
                       "varied examples")


def _choose_sigma(system: System, kernel: str, sigma: float | None, subject: str, warnings: list[str],
                  start: float | None = None, start_rule: str = "joint sigma") -> tuple[float, float, str]:
    """(sigma, condition number, the rule that chose it): scale-free kernels 1, --sigma as
    given (warned when far narrower than the poses' spacing), else the adaptive rule."""
    k = len(system.centers)
    if kernel in SCALE_FREE:
        return 1.0, system.condition(1.0), "scale-free kernel"
    if sigma is not None:
        spacing = float(system.dist[np.triu_indices(k, 1)].min()) if k > 1 else float("inf")
        if kernel == "gaussian" and sigma < spacing / 3:
            warnings.append(f"{subject}: --sigma {sigma:.3g} rad is far below the closest poses' distance "
                            f"({spacing:.3g} rad): each corrective vanishes before the next example; omit --sigma "
                            "for the automatic one")
        return float(sigma), system.condition(float(sigma)), "--sigma"
    sigma0 = auto_sigma(system.centers) if start is None else float(start)
    sig, cond, j = _adapt_sigma(system, sigma0)
    rule = "mean pairwise distance" if start is None else start_rule
    return sig, cond, rule if j == 0 else f"{rule} {sigma0:.4g} x 2^(-{j}/4)"


def _advice(system: System, kernel: str, sigma: float | None, deg: int, cond: float) -> str:
    """The option to change, for a system that is singular or not exact."""
    if kernel not in SCALE_FREE and sigma is not None:
        auto, auto_cond, _ = _adapt_sigma(system, auto_sigma(system.centers))  # eigenvalues only: no solve
        if auto_cond < cond:
            return f"use a smaller --sigma (the automatic {auto:.3g} rad gives {auto_cond:.1e}) or omit it"
    if deg >= 0:
        return "use a lower --degree, --smoothing or fewer examples"
    if kernel in SCALE_FREE:
        return "use another --kernel, --smoothing or fewer examples"
    return "use --smoothing, another --kernel or fewer examples"


def _plan(full: NDArray[np.float64], labels: Sequence[str], kernel: str, sigma: float | None, degree: int | None,
          smoothing: float, where_: str, start: float | None = None, start_rule: str = "joint sigma") -> RbfPlan:
    deg = _check_settings(full, labels, kernel, sigma, degree, smoothing, f"{where_}: " if where_ else "")
    dims = np.nonzero(np.ptp(full, axis=0) > tol.DRIVER_ANGLE_ATOL)[0] if deg >= 0 else np.arange(full.shape[1])
    centers = full[:, dims]
    subject = _subject(labels, where_)
    system = System(centers, kernel, deg, float(smoothing))
    _check_polynomial(system, subject, deg, len(dims))
    warnings: list[str] = []
    sig, cond, rule = _choose_sigma(system, kernel, sigma, subject, warnings, start, start_rule)
    at_sigma = f"with sigma {sig:.3g} rad, kernel {kernel}, degree {deg}"
    if not cond < tol.RBF_COND_MAX:
        raise FitError(f"{subject} is numerically singular (condition number {cond:.1e} {at_sigma}): "
                       f"{_advice(system, kernel, sigma, deg, cond)}")
    solved = _solve_checked(system, sig, deg, float(smoothing), subject, at_sigma,
                            lambda: _advice(system, kernel, sigma, deg, cond), cond)
    coefficients, powers, shift, scale, err, noise = solved
    if cond > tol.RBF_COND_TARGET:
        warnings.append(f"{subject} is ill-conditioned (condition number {cond:.1e} {at_sigma}, above "
                        f"{tol.RBF_COND_TARGET:.0e}) but exact at the examples (to {err:.1e}); its weights between "
                        f"examples carry round-off of ~{noise:.0e}: {_advice(system, kernel, sigma, deg, cond)}")
    return RbfPlan(
        kernel=kernel, degree=deg, smoothing=float(smoothing), sigma=sig, sigma_rule=rule, dims=dims.astype(np.int64),
        centers=centers, labels=tuple(labels), condition=cond, cardinal_error=err, warnings=tuple(warnings),
        coefficients=coefficients, powers=powers, shift=shift, scale=scale,
    )


def _solve_checked(system: System, sig: float, deg: int, smoothing: float, subject: str, at_sigma: str,
                   advice: Callable[[], str], cond: float):
    """scipy's solution, copied into the documented formula's terms, and checked exact at the
    examples: (coefficients, powers, shift, scale, error at the examples, round-off scale)."""
    centers, kernel, k = system.centers, system.kernel, len(system.centers)
    try:
        with np.errstate(all="ignore"):
            interp = RBFInterpolator(centers, np.eye(k), kernel=kernel, epsilon=1.0 / sig, degree=deg,
                                     smoothing=smoothing)
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
        target = np.eye(k) - smoothing * coefficients[:k]
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
    return coefficients, powers, shift, scale, err, noise


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
