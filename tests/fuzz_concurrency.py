"""The fuzzer's concurrency mode (``python -m tests.fuzz --mode concurrency``): two psdbake
processes writing one output, interleaved at random.

Each case takes a family of writers of one output and a starting state of it, two writers of
that family (the same one twice is allowed), a random set of commit moments at which each is
held (``tests/pausing.py``: ``lock``, ``locked``, ``commit``, ``rename``), whether the second
starts at once or once the first is held, and then releases held runs in a random order until
both have ended: a run is released only when the other is held, waiting for a lock
(``/proc/locks``) or done, so every case is a real interleaving of the two commits.

- ``correctives`` (the humanoid; ``c.usda``): ``fit --group Neck``, ``fit --group L_Knee``, a
  plain ``fit --driver L_Elbow --driver L_Knee``, ``mirror`` in place and ``groups --remove
  L_Elbow`` in place, over a layer holding a ``--group`` fit's group or a plain fit's;
- ``eval`` (the arm; ``w.usda``, ``c.usda`` and chunk files): ``eval --points-cache`` of two
  shots (the same animation through two CORRECTIVES), ``eval`` without a cache, and the two
  chunks of each shot (``--chunk-size 6`` over frames 1..12), over nothing, shot A complete, or
  A's first chunk only.

The only accepted outcome: the exit codes and every file of the folder (byte for byte, no
temporary left) are those of the two runs one after the other, in one order or the other
(``reference``, computed once per worker by running them so); a refusal (exit 2-7) is one
``psdbake: error:`` line; nothing else on stderr but psdbake warnings. A deadlock (both runs
waiting for a lock) or a hang is a failure.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
import pausing  # noqa: E402  (tests/pausing.py)

FIXTURES = os.path.join(ROOT, "fixtures")
HUMANOID = os.path.join(FIXTURES, "humanoid", "humanoid.usda")
HUMANOID_EXAMPLES = os.path.join(FIXTURES, "humanoid", "humanoid_examples.usda")
ARM, ARM_EXAMPLES, ARM_ANIM = (os.path.join(FIXTURES, f) for f in ("arm_lbs.usda", "arm_lbs_examples.usda",
                                                                    "arm_anim.usda"))
PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")

Command = Callable[[str, str], list[str]]  # (run folder, shared inputs folder) -> psdbake's arguments


def _fit_group(group: str, driver: str) -> Command:
    return lambda d, s: ["fit", HUMANOID, HUMANOID_EXAMPLES, "--group", group, "--driver", driver, "-o",
                         f"{d}/c.usda", "-q"]


def _plain(kernel: str) -> Command:
    return lambda d, s: ["fit", HUMANOID, HUMANOID_EXAMPLES, "--driver", "L_Elbow", "--driver", "L_Knee", "--kernel",
                         kernel, "-o", f"{d}/c.usda", "-q"]


def _mirror(d: str, s: str) -> list[str]:
    return ["mirror", HUMANOID, f"{d}/c.usda", "--joints", "L_=R_", "-o", f"{d}/c.usda", "-q"]


def _remove(group: str) -> Command:
    return lambda d, s: ["groups", f"{d}/c.usda", "--remove", group, "--asset", HUMANOID, "-q"]


def _eval(shot: str, *extra: str) -> Command:
    return lambda d, s: ["eval", ARM, f"{s}/{shot}.usda", "--anim", ARM_ANIM, "-o", f"{d}/w.usda", "--frames", "1:12",
                         "-q", *[f"{d}/c.usda" if e == "CACHE" else e for e in extra]]


#: family -> (writers by name, starting states by name: the commands that make them)
FAMILIES: dict[str, tuple[dict[str, Command], dict[str, list[Command]]]] = {
    "correctives": (
        {"fit_neck": _fit_group("Neck", "Neck"), "fit_knee": _fit_group("L_Knee", "L_Knee"),
         "plain": _plain("gaussian"), "mirror": _mirror, "remove_elbow": _remove("L_Elbow")},
        {"group": [_fit_group("L_Elbow", "L_Elbow")], "plain": [_plain("inverse_quadratic")]},
    ),
    "eval": (
        {"cache_a": _eval("a", "--points-cache", "CACHE"), "cache_b": _eval("b", "--points-cache", "CACHE"),
         "weights_a": _eval("a"), "chunk_a1": _eval("a", "--chunk-size", "6", "--chunk", "1"),
         "chunk_a2": _eval("a", "--chunk-size", "6", "--chunk", "2"),
         "chunk_b1": _eval("b", "--chunk-size", "6", "--chunk", "1"),
         "chunk_b2": _eval("b", "--chunk-size", "6", "--chunk", "2")},
        {"none": [], "a_complete": [_eval("a", "--chunk-size", "6")],
         "a_half": [_eval("a", "--chunk-size", "6", "--chunk", "1")]},
    ),
}
FAMILY_NAMES = tuple(sorted(FAMILIES))


def _shared(root: str) -> str:
    """The eval family's two CORRECTIVES of the arm (shots a and b: two kernels), made once for
    every worker (each makes them in a folder of its own at the same depth and renames it into
    place; a worker that finds it there already drops its own)."""
    shared = os.path.join(root, "shared")
    if not os.path.isdir(shared):
        mine = f"{shared}.{os.getpid()}"
        os.makedirs(mine, exist_ok=True)
        for shot, kernel in (("a", "gaussian"), ("b", "inverse_quadratic")):
            subprocess.run([PSDBAKE, "fit", ARM, ARM_EXAMPLES, "--kernel", kernel, "-o", os.path.join(mine, f"{shot}.usda"),
                            "-q"], check=True)
        try:
            os.rename(mine, shared)
        except OSError:  # another worker's is there
            shutil.rmtree(mine, ignore_errors=True)
    return shared


def files(folder: str) -> dict[str, str]:
    """SHA-256 of every file under folder by relative path, markers (dot files) left out; a
    temporary file left behind is listed under its own name, so it never matches."""
    found = {}
    for here, _, names in os.walk(folder):
        for n in names:
            if n.startswith(".") and ".tmp" not in n:
                continue
            with open(os.path.join(here, n), "rb") as fh:
                found[os.path.relpath(os.path.join(here, n), folder)] = hashlib.sha256(fh.read()).hexdigest()
    return dict(sorted(found.items()))


def _fill(run: str, family: str, state: str, shared: str) -> None:
    os.makedirs(run)
    for command in FAMILIES[family][1][state]:
        subprocess.run([PSDBAKE, *command(run, shared)], check=True, stdout=subprocess.DEVNULL)


def reference(root: str, family: str, state: str, order: tuple[str, str]) -> dict:
    """{"codes": [...], "files": {...}} of the writers in order, one after the other, from state;
    computed once for every worker of a run (``root/refs/KEY/result.json``), each computing in a
    folder of its own at the same depth as a case's, so every relative path a layer records is
    the same."""
    key = "-".join((family, state, *order))
    path = os.path.join(root, "refs", key, "result.json")
    if os.path.isfile(path):
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    shared = _shared(root)
    mine = os.path.join(root, "refs", f"{key}.{os.getpid()}")
    run = os.path.join(mine, "run")
    shutil.rmtree(mine, ignore_errors=True)
    _fill(run, family, state, shared)
    writers = FAMILIES[family][0]
    codes = [subprocess.run([PSDBAKE, *writers[w](run, shared)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL).returncode for w in order]
    result = {"codes": codes, "files": files(run)}
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(f"{path}.{os.getpid()}", "w", encoding="utf-8") as fh:
        json.dump(result, fh)
    os.replace(f"{path}.{os.getpid()}", path)
    shutil.rmtree(mine, ignore_errors=True)
    return result


class _Writer:
    def __init__(self, run: str, label: str, argv: list[str], moments: list[str]) -> None:
        self.label, self.argv = label, argv
        self.markers = {m: os.path.join(run, f".{label}-{m}") for m in moments}
        self.proc: subprocess.Popen | None = None
        self.err = ""

    def start(self) -> None:
        self.proc = subprocess.Popen(pausing.argv(self.markers, *self.argv), stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)

    def state(self) -> str:
        """not started, done, held, blocked (waiting for a lock) or running."""
        if self.proc is None:
            return "not started"
        if self.proc.poll() is not None:
            return "done"
        if any(os.path.exists(m) for m in self.markers.values()):
            return "held"
        return "blocked" if pausing.waiting_for_lock(self.proc.pid) else "running"

    def release(self) -> str:
        held = [m for m, marker in self.markers.items() if os.path.exists(marker)]
        for m in held:
            os.remove(self.markers[m])
        return f"{self.label}@{','.join(held)}"

    def finish(self) -> int:
        assert self.proc is not None
        _, self.err = self.proc.communicate(timeout=120)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()


def _judge_stderr(code: int, err: str) -> str | None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if "Traceback" in err or "pxrInternal" in err:
        return f"a traceback or C++ names on stderr (exit {code})"
    if code == 0:
        others = [ln for ln in lines if not ln.startswith("psdbake: warning:")]
        return f"exit 0 with other lines on stderr: {others[0]}" if others else None
    errors = [ln for ln in lines if ln.startswith("psdbake: error:")]
    if not 2 <= code <= 7:
        return f"exit {code}: {lines[-1] if lines else 'no message'}"
    if len(errors) != 1 or errors[0] != lines[-1]:
        return f"exit {code} without exactly one error line: {lines[-3:]}"
    return None


def run_case(case: int, rng: np.random.Generator, root: str, report: Callable[[str, object], None]
             ) -> tuple[str, bool, str, list[str], str, str]:
    """One case: (family, ok, what, description, command, stderr)."""
    family = FAMILY_NAMES[int(rng.integers(len(FAMILY_NAMES)))]
    writers, states = FAMILIES[family]
    state = sorted(states)[int(rng.integers(len(states)))]
    names = sorted(writers)
    pair = (names[int(rng.integers(len(names)))], names[int(rng.integers(len(names)))])
    moments = [[m for m in pausing.MOMENTS if rng.random() < 0.5] for _ in pair]
    staggered = bool(rng.random() < 0.5)
    description = [f"{family} from {state}: 1 {pair[0]} held at {moments[0] or 'nothing'}, 2 {pair[1]} held at "
                   f"{moments[1] or 'nothing'}" + (", 2 started once 1 is held or done" if staggered else "")]
    report("target", family)
    report("mutations", description)
    shared = _shared(root)
    run = os.path.join(root, "cases", str(case), "run")
    shutil.rmtree(os.path.dirname(run), ignore_errors=True)
    _fill(run, family, state, shared)
    labels = ("1", "2")
    ws = [_Writer(run, labels[i], writers[pair[i]](run, shared), moments[i]) for i in range(2)]
    command = " & ".join("psdbake " + " ".join(os.path.relpath(a, root) if a.startswith(root) else
                                               os.path.relpath(a, ROOT) if a.startswith(ROOT) else a for a in w.argv)
                         for w in ws)
    report("command", command)
    released: list[str] = []
    try:
        ws[0].start()
        if not staggered:
            ws[1].start()
        while True:
            states_now = [w.state() for w in ws]
            if states_now[1] == "not started" and states_now[0] in ("held", "done", "blocked"):
                ws[1].start()
                continue
            if all(s == "done" for s in states_now):
                break
            if "running" in states_now or "not started" in states_now:
                time.sleep(0.005)
                continue
            held = [w for w, s in zip(ws, states_now, strict=True) if s == "held"]
            if not held:
                return family, False, f"deadlock: both runs wait for a lock ({', '.join(released)})", description, \
                    command, ""
            released.append(held[int(rng.integers(len(held)))].release())
        codes = [w.finish() for w in ws]
    finally:
        for w in ws:
            w.kill()
    description.append("released: " + (", ".join(released) or "none held"))
    stderr = "\n".join(f"[{w.label}] {w.err.strip()}" for w in ws if w.err.strip())
    for w, code in zip(ws, codes, strict=True):
        why = _judge_stderr(code, w.err)
        if why:
            return family, False, f"run {w.label} ({w.argv[0]}): {why}", description, command, stderr
    got = files(run)
    orders = {"1 then 2": (pair, codes), "2 then 1": ((pair[1], pair[0]), codes[::-1])}
    for name, (order, order_codes) in orders.items():
        ref = reference(root, family, state, order)
        if ref["codes"] == order_codes and ref["files"] == got:
            refused = [lab for lab, c in zip(labels if name == "1 then 2" else labels[::-1], order_codes, strict=True)
                       if c]
            shutil.rmtree(os.path.dirname(run), ignore_errors=True)
            return family, True, f"ok: as {name}" + (f", run {' and '.join(refused)} refused" if refused else ""), \
                description, command, stderr
    refs = {name: reference(root, family, state, order) for name, (order, _) in orders.items()}
    diff = sorted({p for r in refs.values() for p in set(r["files"]) ^ set(got)} |
                  {p for r in refs.values() for p in set(r["files"]) & set(got) if r["files"][p] != got[p]})
    return family, False, (f"neither order: exit codes {codes} (serial: " + ", ".join(
        f"{n} {r['codes']}" for n, r in refs.items()) + f"); files differing: {', '.join(diff[:6])}"), description, \
        command, stderr
