"""Mutation fuzzer: psdbake fit and eval on mutated fixture layers.

Each case takes the small good asset, examples and animation from ``fixtures/bad/``, applies
a few random mutations to one of them as text — a number replaced (NaN, inf, 1e30, 0,
negative, huge integer), a type name changed, an array element dropped or duplicated, a
time-sample key moved, a line deleted or duplicated, the file truncated — and runs
``psdbake fit`` and, when that succeeds, ``psdbake eval --points-cache``. The only allowed
outcomes are success with finite output or a clean psdbake refusal (one ``psdbake:
error:`` line, exit code 3-6). An internal error (exit 1), a traceback, a hang (> 60 s)
or a non-finite number in an output is a failure.

Cases are numbered and seeded: ``python -m tests.fuzz --cases 20000 --seed 0`` (``make
fuzz``) and ``--only N`` replays case N. ``tests/test_fuzz.py`` runs a bounded number in
``make test``.
"""

from __future__ import annotations

import argparse
import io
import os
import re
import signal
import sys
import tempfile
import threading
import time
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BAD = os.path.join(ROOT, "fixtures", "bad")
SOURCES = {
    "asset": os.path.join(BAD, "good_asset.usda"),
    "examples": os.path.join(BAD, "good_examples.usda"),
    "anim": os.path.join(ROOT, "fixtures", "arm_anim.usda"),
}
CLEAN_EXITS = {3, 4, 5, 6}
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:e[-+]?\d+)?(?![\w.])")
TYPES = ["float3[]", "point3f[]", "int[]", "float[]", "quatf[]", "half3[]", "token[]", "double[]", "matrix4d[]",
         "string", "bool", "vector3f[]"]
CASE_SECONDS = 60


@dataclass(frozen=True)
class Outcome:
    case: int
    target: str
    ok: bool
    what: str


def mutate(text: str, rng: np.random.Generator) -> str:
    """1-3 random edits of a usda text."""
    for _ in range(int(rng.integers(1, 4))):
        kind = rng.integers(0, 8)
        lines = text.split("\n")
        if kind == 0:  # a number replaced
            spans = [m.span() for m in NUMBER.finditer(text)]
            if spans:
                a, b = spans[int(rng.integers(len(spans)))]
                value = rng.choice(["nan", "inf", "-inf", "1e30", "0", "-1", "-0.5", "3", "99999999999", "1e-30", "7"])
                text = text[:a] + str(value) + text[b:]
        elif kind == 1:  # a type name changed
            found = [t for t in TYPES if t in text]
            if found:
                old = str(rng.choice(found))
                text = text.replace(old, str(rng.choice(TYPES)), 1)
        elif kind == 2:  # an array element dropped
            idx = [m.start() for m in re.finditer(r", \(", text)]
            if idx:
                a = idx[int(rng.integers(len(idx)))]
                b = text.find(")", a + 3)
                text = text[:a] + text[b + 1:] if b > a else text
        elif kind == 3:  # an array element duplicated
            m = list(re.finditer(r"\([^()]*\)", text))
            if m:
                pick = m[int(rng.integers(len(m)))]
                text = text[:pick.end()] + ", " + pick.group(0) + text[pick.end():]
        elif kind == 4:  # a time-sample key moved
            keys = list(re.finditer(r"^(\s*)(-?\d+(?:\.\d+)?): ", text, flags=re.M))
            if keys:
                k = keys[int(rng.integers(len(keys)))]
                new = str(rng.choice(["1", "2", "3", "-5", "1.5", "1000000"]))
                text = text[:k.start(2)] + new + text[k.end(2):]
        elif kind == 5 and len(lines) > 3:  # a line deleted
            del lines[int(rng.integers(len(lines)))]
            text = "\n".join(lines)
        elif kind == 6 and len(lines) > 3:  # a line duplicated
            i = int(rng.integers(len(lines)))
            lines.insert(i, lines[i])
            text = "\n".join(lines)
        elif kind == 7:  # truncated
            text = text[: int(rng.integers(len(text) // 2, len(text)))]
    return text


class _TimeoutError(Exception):
    pass


def _alarm(signum, frame):
    raise _TimeoutError


def _hung(case: int, seed: int) -> None:
    print(f"FAIL case {case} (seed {seed}): hang inside native code; replay with --only {case} --seed {seed}",
          flush=True)
    os._exit(2)


def _run(argv: list[str]) -> tuple[int, str]:
    from psdbake.cli import main

    err, out = io.StringIO(), io.StringIO()
    code = 0
    with redirect_stderr(err), redirect_stdout(out):
        try:
            main(argv)
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, err.getvalue()


def _finite_layer(path: str) -> bool:
    """Every number written in a usda output is finite."""
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    return not re.search(r"(?<![\w])(nan|inf)(?![\w])", text, flags=re.I)


def _judge(code: int, err: str, outputs: list[str]) -> tuple[bool, str]:
    if "Traceback" in err:
        return False, "traceback: " + err.strip().splitlines()[-1]
    if code == 0:
        bad = [p for p in outputs if os.path.exists(p) and not _finite_layer(p)]
        return (not bad), ("non-finite numbers in " + ", ".join(bad)) if bad else "ok"
    if code in CLEAN_EXITS:
        lines = [ln for ln in err.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("psdbake: error:")]
        if len(errors) != 1 or len(lines) != 1:
            return False, f"exit {code} with {len(lines)} stderr lines: {err.strip()[:300]}"
        leftovers = [p for p in outputs if os.path.exists(p)]
        return (not leftovers), "refused" if not leftovers else f"refused but wrote {leftovers}"
    return False, f"exit {code}: {err.strip()[:300]}"


def run_case(case: int, seed: int, folder: str) -> Outcome:
    rng = np.random.default_rng([seed, case])
    target = str(rng.choice(sorted(SOURCES)))
    paths = dict(SOURCES)
    with open(SOURCES[target], encoding="utf-8") as fh:
        mutated = mutate(fh.read(), rng)
    paths[target] = os.path.join(folder, f"case{case}_{target}.usda")
    with open(paths[target], "w", encoding="utf-8") as fh:
        fh.write(mutated)
    corr, weights, cache = (os.path.join(folder, f"case{case}_{k}.usda") for k in ("corr", "weights", "cache"))
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(CASE_SECONDS)
    # A hang inside C++ never returns to Python for the alarm: a watchdog ends the run.
    watchdog = threading.Timer(CASE_SECONDS + 10, _hung, args=(case, seed))
    watchdog.daemon = True
    watchdog.start()
    try:
        code, err = _run(["fit", paths["asset"], paths["examples"], "-o", corr, "-q", "-j", "1"])
        ok, what = _judge(code, err, [corr])
        if ok and code == 0:
            code, err = _run(["eval", paths["asset"], corr, "--anim", paths["anim"], "-o", weights,
                              "--points-cache", cache, "-q"])
            ok, what = _judge(code, err, [weights, cache])
            what = "eval " + what
        else:
            what = "fit " + what
    except _TimeoutError:
        ok, what = False, f"hang: more than {CASE_SECONDS} s"
    finally:
        signal.alarm(0)
        watchdog.cancel()
    for p in (paths[target], corr, weights, cache):
        if os.path.exists(p) and p != SOURCES.get(target):
            os.remove(p)
    return Outcome(case, target, ok, what)


def run(cases: int, seed: int = 0, only: int | None = None, progress: bool = False) -> list[Outcome]:
    outcomes = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        todo = [only] if only is not None else range(cases)
        trace = bool(os.environ.get("PSDBAKE_FUZZ_TRACE"))
        for n, case in enumerate(todo, start=1):
            if trace:
                print(f"case {case}", file=sys.stderr, flush=True)
            outcomes.append(run_case(case, seed, folder))
            if progress and n % 500 == 0:
                bad = sum(not o.ok for o in outcomes)
                rate = n / (time.perf_counter() - started)
                print(f"  {n} cases, {bad} failures, {rate:.0f} cases/s", file=sys.stderr, flush=True)
    return outcomes


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", type=int, default=None, help="replay one case")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    outcomes = run(args.cases, args.seed, args.only, progress=True)
    failures = [o for o in outcomes if not o.ok]
    kinds: dict[str, int] = {}
    for o in outcomes:
        key = o.what.split(":")[0] if o.ok else "FAIL"
        kinds[key] = kinds.get(key, 0) + 1
    for f in failures[:50]:
        print(f"FAIL case {f.case} ({f.target}): {f.what}")
    seconds = time.perf_counter() - started
    print(f"fuzz: {len(outcomes)} cases tried (seed {args.seed}), {len(failures)} failures, "
          f"{seconds:.0f} s; outcomes: " + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
