"""Inverting a chain that couples vertices: LBS + Delta Mush (10 iterations, step 0.5).

Three methods on the same examples, side by side in one run:

* per-vertex: ``inverse.invert_example`` as is (Powell in lockstep, assumes no coupling);
* one-shot: cvShapeInverter's linearisation, a 3x3 Jacobian per vertex from 3 calls moving
  every sculpted vertex together, D = J^-1 r, no iteration (its residual checked here);
* psdbake: ``coupled.invert`` (the smooth start that measures the chain's smoothing, then
  Newton-Krylov: ``psdbake.coupled``).

Tables: the bench rigs (``benchmarks.rigs`` variant ``lbs+deltamush``) at about 1.3k, 3k, 13k
and 100k points, eight examples each (elbow 20-160 degrees), every example and the folded
ones (elbow 60 degrees and more, where LBS folds the inner elbow) in rows of their own; the
real characters (``benchmarks.characters``: CesiumMan and the character fixture) with sculpts
made through the chain from known smooth offsets; and CesiumMan's shipped sculpts, which no
offset reproduces through Delta Mush, against a long-run reference optimiser on the same
objective (``reference``). Every residual is measured here by running the full chain on
rest + offsets. Usage: ``python -m benchmarks.coupled [--sizes 1.3k,3k,13k,100k] [--examples N]
[--no-characters] [--reference-iterations N]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from psdbake import coupled
from psdbake import tolerances as tol
from psdbake.inverse import invert_example, sculpted_vertices
from psdbake.smoothbasis import edge_adjacency
from psdbake.usd.meshrest import rest_mesh

from . import characters, rigs

VARIANT = "lbs+deltamush"
METHODS = ("per-vertex", "one-shot", "coupled")
SIZES = ("1.3k", "3k", "13k", "100k")
#: An example is folded where the elbow bends this far or more (LBS folds the inner elbow).
FOLDED_DEGREES = 60.0
#: The reference optimiser's Gauss-Newton iterations on CesiumMan's shipped sculpts (each a
#: Jacobian by coloured finite differences: 1,159 calls on CesiumMan, whose whole mesh is
#: sculpted).
REFERENCE_ITERATIONS = 40

Box = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def one_shot(box: Box, rest: NDArray[np.float64], sculpt: NDArray[np.float64]
             ) -> tuple[NDArray[np.int64], NDArray[np.float64], int]:
    """cvShapeInverter's method: (sculpted indices, offsets, calls)."""
    base = box(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, sculpt)
    jac = coupled.chain_blocks(box, rest, base, idx, diagonal, floor)  # the same 3 calls psdbake makes
    offsets = np.linalg.solve(jac, (sculpt[idx] - base[idx])[:, :, None])[:, :, 0]
    return idx, offsets, 4


def run_method(method: str, box: Box, rest: NDArray[np.float64], sculpt: NDArray[np.float64], adjacency
               ) -> tuple[NDArray[np.int64], NDArray[np.float64], int, float]:
    """(sculpted indices, offsets, calls, seconds) of one method on one example."""
    started = time.perf_counter()
    if method == "one-shot":
        idx, offsets, calls = one_shot(box, rest, sculpt)
    else:
        res = (invert_example(box, rest, sculpt) if method == "per-vertex" else
               coupled.invert(box, rest, sculpt, neighbours=lambda: adjacency))
        idx, offsets, calls = res.indices, res.offsets, res.evaluations
    return idx, offsets, calls, time.perf_counter() - started


def residuals(check: Box, rest: NDArray[np.float64], sculpt: NDArray[np.float64], idx: NDArray[np.int64],
              offsets: NDArray[np.float64]) -> tuple[NDArray[np.float64], float, float]:
    """(residual per sculpted vertex, atol, diagonal), by running the full chain on rest + offsets."""
    base = check(rest)
    diagonal, floor, _ = sculpted_vertices(rest, base, sculpt)
    moved = rest.copy()
    moved[idx] += offsets
    return np.linalg.norm(sculpt[idx] - check(moved)[idx], axis=1), max(tol.INVERSE_RTOL * diagonal, floor), diagonal


class Tally:
    """Sums over examples for one table row."""

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.seconds = self.worst = 0.0
        self.missed = self.sculpted = 0

    def add(self, calls: int, seconds: float, residual: NDArray[np.float64], atol: float, diagonal: float) -> None:
        self.calls.append(calls)
        self.seconds += seconds
        self.worst = max(self.worst, float(residual.max(initial=0.0)) / diagonal)
        self.missed += int(np.count_nonzero(residual > atol))
        self.sculpted += len(residual)

    def row(self, label: str, count: str, method: str) -> str:
        n = max(len(self.calls), 1)
        spread = f"{min(self.calls)}-{max(self.calls)}" if self.calls else "-"
        return (f"{label:<28} {count:>8} {method:<11} {sum(self.calls) / n:>9.1f} {spread:>9} {self.seconds / n:>8.2f} "
                f"{self.worst:>13.2e} {f'{self.missed} / {self.sculpted}':>18}")


HEADER = (f"{'rig':<28} {'examples':>8} {'method':<11} {'calls/ex':>9} {'range':>9} {'s/ex':>8} {'max res/diag':>13} "
          f"{'missed / sculpted':>18}")


def bench_rig(rig: rigs.Rig, times: Sequence[float], poses: dict, methods: Sequence[str]) -> None:
    """Every method on every example of one rig: a row for all, one for the folded ones."""
    scene = rig.scene()
    adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
    folded = [t for t in times if poses[t]["Elbow"][1] >= FOLDED_DEGREES]
    for method in methods:
        every, bent = Tally(), Tally()
        for t in times:
            idx, offsets, calls, seconds = run_method(method, rig.blackbox(scene, t), rig.rest, rig.sculpts[t], adjacency)
            residual, atol, diagonal = residuals(rig.blackbox(scene, t), rig.rest, rig.sculpts[t], idx, offsets)
            for tally in (every, bent) if t in folded else (every,):
                tally.add(calls, seconds, residual, atol, diagonal)
        print(every.row(rig.name, str(len(times)), method), flush=True)
        if folded and len(folded) < len(times):
            print(bent.row(f"{rig.name} folded", str(len(folded)), method), flush=True)


def bench_cases(label: str, cases: Sequence[characters.Case], methods: Sequence[str]) -> None:
    """Every method on a set of character examples (one row per method)."""
    for method in methods:
        tally = Tally()
        for case in cases:
            idx, offsets, calls, seconds = run_method(method, case.box, case.rest, case.sculpt, case.adjacency)
            residual, atol, diagonal = residuals(case.box, case.rest, case.sculpt, idx, offsets)
            tally.add(calls, seconds, residual, atol, diagonal)
        print(tally.row(label, str(len(cases)), method), flush=True)


def reference(case: characters.Case, iterations: int) -> tuple[float, int, float]:
    """A long-run reference optimiser on psdbake's objective, ``|r|^2 + ridge |D|^2`` over the
    sculpted vertices (``smoothstart.ridge`` of the chain's own blocks): scipy's trust-region
    least squares (``least_squares(method="trf")``) from zero, its Jacobian by finite
    differences over Delta Mush's reach, coloured (``jac_sparsity``: one call per colour).
    Only the chain is called, as psdbake does. Returns (RMS residual / diagonal, calls, seconds)."""
    from psdbake import smoothstart

    started = time.perf_counter()
    base = case.box(case.rest)
    diagonal, floor, idx = sculpted_vertices(case.rest, base, case.sculpt)
    blocks = coupled.chain_blocks(case.box, case.rest, base, idx, diagonal, floor)
    weight = np.sqrt(smoothstart.ridge(blocks))
    pattern = characters.reach_pattern(case.adjacency, idx, characters.DELTA_MUSH_RINGS)
    k = len(idx)
    augmented = pattern.tolil()
    augmented.resize((6 * k, 3 * k))
    augmented.setdiag(1.0, k=-3 * k)
    target = case.sculpt[idx].ravel()
    calls = [4]

    def misfit(x: NDArray[np.float64]) -> NDArray[np.float64]:
        calls[0] += 1
        moved = case.rest.copy()
        moved[idx] += x.reshape(k, 3)
        return np.concatenate([case.box(moved)[idx].ravel() - target, weight * x]) / diagonal

    with threadpool_limits(limits=1, user_api="blas"):
        found = least_squares(misfit, np.zeros(3 * k), jac_sparsity=augmented.tocsr(), method="trf", tr_solver="lsmr",
                              x_scale="jac", max_nfev=iterations, diff_step=1e-4)
    r = found.fun[: 3 * k].reshape(k, 3)
    return float(np.sqrt(np.mean(np.sum(r**2, axis=1)))), calls[0], time.perf_counter() - started


def bench_shipped(iterations: int) -> None:
    """psdbake against the reference optimiser on CesiumMan's shipped sculpts."""
    print(f"{'example':<24} {'psdbake calls':>13} {'rms/diag':>10} {'max/diag':>10} {'at optimum':>10} {'unreachable':>11} "
          f"{'reference calls':>15} {'rms/diag':>10} {'ratio':>7}")
    for case in characters.cesium(shipped=True):
        res = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda case=case: case.adjacency)
        residual, _, diagonal = residuals(case.box, case.rest, case.sculpt, res.indices, res.offsets)
        rms = float(np.sqrt(np.mean(residual**2))) / diagonal
        ref_rms, ref_calls, _ = reference(case, iterations) if iterations > 0 else (float("nan"), 0, 0.0)
        optimum, unreachable = getattr(res, "at_optimum", "-"), getattr(res, "unreachable_fraction", float("nan"))
        print(f"{case.name:<24} {res.evaluations:>13} {rms:>10.3e} {float(residual.max()) / diagonal:>10.2e} "
              f"{optimum!s:>10} {unreachable:>11.1%} {ref_calls:>15} {ref_rms:>10.3e} {rms / ref_rms:>7.3f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(SIZES), help="comma-separated, of: " + ", ".join(rigs.SIZES))
    parser.add_argument("--examples", type=int, default=8, help="examples per rig (of 8)")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated, of: " + ", ".join(METHODS))
    parser.add_argument("--no-characters", action="store_true", help="skip CesiumMan and the character fixture")
    parser.add_argument("--reference-iterations", type=int, default=REFERENCE_ITERATIONS,
                        help="the reference optimiser's iterations on CesiumMan's shipped sculpts (0: skip it)")
    args = parser.parse_args()
    methods = tuple(m for m in args.methods.split(",") if m)
    sizes = tuple(s for s in args.sizes.split(",") if s)
    if not set(methods) <= set(METHODS):
        parser.error(f"--methods: unknown {sorted(set(methods) - set(METHODS))}")
    if not set(sizes) <= set(rigs.SIZES):
        parser.error(f"--sizes: unknown {sorted(set(sizes) - set(rigs.SIZES))}")
    print(f"# {VARIANT}: per-vertex vs one-shot vs coupled inverse (residuals by running the chain)")
    print(HEADER)
    with tempfile.TemporaryDirectory() as folder:
        poses_layer, poses = rigs.write_poses(folder)
        for size in sizes:
            rig = rigs.build(folder, VARIANT, size, poses, poses_layer)
            bench_rig(rig, rig.times[: args.examples], poses, methods)
        if not args.no_characters:
            bench_cases("CesiumMan", characters.cesium(), methods)
            bench_cases("character", characters.whole_character(folder), methods)
    if not args.no_characters:
        print(f"# CesiumMan's shipped sculpts (made on the plain-skinned mesh) through {VARIANT}")
        bench_shipped(args.reference_iterations)


if __name__ == "__main__":
    main()
