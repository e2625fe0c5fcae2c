"""``psdbake batch --workers N``: jobs at once on the local pool, and identical outputs.

A jobs file of fits of one rig (each with its own kernel, so each is a real job) and evals with
a points cache over a shot, run with ``--workers 1`` and ``--workers <cores>``; prints the wall
time of each and checks the output layers byte for byte. This is what chose the default.

Run: ``python -m benchmarks.batch [--size 13k] [--fits 4] [--evals 4]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from benchmarks import results, rigs

KERNELS = ("gaussian", "inverse_quadratic", "inverse_multiquadric", "thin_plate_spline", "cubic", "linear")


def jobs_text(rig: rigs.Rig, shot: str, fits: int, evals: int) -> str:
    lines = [f'[defaults]\nasset = "{rig.asset}"\n']
    for k in range(fits):
        lines.append(f'[[fit]]\nexamples = ["{rig.examples}"]\nkernel = "{KERNELS[k % len(KERNELS)]}"\n'
                     f'output = "out/c{k}.usdc"\n')
    for k in range(evals):
        lines.append(f'[[eval]]\ncorrectives = "out/c{k % fits}.usdc"\nanim = "{shot}"\noutput = "out/w{k}.usdc"\n'
                     f'points_cache = "out/p{k}.usdc"\n')
    return "\n".join(lines)


def run_batch(folder: str, text: str, workers: int) -> tuple[float, dict[str, bytes]]:
    os.makedirs(folder)
    with open(os.path.join(folder, "jobs.toml"), "w") as fh:
        fh.write(text)
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    started = time.perf_counter()
    subprocess.run([exe, "batch", os.path.join(folder, "jobs.toml"), "--workers", str(workers), "-q"], check=True)
    seconds = time.perf_counter() - started
    out = os.path.join(folder, "out")
    files = {}
    for name in sorted(os.listdir(out)):
        with open(os.path.join(out, name), "rb") as fh:
            files[name] = fh.read()
    return seconds, files


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="13k", choices=sorted(rigs.SIZES))
    parser.add_argument("--fits", type=int, default=4)
    parser.add_argument("--evals", type=int, default=4)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--json", default=results.path_of("batch"), help="where to write the results record")
    args = parser.parse_args(argv)
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as folder:
        poses_layer, poses = rigs.write_poses(folder)
        rig = rigs.build(folder, "lbs", args.size, poses, poses_layer)
        shot = rigs.write_shot(folder, args.frames)
        text = jobs_text(rig, shot, args.fits, args.evals)
        rows, outputs = [], []
        for workers in sorted({1, cores}):
            seconds, files = run_batch(os.path.join(folder, f"w{workers}"), text, workers)
            rows.append((workers, seconds))
            outputs.append(files)
    print(f"batch of {args.fits} fits + {args.evals} evals ({args.frames} frames, points cache), lbs {args.size} "
          f"({rig.points:,} points), {cores} cores:")
    print(f"  {'--workers':>9} {'seconds':>8} {'speed-up':>9}")
    for workers, seconds in rows:
        print(f"  {workers:>9} {seconds:>8.2f} {rows[0][1] / seconds:>8.2f}x")
    identical = all(o == outputs[0] for o in outputs)
    print(f"  outputs byte-identical across --workers: {'yes' if identical else 'NO'}")
    about = (f"`psdbake batch` of {args.fits} fits (each with its own kernel) and {args.evals} evals with a points cache "
             f"over a {args.frames}-frame shot, lbs {args.size} bench rig, with `--workers 1` and `--workers <cores>`; "
             "the output layers compared byte for byte. This is what chose the default.")
    table = results.table(f"`batch --workers`: {args.fits} fits + {args.evals} evals, {args.size}",
                          ["--workers", "seconds", "speed-up"],
                          [[str(w), f"{s:.2f}", f"{rows[0][1] / s:.2f}x"] for w, s in rows],
                          f"Outputs byte-identical across --workers: {'yes' if identical else 'NO'}.")
    results.write("batch", argv, about, [table], raw={"rows": rows, "identical": identical}, path=args.json)
    if not identical:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
