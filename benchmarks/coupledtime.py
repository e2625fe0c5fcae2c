"""The coupled inverse's time at 100k points against the psdbake issue 27 started from.

Issue 27 asks the per-example time of the 100k-point LBS + Delta Mush rig to drop by 30% from
what its tree took (3.13 s an example then, another machine). Seconds from separate runs of a
shared machine move by 10-20%, so both trees are measured here in one run: psdbake's
``psdbake/`` at ``--rev`` (default: 6a46a69, the tree the issue measured), unpacked with ``git
archive``, and this one, on the same numpy, SciPy and USD. The rig, its poses and its sculpts
are made once (``benchmarks.rigs``, variant ``lbs+deltamush``, eight elbows); each measurement
is a fresh process that imports one tree or the other and runs ``coupled.invert`` on every
example, as ``benchmarks.coupled`` does; the two alternate, ``--rounds`` times, so the
machine's load falls on both alike. Each child checks its answers by running the chain on
rest + offsets, so a faster tree that stopped short would show.

Run: ``python -m benchmarks.coupledtime [--rev REV] [--rounds N] [--size 100k]`` (part of ``make bench``;
needs the repository's git history).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time

import numpy as np

from . import against, processes, results, rigs

BEFORE = "6a46a69"  # the tree issue 27 measured (3.13 s an example at 100k)
SIZE = "100k"
VARIANT = "lbs+deltamush"
ROUNDS = 2


def child(folder: str, asset: str, poses_layer: str) -> None:
    """In a fresh process: every example's seconds, calls and worst residual over its atol."""
    from psdbake.deformers import load_deformers
    from psdbake.solver import coupled
    from psdbake.solver.smoothbasis import edge_adjacency
    from psdbake.usd.blackbox import SkinningBlackBox
    from psdbake.usd.meshrest import rest_mesh
    from psdbake.usd.read import Scene

    from . import coupled as bench  # its residuals: the chain run on rest + offsets

    scene = Scene([poses_layer, asset], label=poses_layer)
    chain = load_deformers([rigs.DELTA_MUSH_SPEC])
    rest = scene.rest_points(rigs.MESH)
    adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
    with open(os.path.join(folder, "times.json")) as fh:
        times = json.load(fh)
    out = []
    for t in times:
        sculpt = np.load(os.path.join(folder, f"sculpt_{t:g}.npy"))
        started = time.perf_counter()
        res = coupled.invert(SkinningBlackBox(scene, rigs.MESH, t, chain), rest, sculpt, neighbours=lambda: adjacency)
        seconds = time.perf_counter() - started
        residual, atol, _ = bench.residuals(SkinningBlackBox(scene, rigs.MESH, t, chain), rest, sculpt, res.indices,
                                            res.offsets)
        out.append({"time": t, "seconds": seconds, "calls": res.evaluations,
                    "worst_over_atol": float(residual.max(initial=0.0)) / atol})
    print(json.dumps({"examples": out, "psdbake": os.path.dirname(coupled.__file__)}))


def measure(path: str, folder: str, rig: rigs.Rig) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([path, against.ROOT]))  # psdbake from path
    return processes.in_child("coupledtime", [folder, rig.asset, rig.poses_layer], env=env, cwd=folder)


ABOUT = (
    "The coupled inverse (`coupled.invert`) on the 100k-point LBS + Delta Mush bench rig's eight elbows, this psdbake "
    "against the tree issue 27 measured (its `psdbake/` at a git revision, on the same libraries), side by side: fresh "
    "processes alternating between the two, every example in each. Seconds an example are the mean over the eight "
    "elbows; the worst residual is each tree's answer run through the chain, over the fit tolerance."
)


def _summary(runs: list[dict]) -> dict:
    seconds = [statistics.fmean(e["seconds"] for e in run["examples"]) for run in runs]
    examples = [e for run in runs for e in run["examples"]]
    return {"seconds": seconds, "mean": statistics.fmean(seconds),
            "calls": statistics.fmean(e["calls"] for e in runs[0]["examples"]),
            "worst": max(e["worst_over_atol"] for e in examples)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", default=BEFORE, help="the earlier psdbake's git revision")
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--size", default=SIZE, choices=sorted(rigs.SIZES), help="the bench rig's size")
    parser.add_argument("--json", default=results.path_of("coupledtime"), help="where to write the results record")
    args = parser.parse_args(argv)
    runs: dict[str, list[dict]] = {"before": [], "now": []}
    with tempfile.TemporaryDirectory() as folder:
        before = against.unpack(args.rev, folder)
        poses_layer, poses = rigs.write_poses(folder)
        rig = rigs.build(folder, VARIANT, args.size, poses, poses_layer)
        with open(os.path.join(folder, "times.json"), "w") as fh:
            json.dump(rig.times, fh)
        for t in rig.times:
            np.save(os.path.join(folder, f"sculpt_{t:g}.npy"), rig.sculpts[t])
        for r in range(args.rounds):
            order = (("before", before), ("now", against.ROOT)) if r % 2 == 0 else (("now", against.ROOT),
                                                                                 ("before", before))
            for name, path in order:
                runs[name].append(measure(path, folder, rig))
                seconds = statistics.fmean(e["seconds"] for e in runs[name][-1]["examples"])
                print(f"round {r + 1} {name}: {seconds:.2f} s an example", flush=True)
    got = {name: _summary(v) for name, v in runs.items()}
    ratio = got["now"]["mean"] / got["before"]["mean"]
    pairs = [n / b for n, b in zip(got["now"]["seconds"], got["before"]["seconds"], strict=True)]
    print(f"now {got['now']['mean']:.2f} s an example against {got['before']['mean']:.2f} s ({ratio:.2f}x; "
          f"rounds {', '.join(f'{p:.2f}' for p in pairs)})")
    rows = [[args.rev, f"{got['before']['mean']:.2f}", ", ".join(f"{s:.2f}" for s in got["before"]["seconds"]),
             f"{got['before']['calls']:.1f}", f"{got['before']['worst']:.3g}", "1.00"],
            ["now", f"{got['now']['mean']:.2f}", ", ".join(f"{s:.2f}" for s in got["now"]["seconds"]),
             f"{got['now']['calls']:.1f}", f"{got['now']['worst']:.3g}",
             f"{ratio:.2f} (rounds {', '.join(f'{p:.2f}' for p in pairs)})"]]
    table = results.table(
        f"The {args.size} rig through LBS + Delta Mush: this psdbake against {args.rev}",
        ["psdbake", "s / example", "each round", "calls / example", "worst residual / tolerance",
         "time against the earlier tree"], rows,
        f"{args.rounds} rounds alternating, eight examples each; the ratio is of the means over every round.")
    results.write("coupledtime", argv, ABOUT, [table], raw={"rev": args.rev, "runs": runs}, path=args.json)


if __name__ == "__main__":
    main()
