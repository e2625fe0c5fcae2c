"""Inverting a chain that couples vertices: LBS + Delta Mush (10 iterations, step 0.5).

Three methods on the same examples, side by side in one run:

* per-vertex: ``inverse.invert_example`` as is (Powell in lockstep, assumes no coupling);
* one-shot: cvShapeInverter's linearisation, a 3x3 Jacobian per vertex from 3 calls moving
  every sculpted vertex together, D = J^-1 r, no iteration (its residual checked here);
* psdbake: ``coupled.invert`` (the smooth start that measures the chain's smoothing, then
  Newton-Krylov: ``psdbake.solver.coupled``).

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
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares
from threadpoolctl import threadpool_limits

from psdbake import tolerances as tol
from psdbake.solver import coupled
from psdbake.solver.inverse import invert_example, sculpted_vertices
from psdbake.solver.smoothbasis import edge_adjacency
from psdbake.usd.blackbox import ChainSkinning
from psdbake.usd.meshrest import rest_mesh

from . import characters, results, rigs

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
               coupled.invert(box, rest, sculpt, neighbours=lambda: adjacency, skinning=ChainSkinning(box)))
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
    """Sums over examples for one table row, and each example's own figures (the record's raw)."""

    def __init__(self) -> None:
        self.calls: list[int] = []
        self.seconds = self.worst = self.squares = 0.0
        self.missed = self.sculpted = 0
        self.examples: list[dict] = []

    def add(self, name: str, calls: int, seconds: float, residual: NDArray[np.float64], atol: float,
            diagonal: float) -> None:
        self.calls.append(calls)
        self.seconds += seconds
        worst = float(residual.max(initial=0.0)) / diagonal
        self.worst = max(self.worst, worst)
        self.squares += float(np.sum((residual / diagonal) ** 2))
        missed = int(np.count_nonzero(residual > atol))
        self.missed += missed
        self.sculpted += len(residual)
        self.examples.append({"example": name, "calls": calls, "seconds": round(seconds, 3), "missed": missed,
                              "sculpted": len(residual), "max_residual_rel": worst,
                              "rms_residual_rel": float(np.sqrt(np.mean((residual / diagonal) ** 2)))})

    def cells(self) -> list[str]:
        """calls / example (range), s / example, max and RMS residual / diag, vertices above tolerance."""
        n = max(len(self.calls), 1)
        spread = f" ({min(self.calls)}-{max(self.calls)})" if len(set(self.calls)) > 1 else ""
        rms = np.sqrt(self.squares / max(self.sculpted, 1))
        return [f"{sum(self.calls) / n:.1f}{spread}", f"{self.seconds / n:.2f}", f"{self.worst:.2e}", f"{rms:.2e}",
                f"{self.missed:,} of {self.sculpted:,}"]


COLUMNS = ["calls / example (range)", "s / example", "max residual / diag", "RMS residual / diag",
           "vertices above tolerance"]
LABELS = {"per-vertex": "per-vertex (Powell in lockstep)", "one-shot": "one-shot linearisation (cvShapeInverter's method)",
          "coupled": "psdbake"}


def _show(row: Sequence[str]) -> None:
    print(" | ".join(row), flush=True)


def bench_rig(rig: rigs.Rig, times: Sequence[float], poses: dict, methods: Sequence[str], raw: list[dict]
              ) -> list[list[str]]:
    """Every method on every example of one rig: a row for all, one for the folded ones."""
    scene = rig.scene()
    adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
    folded = [t for t in times if poses[t]["Elbow"][1] >= FOLDED_DEGREES]
    rows = []
    for method in methods:
        every, bent = Tally(), Tally()
        for t in times:
            idx, offsets, calls, seconds = run_method(method, rig.blackbox(scene, t), rig.rest, rig.sculpts[t], adjacency)
            residual, atol, diagonal = residuals(rig.blackbox(scene, t), rig.rest, rig.sculpts[t], idx, offsets)
            name = f"{rig.name} elbow {poses[t]['Elbow'][1]:g} deg"
            for tally in (every, bent) if t in folded else (every,):
                tally.add(name, calls, seconds, residual, atol, diagonal)
        rows.append([rig.size, str(len(times)), LABELS[method], *every.cells()])
        _show(rows[-1])
        if folded and len(folded) < len(times):
            rows.append([f"{rig.size} folded", str(len(folded)), LABELS[method], *bent.cells()])
            _show(rows[-1])
        raw.append({"rig": rig.name, "method": method, "examples": every.examples})
    return rows


def bench_cases(label: str, cases: Sequence[characters.Case], methods: Sequence[str], raw: list[dict]
                ) -> list[list[str]]:
    """Every method on a set of character examples (one row per method)."""
    rows = []
    for method in methods:
        tally = Tally()
        for case in cases:
            idx, offsets, calls, seconds = run_method(method, case.box, case.rest, case.sculpt, case.adjacency)
            residual, atol, diagonal = residuals(case.box, case.rest, case.sculpt, idx, offsets)
            tally.add(case.name, calls, seconds, residual, atol, diagonal)
        rows.append([label, str(len(cases)), LABELS[method], *tally.cells()])
        _show(rows[-1])
        raw.append({"rig": label, "method": method, "examples": tally.examples})
    return rows


@dataclass(frozen=True)
class Optimum:
    """Where an optimiser ended on a shipped sculpt, each figure a fraction of the diagonal
    (``objective`` of its square): RMS residual, largest offset, and the objective."""

    rms: float
    largest_offset: float
    objective: float


@dataclass(frozen=True)
class UnreachableObjective:
    """psdbake's objective for a sculpt the chain cannot reproduce, ``|r|^2 + ridge |D|^2`` over
    the sculpted vertices ``idx`` (``smoothstart.ridge`` of the chain's own blocks at
    ``coupled.UNREACHABLE_RIDGE``, as psdbake solves every piece of CesiumMan's shipped
    sculpts); called with offsets (len(idx), 3), it runs the chain on rest + offsets."""

    case: characters.Case
    idx: NDArray[np.int64]
    diagonal: float
    ridge: float

    @staticmethod
    def of(case: characters.Case) -> UnreachableObjective:
        from psdbake.solver import smoothstart

        base = case.box(case.rest)
        diagonal, floor, idx = sculpted_vertices(case.rest, base, case.sculpt)
        blocks = coupled.chain_blocks(case.box, case.rest, base, idx, diagonal, floor)
        return UnreachableObjective(case, idx, diagonal, smoothstart.ridge(blocks, coupled.UNREACHABLE_RIDGE))

    def __call__(self, offsets: NDArray[np.float64]) -> Optimum:
        case = self.case
        moved = case.rest.copy()
        moved[self.idx] += offsets
        r = np.linalg.norm(case.sculpt[self.idx] - case.box(moved)[self.idx], axis=1)
        size = np.linalg.norm(offsets, axis=1)
        return Optimum(float(np.sqrt(np.mean(r**2))) / self.diagonal, float(size.max()) / self.diagonal,
                       float(np.sum(r**2) + self.ridge * np.sum(size**2)) / self.diagonal**2)


def reference(objective: UnreachableObjective, iterations: int) -> tuple[Optimum, int, float]:
    """A long-run reference optimiser on ``objective``: scipy's trust-region least squares
    (``least_squares(method="trf")``) from zero, its Jacobian by finite differences over Delta
    Mush's reach, coloured (``jac_sparsity``: one call per colour). Only the chain is called,
    as psdbake does; its calls include the 4 that measure the objective's ridge. Returns (where
    it ended, calls, seconds)."""
    case, idx, diagonal = objective.case, objective.idx, objective.diagonal
    started = time.perf_counter()
    weight = np.sqrt(objective.ridge)
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
    seconds = time.perf_counter() - started
    return objective(found.x.reshape(k, 3)), calls[0], seconds


def bench_shipped(iterations: int, raw: list[dict]) -> list[list[str]]:
    """psdbake against the reference optimiser on CesiumMan's shipped sculpts."""
    rows = []
    for case in characters.cesium(shipped=True):
        started = time.perf_counter()
        res = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda case=case: case.adjacency,
                             skinning=ChainSkinning(case.box))
        seconds = time.perf_counter() - started
        residual, atol, diagonal = residuals(case.box, case.rest, case.sculpt, res.indices, res.offsets)
        rms = float(np.sqrt(np.mean(residual**2))) / diagonal
        objective = UnreachableObjective.of(case)
        ours = objective(res.offsets)
        ref, ref_calls, ref_seconds = (reference(objective, iterations) if iterations > 0 else
                                       (Optimum(float("nan"), float("nan"), float("nan")), 0, 0.0))
        optimum, unreachable = getattr(res, "at_optimum", None), getattr(res, "unreachable_fraction", None)
        rows.append([case.name.removesuffix(" shipped"), str(res.evaluations), f"{seconds:.1f}", f"{rms:.3e}",
                     f"{float(residual.max()) / diagonal:.2e}",
                     f"{int(np.count_nonzero(residual > atol)):,} of {len(residual):,}", f"{ours.largest_offset:.3f}",
                     "-" if optimum is None else ("yes" if optimum else "no"),
                     "-" if unreachable is None else f"{unreachable:.1%}",
                     f"{ref_calls:,}", f"{ref_seconds:.0f}", f"{ref.rms:.3e}", f"{ref.largest_offset:.3f}",
                     f"{rms / ref.rms:.3f}", f"{ours.objective / ref.objective:.3f}"])
        _show(rows[-1])
        raw.append({"example": case.name, "calls": res.evaluations, "seconds": seconds, "rms_residual_rel": rms,
                    "largest_offset_rel": ours.largest_offset, "objective_rel2": ours.objective,
                    "regime": res.regime, "at_optimum": optimum, "unreachable_fraction": unreachable,
                    "reference_calls": ref_calls, "reference_seconds": ref_seconds, "reference_rms_residual_rel": ref.rms,
                    "reference_largest_offset_rel": ref.largest_offset, "reference_objective_rel2": ref.objective})
    return rows


#: The bench rigs whose plain-skinned sculpts are inverted through the chain (each mesh one piece:
#: 1.3k within stage 4's pieces, 3k and 13k beyond them).
PLAIN_SIZES = ("1.3k", "3k", "13k")


def bench_plain(folder: str, poses: dict, poses_layer: str, sizes: Sequence[str], examples: int, raw: list[dict]
                ) -> list[list[str]]:
    """psdbake on the bench rigs' sculpts made on the plain-skinned (LBS) mesh, as an artist makes
    them, inverted through LBS + Delta Mush: no offset reproduces them. Per rig: calls, seconds,
    RMS residual, the largest offset over the sculpt's largest move, how many examples ended at
    an optimum, and the share of the sculpt not reproduced."""
    rows = []
    for size in sizes:
        chain = rigs.build(folder, VARIANT, size, poses, poses_layer)
        plain = rigs.build(folder, "lbs", size, poses, poses_layer)
        scene, plain_scene = chain.scene(), plain.scene()
        adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
        found = []
        for t in chain.times[:examples]:
            box, sculpt = chain.blackbox(scene, t), plain.sculpts[t]
            move = float(np.linalg.norm(sculpt - plain.blackbox(plain_scene, t)(plain.rest), axis=1).max())
            started = time.perf_counter()
            res = coupled.invert(box, chain.rest, sculpt, neighbours=lambda adjacency=adjacency: adjacency,
                                 skinning=ChainSkinning(box))
            seconds = time.perf_counter() - started
            residual, _, diagonal = residuals(box, chain.rest, sculpt, res.indices, res.offsets)
            found.append({"rig": size, "elbow": poses[t]["Elbow"][1], "calls": res.evaluations, "seconds": seconds,
                          "rms_residual_rel": float(np.sqrt(np.mean(residual**2))) / diagonal,
                          "largest_offset_over_move": float(np.linalg.norm(res.offsets, axis=1).max()) / move,
                          "at_optimum": res.at_optimum, "unreachable_fraction": res.unreachable_fraction,
                          "regime": res.regime})
            print(f"  {size} {found[-1]['elbow']:g}: {res.evaluations} calls, {seconds:.1f} s, RMS "
                  f"{found[-1]['rms_residual_rel']:.2e}, offsets {found[-1]['largest_offset_over_move']:.2f}x, "
                  f"at optimum {res.at_optimum}; {res.regime}", flush=True)
        raw.extend(found)
        calls = [f["calls"] for f in found]
        rms = [f["rms_residual_rel"] for f in found]
        lost = [f["unreachable_fraction"] for f in found]
        rows.append([f"{size} ({len(chain.rest):,} points, one piece)", str(len(found)),
                     f"{np.mean(calls):.1f} ({min(calls)}-{max(calls)})", f"{np.mean([f['seconds'] for f in found]):.2f}",
                     f"{min(rms):.2e}-{max(rms):.2e}", f"{max(f['largest_offset_over_move'] for f in found):.2f}",
                     f"{sum(f['at_optimum'] for f in found)} of {len(found)}", f"{min(lost):.1%}-{max(lost):.1%}"])
        _show(rows[-1])
    return rows


#: Random poses per rig for the robustness table (``bench_random``): elbow 20-160 degrees and
#: wrist -60-60, from a fixed seed, so the same poses every run.
RANDOM_POSES = 16
RANDOM_SEED = 7
#: The rigs the robustness table runs on (100k is the bench's own: 8 examples take ~40 s).
RANDOM_SIZES = ("1.3k", "3k", "13k")


def random_poses(count: int = RANDOM_POSES, seed: int = RANDOM_SEED) -> dict[float, dict]:
    """``count`` example poses at times 1..count, elbow and wrist drawn uniformly (0.1 degree)."""
    rng = np.random.default_rng(seed)
    return {float(i + 1): {"Elbow": ((0, 0, 1), float(np.round(rng.uniform(20.0, 160.0), 1))),
                           "Wrist": ((1, 0, 0), float(np.round(rng.uniform(-60.0, 60.0), 1)))} for i in range(count)}


def bench_random(folder: str, sizes: Sequence[str], count: int, raw: list[dict]) -> list[list[str]]:
    """psdbake on the bench rigs at random poses, sculpts made through the chain from the
    bench's known offsets: the bench's eight elbows are a small sample of the poses a fit
    meets. Per rig: calls (mean, median, range), seconds, vertices above the tolerance, and
    each example that misses (its pose, and whether it was called an optimum)."""

    poses = random_poses(count)
    sub = os.path.join(folder, "random")
    os.makedirs(sub, exist_ok=True)
    poses_layer = rigs.generate.write_animation(os.path.join(sub, "poses.usda"), poses)
    rows = []
    for size in sizes:
        rig = rigs.build(sub, VARIANT, size, poses, poses_layer)
        scene = rig.scene()
        adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
        tally, misses = Tally(), []
        for t in rig.times:
            pose = f"elbow {poses[t]['Elbow'][1]:g}, wrist {poses[t]['Wrist'][1]:g}"
            started = time.perf_counter()
            box = rig.blackbox(scene, t)
            res = coupled.invert(box, rig.rest, rig.sculpts[t], neighbours=lambda adjacency=adjacency: adjacency,
                                 skinning=ChainSkinning(box))
            seconds = time.perf_counter() - started
            residual, atol, diagonal = residuals(rig.blackbox(scene, t), rig.rest, rig.sculpts[t], res.indices,
                                                 res.offsets)
            tally.add(f"{rig.name} {pose}", res.evaluations, seconds, residual, atol, diagonal)
            tally.examples[-1].update(regime=res.regime, at_optimum=res.at_optimum)
            missed = int(np.count_nonzero(residual > atol))
            if missed:
                misses.append(f"{pose}: {missed} ({'called an optimum' if res.at_optimum else 'short of an optimum'})")
        calls = tally.cells()
        rows.append([f"{size} ({rig.points:,} points)", str(len(rig.times)), calls[0], f"{np.median(tally.calls):.0f}",
                     calls[1], calls[4], "; ".join(misses) or "none"])
        _show(rows[-1])
        raw.append({"rig": rig.name, "examples": tally.examples})
    return rows


ABOUT = (
    "LBS followed by the reference Delta Mush (10 iterations, step 0.5). The bench rigs (`benchmarks/rigs.py`) at "
    "about 1.3k, 3k, 13k and 100k points, 8 examples each bending the elbow from 20° to 160° with the wrist "
    "(\"folded\": the six at 60° and more, where LBS folds the inner elbow); real characters (`benchmarks/characters.py`: "
    "CesiumMan and the character fixture) with sculpts made through the chain from the fixtures' own smooth rest-space "
    "offsets, so an exact answer exists; and CesiumMan's shipped sculpts, made on the plain-skinned mesh, which no "
    "offset reproduces through Delta Mush, against a long-run reference optimiser on the same objective. Three "
    "methods side by side in one run: the per-vertex solver (Powell in lockstep, which assumes no coupling), the "
    "one-shot linearisation (cvShapeInverter's method: a 3x3 Jacobian per vertex from 3 calls, no iteration) and "
    "psdbake. Every residual is measured by running the chain on rest + offsets. How the stages were chosen: "
    "[decisions/coupled-inverse.md](decisions/coupled-inverse.md) and "
    "[decisions/coupled-inverse-coarse-meshes.md](decisions/coupled-inverse-coarse-meshes.md)."
)
SHIPPED_ABOUT = (
    "The reference optimiser minimises psdbake's objective for what the chain cannot reproduce, |r|² + ridge |D|² "
    "over the sculpted vertices (the ridge at `coupled.UNREACHABLE_RIDGE`, as psdbake uses on every piece of these "
    "sculpts), with "
    "scipy's `least_squares(method=\"trf\")` from zero, its Jacobian by finite differences over Delta Mush's 12-edge "
    "reach, coloured (one call per colour); like psdbake it only calls the chain. \"Not reproduced\" is what the "
    "summary reports: the RMS residual over the RMS of the sculpt's own displacement."
)

RANDOM_ABOUT = (
    f"The bench rigs at {RANDOM_POSES} random poses (`benchmarks.coupled.random_poses`: elbow 20-160°, wrist -60-60°, seed "
    f"{RANDOM_SEED}), each sculpt made through LBS + Delta Mush from the bench's own offsets, so an exact answer exists. "
    "An example that misses is listed with its pose; one \"called an optimum\" ended where no nearby offset reproduces "
    "more (a local optimum: the truth is elsewhere)."
)
PLAIN_ABOUT = (
    "Each example's sculpt made on the rig's plain LBS mesh (the `lbs` rig's sculpts), as an artist makes it, "
    "inverted through LBS + Delta Mush: no offset reproduces it. Each mesh is one piece: the 1.3k rig's (1,312 "
    "vertices) is solved on its exact Jacobian (stage 4, at most 1,666 vertices) and ends at the regularised "
    "optimum; the 3k and 13k rigs' are beyond it, and where their offsets exceed what the unreachable ridge lets "
    "through the out-of-reach stage bounds them, without an optimum claimed. \"Not reproduced\" is what the "
    "summary reports."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(SIZES), help="comma-separated, of: " + ", ".join(rigs.SIZES))
    parser.add_argument("--examples", type=int, default=8, help="examples per rig (of 8)")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated, of: " + ", ".join(METHODS))
    parser.add_argument("--no-characters", action="store_true", help="skip CesiumMan and the character fixture")
    parser.add_argument("--reference-iterations", type=int, default=REFERENCE_ITERATIONS,
                        help="the reference optimiser's iterations on CesiumMan's shipped sculpts (0: skip it)")
    parser.add_argument("--no-plain", action="store_true", help="skip the rigs' plain-skinned sculpts")
    parser.add_argument("--random", type=int, default=RANDOM_POSES, help="random poses per rig for the robustness "
                        "table (0: skip it)")
    parser.add_argument("--json", default=results.path_of("coupled"), help="where to write the results record")
    args = parser.parse_args(argv)
    methods = tuple(m for m in args.methods.split(",") if m)
    sizes = tuple(s for s in args.sizes.split(",") if s)
    if not set(methods) <= set(METHODS):
        parser.error(f"--methods: unknown {sorted(set(methods) - set(METHODS))}")
    if not set(sizes) <= set(rigs.SIZES):
        parser.error(f"--sizes: unknown {sorted(set(sizes) - set(rigs.SIZES))}")
    print(f"# {VARIANT}: per-vertex vs one-shot vs coupled inverse (residuals by running the chain)")
    rig_rows: list[list[str]] = []
    character_rows: list[list[str]] = []
    raw: dict[str, list[dict]] = {"rigs": [], "characters": [], "shipped": [], "plain": [], "random": []}
    plain_rows: list[list[str]] = []
    random_rows: list[list[str]] = []
    with tempfile.TemporaryDirectory() as folder:
        poses_layer, poses = rigs.write_poses(folder)
        for size in sizes:
            rig = rigs.build(folder, VARIANT, size, poses, poses_layer)
            rig_rows += bench_rig(rig, rig.times[: args.examples], poses, methods, raw["rigs"])
        if not args.no_characters:
            character_rows += bench_cases("CesiumMan (3,273 points, 2 examples)", characters.cesium(), methods,
                                          raw["characters"])
            character_rows += bench_cases("character fixture (3 tubes + sleeve, 8 examples)",
                                          characters.whole_character(folder), methods, raw["characters"])
        if args.random > 0:
            print(f"# the bench rigs at {args.random} random poses, through {VARIANT}")
            random_rows = bench_random(folder, [s for s in RANDOM_SIZES if s in sizes], args.random, raw["random"])
        if not args.no_plain:
            print(f"# the bench rigs' sculpts made on the plain-skinned mesh, through {VARIANT}")
            plain_rows = bench_plain(folder, poses, poses_layer, [s for s in PLAIN_SIZES if s in sizes],
                                     args.examples, raw["plain"])
    tables = [results.table("The bench rigs: LBS + Delta Mush", ["rig", "examples", "method", *COLUMNS], rig_rows)]
    if not args.no_characters:
        tables.append(results.table("Real characters, sculpts made through the chain", ["character", "examples", "method",
                                                                                        *COLUMNS], character_rows))
        print(f"# CesiumMan's shipped sculpts (made on the plain-skinned mesh) through {VARIANT}")
        shipped = bench_shipped(args.reference_iterations, raw["shipped"])
        tables.append(results.table(
            "CesiumMan's shipped sculpts against a reference optimiser",
            ["example", "psdbake calls", "s", "RMS residual / diag", "max residual / diag", "vertices above tolerance",
             "largest offset / diag", "at optimum", "not reproduced", "reference calls", "reference s",
             "reference RMS / diag", "reference largest offset / diag", "RMS ratio (psdbake / reference)",
             "objective ratio"], shipped,
            notes=SHIPPED_ABOUT))
    if random_rows:
        tables.append(results.table(
            "The bench rigs at random poses", ["rig", "examples", "calls / example (range)", "median calls", "s / example",
                                              "vertices above tolerance", "examples that miss"],
            random_rows, notes=RANDOM_ABOUT))
    if plain_rows:
        tables.append(results.table(
            "The bench rigs' sculpts made on the plain-skinned mesh", ["rig", "examples", "calls / example (range)",
                                                                      "s / example", "RMS residual / diag",
                                                                      "largest offset / sculpt's largest move",
                                                                      "at optimum", "not reproduced"],
            plain_rows, notes=PLAIN_ABOUT))
    results.write("coupled", argv, ABOUT, tables, raw=raw, path=args.json)


if __name__ == "__main__":
    main()
