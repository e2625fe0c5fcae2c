"""The coupled inverse's smooth start: Levenberg-Marquardt over a region's smoothest fields, on
a model of the chain that knows how much the chain smooths.

Model. ``basis`` (k, b) holds the region's smoothest fields (``psdbake.solver.smoothbasis``), field
j with normalised frequency ``f_j`` (its Rayleigh quotient of the random-walk Laplacian,
0 for a constant, up to 2). Offsets are ``D = basis @ X`` (X: (b, 3) coefficients), and
the chain's Jacobian on field j along axis a is modelled as::

    J (phi_j e_a)  ~  g_j * B (phi_j e_a),        g_j = (1 - f_j / 2) ** reach

``B`` the per-vertex 3x3 blocks (the chain's response to moving every sculpted vertex along
one axis: for a chain that smooths, the skinning's own blocks) and ``g_j`` the gain of a
uniform smoothing step of weight 1/2 taken ``reach`` times (Delta Mush's umbrella smoothing
is exactly such steps). A chain that smooths passes a smooth field at less than its full
size: where the smoothing reaches across a large part of a small mesh, fields the sculpt
needs come out at a fifth of their size or less (1.3k bench rig: the 64th field at 0.18,
measured with the full Jacobian), and a model that takes them at full size (the blocks
alone, ``reach = 0``) undershoots every step there. One probe call measures ``reach``
(``measure_reach``): the response to a small random combination of the fields, projected
back on them, fitted by one parameter. The chain is only called, never looked into; a chain
that does not smooth fits ``reach = 0`` and the model is the blocks'.

Solve (``span_solve``): Levenberg-Marquardt steps in coefficient space on that model,
``(G + lam I) y = C r`` with ``C`` the model's columns and ``G = C C^T``; each step is one
call, whose secant corrects the model (Broyden's update of ``C``, and ``G`` with it, by
rank-two updates). ``lam`` follows the steps' gain ratio (actual over predicted decrease):
it is cut where the model predicted well and raised where it did not. The objective is
regularised, ``|r|^2 + ridge |D|^2`` with ``ridge`` (``ridge``) ``SPAN_RIDGE**2`` times the
blocks' squared gain: the documented regularisation that keeps offsets bounded where a sculpt
asks for what the chain cannot produce (a direction the chain passes at less than
``SPAN_RIDGE`` of a smooth move is not pushed further than the residual it removes);
Newton-Krylov's finish (``coupled.invert_coupled``) then weighs the departure from the smooth
start more strongly. A rejected step changes nothing but the model. The solve stops when every
vertex is within ``atol``, at the span's optimum
(``SpanResult.stalled``: ``SPAN_PATIENCE`` accepted steps in a row gained less than
``SPAN_MIN_GAIN`` of the residual, or, for a model the probe found accurate or anywhere
within ``BELIEVE_NEAR`` times the tolerance, a model whose last prediction came true within
``1 - GOOD_RATIO`` predicts no more than that for the next step, which costs no call), or
when its calls run out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from .. import tolerances as tol
from ..arrays import Points, is_singular
from .inverse import BlackBox

#: Largest reach fitted (smoothing steps of weight 1/2): beyond ~40 the fields a span holds
#: are all passed at nearly nothing, and the fit can no longer tell reaches apart.
MAX_REACH = 40.0
#: Reach is fitted on this grid (steps).
REACH_STEP = 0.25
#: A fit that leaves more than this fraction of the probe's response unexplained is not
#: used (the model falls back to the blocks alone, reach 0). Measured: 0.02-0.03 on the 13k
#: bench rig, 0.11-0.68 on the 1.3k rig's folds, where the fitted reach stays within 10 +- 0.8.
REACH_MAX_MISFIT = 0.9
#: The probe's largest vertex move, a fraction of the diagonal: small enough that the chain
#: is linear over it, far above float32 noise.
PROBE_RTOL = 1e-3
#: Levenberg-Marquardt's starting damping, relative to the model's largest eigenvalue.
SPAN_DAMPING = 1e-6
#: Damping never goes below SPAN_RIDGE**2 times the model's largest eigenvalue: the
#: documented regularisation of ``span_solve`` (module docstring).
SPAN_RIDGE = 1e-3
#: A step is judged by its gain ratio (actual over predicted decrease of |r|^2): above
#: GOOD_RATIO the damping is cut tenfold, below POOR_RATIO raised tenfold.
GOOD_RATIO, POOR_RATIO = 0.75, 0.25
#: The span solve stops after SPAN_PATIENCE accepted steps in a row that each lowered the
#: residual's norm by less than SPAN_MIN_GAIN (the span's optimum), or SPAN_PATIENCE
#: rejected steps in a row.
SPAN_PATIENCE = 3
SPAN_MIN_GAIN = 0.05
#: A reach fit that explains the probe's response within this is accurate enough for the span
#: solve to stop where its model sees no more to gain (``span_solve(believe=True)``).
#: Measured misfits: 0.0015-0.002 on the 100k bench rig, 0.02-0.03 at 13k, 0.026 on CesiumMan;
#: 0.11-0.68 on the 1.3k rig, where the model keeps learning over 10-20 steps at the fold.
BELIEVE_MISFIT = 0.05
#: Any model is believed so once the residual's RMS is within this many times the tolerance:
#: a model that has just predicted a step that close to the answer is the chain's local
#: secant model there, whatever the probe found over the whole span from zero. Measured
#: through LBS + Delta Mush: the 1.3k bench rig's folded six 41.2 -> 37.3 calls an example,
#: the 3k rig's eight 29.5 -> 25.9, the character fixture's 34.2 -> 32.1, CesiumMan, 13k and
#: 100k unchanged. At 10 the 3k rig took 23.4, but one of its random poses stopped a vertex
#: short after 580 calls; 5 gave the 3k rig 27.1 and 3 the 1.3k folds 39.5; at 30 CesiumMan@12
#: (its smooth start ends at 29 times the tolerance) took 243 calls, not 187. A model believed
#: everywhere stopped the 1.3k rig's 60 degree elbow at 617 times the tolerance, and it missed
#: after 1,705 calls.
BELIEVE_NEAR = 7.0


@dataclass(frozen=True)
class Reach:
    """The chain's smoothing as the model sees it: ``steps`` smoothing steps of weight 1/2,
    fitted to the probe's response with ``misfit`` (fraction of it unexplained)."""

    steps: float
    misfit: float


@dataclass(frozen=True)
class SpanResult:
    """Where the span solve ended: coefficients (b, 3), the chain's outputs there (k, 3),
    calls made, and whether it stopped at the span's optimum (``stalled``) rather than
    reaching the tolerance or running out of calls."""

    coefficients: NDArray[np.float64]
    outputs: Points
    calls: int
    stalled: bool


def frequencies(adjacency: sp.csr_matrix, region: NDArray[np.int64], basis: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each field's normalised frequency (b,): its Rayleigh quotient ``phi^T L phi / phi^T D phi``
    on the region's edges (0 for a constant field, at most 2)."""
    inner = adjacency[region][:, region].tocsr()
    degree = np.asarray(inner.sum(axis=1)).ravel()
    rough = np.einsum("ij,ij->j", basis, degree[:, None] * basis - inner @ basis)
    mass = np.einsum("ij,ij->j", basis, degree[:, None] * basis)
    return np.asarray(np.divide(rough, mass, out=np.zeros_like(rough), where=mass > 0), dtype=np.float64)


def gains(freqs: NDArray[np.float64], reach: float) -> NDArray[np.float64]:
    """How much of each field the modelled chain passes: ``(1 - f / 2) ** reach``."""
    return np.asarray(np.clip(1.0 - 0.5 * freqs, 0.0, 1.0) ** reach, dtype=np.float64)


def measure_reach(call: BlackBox, rest: Points, base: Points, idx: NDArray[np.int64], blocks: NDArray[np.float64],
                  basis: NDArray[np.float64], freqs: NDArray[np.float64], diagonal: float) -> Reach:
    """One call: move the sculpted vertices by a small combination of every field (signs from a
    fixed sequence, so the same inputs give the same probe), mapped through the blocks' inverse
    so that the posed move is the combination itself; project the chain's response on the
    fields and fit the reach whose gains explain it best (``REACH_STEP`` grid up to
    ``MAX_REACH``)."""
    b = basis.shape[1]
    signs = np.where(np.sin(np.arange(1, 3 * b + 1, dtype=np.float64) * 2.3999632297286535) >= 0.0, 1.0, -1.0)
    coefficients = signs.reshape(b, 3)
    field = basis @ coefficients
    ok = ~is_singular(blocks, tol.JACOBIAN_RCOND)
    offsets = np.zeros_like(field)
    offsets[ok] = np.linalg.solve(blocks[ok], field[ok][:, :, None])[:, :, 0]
    size = float(np.abs(offsets).max())
    if not size > 0 or not np.isfinite(size):
        return Reach(0.0, 1.0)
    scale = PROBE_RTOL * diagonal / size
    moved = rest.copy()
    moved[idx] += scale * offsets
    response = (call(moved)[idx] - base[idx]) / scale
    if not np.all(np.isfinite(response)):
        return Reach(0.0, 1.0)
    measured = basis.T @ response  # (b, 3): each field's share of the response, per posed axis
    total = float(np.sum(measured**2))
    best = (0.0, np.inf)
    for steps in np.arange(0.0, MAX_REACH + REACH_STEP / 2, REACH_STEP):
        misfit = float(np.sum((measured - gains(freqs, steps)[:, None] * coefficients) ** 2))
        if misfit < best[1]:
            best = (float(steps), misfit)
    return Reach(best[0], float(np.sqrt(best[1] / total)) if total > 0 else 1.0)


class SpanModel:
    """The model's Jacobian on the span, ``C`` (3b, 3k): row ``3j + a`` is ``g_j * B (phi_j e_a)``,
    raveled, plus the rank-one corrections of Broyden's updates (``update``). It is applied,
    never formed: at 100k a formed ``C`` is 3b x 3k, 250 MB built in 0.27 s of a 3.1 s example;
    applied, each product costs a few products of the basis with a (k, 3) array."""

    def __init__(self, blocks: NDArray[np.float64], basis: NDArray[np.float64], gain: NDArray[np.float64]) -> None:
        self.blocks, self.basis, self.gain = blocks, basis, gain
        self.steps: list[NDArray[np.float64]] = []  # each update's y / (y . y)
        self.changes: list[NDArray[np.float64]] = []  # and its u

    def apply(self, r: NDArray[np.float64]) -> NDArray[np.float64]:
        """``C @ r`` for a residual ``r`` (3k,): each coefficient's share of it, (3b,)."""
        k = self.basis.shape[0]
        pulled = np.einsum("vca,vc->va", self.blocks, r.reshape(k, 3))
        out = ((self.basis.T @ pulled) * self.gain[:, None]).ravel()
        for step, change in zip(self.steps, self.changes, strict=True):
            out += float(change @ r) * step
        return out

    def respond(self, y: NDArray[np.float64]) -> NDArray[np.float64]:
        """``y @ C`` for coefficients ``y`` (3b,): the modelled change of the outputs, (3k,)."""
        b = self.basis.shape[1]
        field = self.basis @ (y.reshape(b, 3) * self.gain[:, None])
        out = np.einsum("vca,va->vc", self.blocks, field).ravel()
        for step, change in zip(self.steps, self.changes, strict=True):
            out += float(y @ step) * change
        return out

    def update(self, gram: NDArray[np.float64], y: NDArray[np.float64], observed: NDArray[np.float64]) -> None:
        """Broyden's update from a step ``y`` and the change it caused, ``C += y u^T / (y.y)``
        with ``u = observed - C^T y``, and of ``G = C C^T`` with it (in place)."""
        yy = float(y @ y)
        if yy == 0.0:
            return
        u = observed - self.respond(y)
        cu = self.apply(u)
        self.steps.append(y / yy)
        self.changes.append(u)
        _gram_update(gram, y, u, cu)

    def leading(self, fields: int) -> SpanModel:
        """The model on the first ``fields`` fields only (the coarse span), without updates."""
        return SpanModel(self.blocks, self.basis[:, :fields], self.gain[:fields])

    def carry(self, coarse: SpanModel, gram: NDArray[np.float64], coarse_gram: NDArray[np.float64]) -> None:
        """Take over the updates ``coarse`` (``leading``) learned, and ``gram``, this model's
        ``model_gram``, with them: the coarse rows' block is ``coarse_gram``, and the cross
        block gains ``y_i (C_rest u_i)^T / (y_i.y_i)`` per update (the other rows unchanged)."""
        n = 3 * coarse.basis.shape[1]
        rest = SpanModel(self.blocks, self.basis[:, n // 3:], self.gain[n // 3:])
        gram[:n, :n] = coarse_gram
        for step, change in zip(coarse.steps, coarse.changes, strict=True):
            cross = np.outer(step, rest.apply(change))
            gram[:n, n:] += cross
            gram[n:, :n] += cross.T
            padded = np.zeros(3 * self.basis.shape[1])
            padded[:n] = step
            self.steps.append(padded)
            self.changes.append(change)


def model_gram(blocks: NDArray[np.float64], basis: NDArray[np.float64], gain: NDArray[np.float64]) -> NDArray[np.float64]:
    """``C C^T`` for ``C``, ``SpanModel(blocks, basis, gain)``, without forming it: entry
    ``(3i + a, 3j + e)`` is ``g_i g_j sum_v phi_vi phi_vj (B_v^T B_v)_ae``, six weighted
    products of the basis (a third of the flops of ``C @ C.T``)."""
    b = basis.shape[1]
    squares = np.einsum("vba,vbe->vae", blocks, blocks)
    gram = np.empty((3 * b, 3 * b))
    outer = np.outer(gain, gain)
    for a in range(3):
        for e in range(a, 3):
            part = outer * ((basis * squares[:, a, e][:, None]).T @ basis)
            gram[a::3, e::3] = part
            gram[e::3, a::3] = part.T
    return gram


def ridge(blocks: NDArray[np.float64], scale: float = SPAN_RIDGE) -> float:
    """The regularisation's weight: ``scale**2`` (``SPAN_RIDGE``) times the square of the blocks'
    median spectral norm (the chain's gain on a smooth move), in the units of |r|^2 / |D|^2."""
    if not len(blocks) or not np.all(np.isfinite(blocks)):
        return 0.0
    return scale**2 * float(np.median(np.linalg.norm(blocks, ord=2, axis=(1, 2)))) ** 2


def span_solve(call: BlackBox, rest: Points, sculpt: Points, idx: NDArray[np.int64], basis: NDArray[np.float64],
               model: SpanModel, atol: float, regularisation: float, max_calls: int, *,
               start: NDArray[np.float64] | None = None, start_outputs: Points | None = None,
               gram: NDArray[np.float64], believe: bool = False) -> SpanResult:
    """Levenberg-Marquardt over the span (module docstring) on ``|r|^2 + regularisation |D|^2``
    (``ridge``), from coefficients ``start`` whose outputs are ``start_outputs`` (zero and the
    chain at rest when not given); ``model`` is updated in place by each step's secant. At most
    ``max_calls`` calls. ``gram`` is the model's ``C C^T`` (``model_gram``; updated in place too).
    ``believe``: stop, without a call, where a model whose last prediction came true sees no
    more to gain (for a model the reach probe found accurate, ``Reach.misfit`` within
    ``BELIEVE_MISFIT``); any model is believed so within ``BELIEVE_NEAR`` times ``atol`` (RMS)."""
    k, b = basis.shape
    target = sculpt[idx].ravel()
    x = np.zeros(3 * b) if start is None else np.asarray(start, dtype=np.float64).ravel().copy()
    if start_outputs is None:
        moved = rest.copy()
        moved[idx] += basis @ x.reshape(b, 3)
        start_outputs = call(moved)[idx]
        max_calls -= 1
    out = np.asarray(start_outputs, dtype=np.float64).ravel().copy()
    r = target - out
    top = float(np.linalg.eigvalsh(gram)[-1]) if np.all(np.isfinite(gram)) else 0.0
    if not top > 0 or not np.all(np.isfinite(r)):
        return SpanResult(x.reshape(b, 3), out.reshape(k, 3), 0, True)
    floor_damping = regularisation
    damping = max(SPAN_DAMPING * top, floor_damping)
    calls = slow = rejected = 0
    stalled = False
    eye = np.eye(3 * b)
    trusted = False  # the last step's gain ratio was good: the model's prediction can be believed
    while calls < max_calls:
        rhs = model.apply(r) - floor_damping * x
        y = np.asarray(np.linalg.solve(gram + damping * eye, rhs), dtype=np.float64)
        predicted_r = r - model.respond(y)
        rr = float(r @ r)
        near = rr <= k * (BELIEVE_NEAR * atol) ** 2
        if (believe or near) and trusted and float(predicted_r @ predicted_r) >= (1.0 - SPAN_MIN_GAIN) ** 2 * rr:
            stalled = True  # a model that has just predicted well sees nothing left in the span
            break
        trial = x + y
        moved = rest.copy()
        moved[idx] += basis @ trial.reshape(b, 3)
        out_trial = call(moved)[idx].ravel()
        calls += 1
        if not np.all(np.isfinite(out_trial)):
            stalled = True
            break
        model.update(gram, y, out_trial - out)
        r_trial = target - out_trial
        before = float(r @ r) + floor_damping * float(x @ x)
        actual = before - float(r_trial @ r_trial) - floor_damping * float(trial @ trial)
        predicted = before - float(predicted_r @ predicted_r) - floor_damping * float(trial @ trial)
        ratio = actual / predicted if predicted > 0 else -1.0
        trusted = abs(ratio - 1.0) <= 1.0 - GOOD_RATIO
        if ratio > 0:
            gain = 1.0 - np.sqrt(float(r_trial @ r_trial) / max(float(r @ r), 1e-300))
            x, out, r = trial, out_trial, r_trial
            rejected = 0
            if np.sqrt(np.max(np.einsum("ij,ij->i", r.reshape(k, 3), r.reshape(k, 3)))) <= atol:
                break
            slow = slow + 1 if gain < SPAN_MIN_GAIN else 0
        else:
            rejected += 1
        if slow >= SPAN_PATIENCE or rejected >= SPAN_PATIENCE:
            stalled = True
            break
        if ratio > GOOD_RATIO:
            damping = max(0.1 * damping, floor_damping)
        elif ratio < POOR_RATIO:
            damping *= 10.0
    return SpanResult(x.reshape(b, 3), out.reshape(k, 3), calls, stalled)


def broyden(cols: NDArray[np.float64], gram: NDArray[np.float64], y: NDArray[np.float64],
             observed: NDArray[np.float64]) -> None:
    """Broyden's update of the model's columns from a step ``y`` and the change it caused,
    ``C += y u^T / (y.y)`` with ``u = observed - C^T y``, row by row (no (3b, 3k) temporary),
    and of ``G = C C^T`` with it."""
    yy = float(y @ y)
    if yy == 0.0:
        return
    u = observed - y @ cols
    cu = cols @ u
    for j in np.nonzero(y)[0]:
        cols[j] += (y[j] / yy) * u
    _gram_update(gram, y, u, cu)


def _gram_update(gram: NDArray[np.float64], y: NDArray[np.float64], u: NDArray[np.float64],
                 cu: NDArray[np.float64]) -> None:
    """``G = C C^T`` after Broyden's ``C += y u^T / (y.y)``, in place (``cu`` is ``C u`` before):
    ``G += (C u y^T + y (C u)^T) / (y.y) + y y^T (u.u) / (y.y)^2``."""
    yy = float(y @ y)
    gram += (np.outer(cu, y) + np.outer(y, cu)) / yy + np.outer(y, y) * (float(u @ u) / yy**2)

