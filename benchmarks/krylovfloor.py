"""How many measured directions the linear problem alone needs: the floor under the coupled
inverse's calls on the real characters.

For each sculpt made through LBS + Delta Mush from known offsets (``benchmarks.characters``:
the character fixture's eight examples and CesiumMan's two), the chain's Jacobian on the
sculpted vertices is measured *at the answer* (central differences, 2 calls a column, calls
the solver never gets), and GMRES, right-preconditioned by the per-vertex blocks as the
solver's Krylov stages are, solves the linear problem ``J D = J D_true`` from zero. The
products it needs until every vertex's linear residual is within the fit's tolerance are what
a Krylov method measuring one direction a call spends on the linearised problem alone, with
the exact Jacobian: no nonlinearity, no noise. The answer's smooth fields are counted too: the
fewest of the region's smoothest fields (``psdbake.solver.smoothbasis``) in whose span the
least-squares fit on the exact Jacobian is within the tolerance, 3 unknowns a field.

Beside them, psdbake's own calls on the same example (``coupled.invert``, given the chain's
skinning as ``fit`` gives it), which include the per-vertex solver's first 5 calls; the
skinning's blocks are read from those calls (``ChainSkinning``).

Run: ``python -m benchmarks.krylovfloor [--no-cesium]`` (``make bench``; CesiumMan's two
Jacobians take about 16k calls each).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from numpy.typing import NDArray

from psdbake import tolerances as tol
from psdbake.solver import coupled, pieces
from psdbake.solver.inverse import sculpted_vertices
from psdbake.solver.smoothbasis import smooth_basis
from psdbake.usd.blackbox import ChainSkinning

from . import characters, results

#: Central-difference step, a fraction of the diagonal (float32 outputs: ~1e-7 of it is noise).
STEP_RTOL = 1e-5
#: GMRES products at most (beyond it the example is reported as "> MAX_PRODUCTS").
MAX_PRODUCTS = 600
#: Smooth-field counts tried, smallest first.
FIELDS = (4, 8, 16, 32, 48, 64, 96, 128, 192, 256)

ABOUT = (
    "The floor under the coupled inverse's calls on the real characters: for each sculpt made through LBS + Delta "
    "Mush from known offsets, the chain's Jacobian on the sculpted vertices measured at the answer (central "
    "differences), then GMRES right-preconditioned by the per-vertex blocks (as psdbake's Krylov stages are) on "
    "the linear problem J D = J D_true from zero. Its products, until every vertex is within the fit's tolerance, "
    "are what one measured direction a call spends on the linearised problem alone, with the exact Jacobian; "
    "beside them psdbake's calls on the nonlinear problem, and the fewest of the region's smoothest fields whose "
    "span holds the answer within the tolerance (3 unknowns a field).")


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def jacobian(case: characters.Case, idx: NDArray[np.int64], at: NDArray[np.float64], step: float
             ) -> NDArray[np.float64]:
    """d outputs[idx] / d offsets[idx] at ``rest + at`` (3k, 3k), by central differences."""
    k = len(idx)
    columns = np.empty((3 * k, 3 * k))
    moved = case.rest.copy()
    moved[idx] += at
    for j in range(3 * k):
        v, a = divmod(j, 3)
        value = moved[idx[v], a]
        moved[idx[v], a] = value + step
        plus = case.box(moved)[idx]
        moved[idx[v], a] = value - step
        minus = case.box(moved)[idx]
        moved[idx[v], a] = value
        columns[:, j] = ((plus - minus) / (2 * step)).ravel()
    return columns


def gmres_products(jac: NDArray[np.float64], blocks_inverse: NDArray[np.float64], b: NDArray[np.float64],
                   atol: float) -> int | None:
    """Products the solver's own GMRES (``coupled._gmres``, right-preconditioned by the blocks)
    takes on ``jac x = b`` from zero until every vertex's residual is within ``atol``; None where
    it stops short of that (``MAX_PRODUCTS``, or its Krylov space exhausted)."""
    k = len(b) // 3
    directions, images = coupled._gmres(lambda z: (jac @ z.ravel()).reshape(k, 3),
                                        lambda v: np.einsum("kab,kb->ka", blocks_inverse, v),
                                        b.reshape(k, 3), atol, MAX_PRODUCTS)
    y = np.linalg.lstsq(images.T, b, rcond=None)[0]
    return len(directions) if np.linalg.norm((b - y @ images).reshape(k, 3), axis=1).max() <= atol else None


def per_piece_products(case: characters.Case, idx: NDArray[np.int64], jac: NDArray[np.float64],
                       blocks_inverse: NDArray[np.float64], b: NDArray[np.float64], atol: float) -> int | None:
    """The most products GMRES takes on any one piece of the mesh (connected component) alone:
    Delta Mush couples no piece to another, so the Jacobian is block-diagonal by piece, and
    ``pieces_krylov`` measures one product of every piece a call. None where any piece misses."""
    most = 0
    for piece in pieces.small_pieces(case.adjacency, idx, case.adjacency.shape[0]):
        rows = (3 * piece.positions[:, None] + np.arange(3)).ravel()
        found = gmres_products(jac[np.ix_(rows, rows)], blocks_inverse[piece.positions], b[rows], atol)
        if found is None:
            return None
        most = max(most, found)
    return most


def fields_needed(case: characters.Case, idx: NDArray[np.int64], jac: NDArray[np.float64],
                  truth: NDArray[np.float64], atol: float) -> int | None:
    """The fewest of ``FIELDS`` smoothest fields whose span, fitted by least squares on ``jac``,
    leaves every vertex within ``atol``; None where none does."""
    b = jac @ truth.ravel()
    for count in FIELDS:
        if count > len(idx):
            break
        basis = smooth_basis(case.adjacency, idx, count)
        if basis is None:
            return None
        span = jac @ np.kron(basis, np.eye(3))
        y = np.linalg.lstsq(span, b, rcond=None)[0]
        if np.linalg.norm((b - span @ y).reshape(-1, 3), axis=1).max() <= atol:
            return count
    return None


def measure(case: characters.Case) -> dict:
    """The floor and psdbake's calls for one example."""
    assert case.offsets is not None
    started = time.perf_counter()
    res = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda: case.adjacency,
                         skinning=ChainSkinning(case.box))  # as ``fit`` calls it
    base = case.box(case.rest)
    diagonal, floor, idx = sculpted_vertices(case.rest, base, case.sculpt)
    atol = max(tol.INVERSE_RTOL * diagonal, floor)
    truth = case.offsets[idx]
    jac = jacobian(case, idx, truth, STEP_RTOL * diagonal)
    blocks = row_sums(jac, len(idx))
    b = jac @ truth.ravel()
    products = gmres_products(jac, np.linalg.inv(blocks), b, atol)
    per_piece = per_piece_products(case, idx, jac, np.linalg.inv(blocks), b, atol)
    fields = fields_needed(case, idx, jac, truth, atol)
    row = {"example": case.name, "vertices": len(idx), "psdbake_calls": res.evaluations,
           "psdbake_missed": len(res.missed), "gmres_products": products,
           "gmres_products_per_piece": per_piece, "fields": fields,
           "seconds": time.perf_counter() - started}
    log(f"{case.name}: {row}")
    return row


def row_sums(jac: NDArray[np.float64], k: int) -> NDArray[np.float64]:
    """The per-vertex 3x3 blocks the solver measures (3 calls moving every sculpted vertex along
    x, y, z): the row sums of the Jacobian's 3x3 tiles, (k, 3, 3)."""
    return jac.reshape(k, 3, k, 3).sum(axis=2)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-cesium", action="store_true", help="the character fixture only")
    parser.add_argument("--json", default=results.path_of("krylovfloor"), help="where to write the results record")
    args = parser.parse_args(argv)
    cases = characters.whole_character() + ([] if args.no_cesium else characters.cesium())
    rows = [measure(case) for case in cases]
    cells = [[r["example"], f"{r['vertices']:,}", f"{r['psdbake_calls']:,}",
              str(r["gmres_products"]) if r["gmres_products"] is not None else f"> {MAX_PRODUCTS}",
              str(r["gmres_products_per_piece"]) if r["gmres_products_per_piece"] is not None
              else f"> {MAX_PRODUCTS}",
              str(r["fields"]) if r["fields"] is not None else f"> {FIELDS[-1]}"] for r in rows]
    for c in cells:
        print(" | ".join(c))
    table = results.table(
        "The linear problem's floor: measured directions with the exact Jacobian",
        ["example", "sculpted vertices", "psdbake calls", "GMRES products, exact Jacobian at the answer",
         "the most on one piece alone",
         "smooth fields the answer needs"], cells,
        notes="GMRES products: right-preconditioned by the per-vertex blocks, from zero, until every vertex of "
              "the linear problem is within the fit's tolerance (1e-6 of the diagonal); on one piece alone: the most any "
              "connected piece of the mesh needs with its own rows and columns of the Jacobian (Delta Mush couples "
              "no piece to another, and psdbake's last Krylov stage measures one product of every piece a call). "
              "psdbake's calls (given the chain's skinning, as fit gives it) include its 5 first calls and, where "
              "it fits the structured model, the skinning's blocks, read from those first calls (no call of their own); it is "
              "not given the exact Jacobian.")
    results.write("krylovfloor", argv, ABOUT, [table], raw=rows, path=args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
