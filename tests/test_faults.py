"""Faults: killed during start-up, mid-write or mid-rename (each moment reached for sure, not
guessed by a delay), a full disk, two writers at once. Outputs are either the old file or
the complete new one, never a partial one, and no temporary file is left."""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
import time

import pytest
from conftest import ROOT, fixture

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
OLD = b"#usda 1.0\n(\n    doc = \"an older CORRECTIVES layer\"\n)\n"


PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")  # the console script


def _cmd(out, *extra) -> list[str]:
    """fit into out; --force: the old files these tests plant are stand-ins, not psdbake's outputs."""
    return [PSDBAKE, "fit", ASSET, EXAMPLES, "-o", str(out), "-q", "--force", *extra]


def _no_temps(folder) -> None:
    left = [f for f in os.listdir(folder) if ".tmp" in f]
    assert not left, f"temporary files left behind: {left}"


@pytest.fixture(scope="module")
def complete(tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("ref") / "corr.usda"
    subprocess.run(_cmd(out), check=True, cwd=ROOT)
    return out.read_bytes()


# --- killed at a known moment, not after a guessed delay ----------------------------------
#
# The run is held at the moment under test (psdbake's own commit hook, PSDBAKE_PAUSE_AT, or an
# import hook during start-up), the test checks that it is there (the marker file exists, and
# what is on disk at that moment), then signals it.

def _temps(folder) -> list:
    return sorted(p for p in folder.iterdir() if ".tmp" in p.name)


#: ``python -c`` start-up that holds psdbake when it first imports USD: during the command's
#: start-up (``psdbake._entry`` has installed its signal handlers, ``psdbake.cli`` is loading),
#: before any option is parsed or output planned. argv: MARKER, then psdbake's arguments.
_PAUSE_IN_START_UP = """
import os, sys, time
marker = sys.argv.pop(1)

class PauseAtUsdImport:
    def find_spec(self, name, path=None, target=None):
        if name == "pxr":
            sys.meta_path.remove(self)
            open(marker, "w").close()
            deadline = time.monotonic() + 30.0
            while os.path.exists(marker) and time.monotonic() < deadline:
                time.sleep(0.01)
        return None

sys.meta_path.insert(0, PauseAtUsdImport())
sys.argv[0] = "psdbake"
from psdbake._entry import main

main()
"""


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_killed_during_start_up_keeps_the_old_file(sig, tmp_path):
    out = tmp_path / "corr.usda"
    out.write_bytes(OLD)

    def nothing_planned() -> None:
        assert not _temps(tmp_path) and out.read_bytes() == OLD

    argv = [sys.executable, "-c", _PAUSE_IN_START_UP, str(tmp_path / "marker"), *_cmd(out)[1:]]
    done = _run_paused(argv, "start-up", tmp_path / "marker", sig, release=False, at_pause=nothing_planned)
    assert done.returncode == 130, done.stderr
    assert done.stderr.strip() == "psdbake: interrupted"
    assert out.read_bytes() == OLD
    _no_temps(tmp_path)


def _written_not_renamed(tmp_path, out, complete):
    """At the commit moment: the new layer complete in its one temporary file, the old one in place."""

    def check() -> None:
        temps = _temps(tmp_path)
        assert len(temps) == 1, temps
        assert temps[0].read_bytes() == complete, "the temporary file is not the complete layer"
        assert out.read_bytes() == OLD

    return check


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_killed_mid_write_keeps_the_old_file(sig, tmp_path, complete):
    """Killed with the new layer written to its temporary file but not renamed: the run
    unwinds (exit 130, one line), the old file is intact, no temporary is left."""
    out = tmp_path / "corr.usda"
    out.write_bytes(OLD)
    done = _run_paused(_cmd(out), "commit", tmp_path / "marker", sig, release=False,
                       at_pause=_written_not_renamed(tmp_path, out, complete))
    assert done.returncode == 130, done.stderr
    assert done.stderr.strip() == "psdbake: interrupted"
    assert out.read_bytes() == OLD
    _no_temps(tmp_path)


def test_killed_during_the_rename_has_the_complete_file(tmp_path, complete):
    """SIGTERM while the output is renamed is held until the rename is done: the new file,
    complete, and exit 130."""
    out = tmp_path / "corr.usda"
    out.write_bytes(OLD)

    def renamed() -> None:
        assert out.read_bytes() == complete and not _temps(tmp_path)

    done = _run_paused(_cmd(out), "rename", tmp_path / "marker", signal.SIGTERM, release=True, at_pause=renamed)
    assert done.returncode == 130, done.stderr
    assert out.read_bytes() == complete
    _no_temps(tmp_path)


def test_sigkill_mid_write_keeps_the_old_file(tmp_path, complete):
    """SIGKILL cannot be handled: the temporary file stays, the output is untouched."""
    out = tmp_path / "corr.usda"
    out.write_bytes(OLD)
    done = _run_paused(_cmd(out), "commit", tmp_path / "marker", signal.SIGKILL, release=False,
                       at_pause=_written_not_renamed(tmp_path, out, complete))
    assert done.returncode == -signal.SIGKILL
    assert out.read_bytes() == OLD


def _small_file_limit() -> None:
    """A 'full disk' for this process: writes past 4 KiB fail with EFBIG."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))


def test_full_disk_keeps_the_old_file(tmp_path):
    out = tmp_path / "corr.usda"
    out.write_bytes(OLD)
    proc = subprocess.run(_cmd(out), cwd=ROOT, capture_output=True, text=True, preexec_fn=_small_file_limit)
    assert proc.returncode == 6, proc.stderr
    assert (len(proc.stderr.strip().splitlines()) == 1 and "cannot write" in proc.stderr) or "could not write" in proc.stderr
    assert out.read_bytes() == OLD
    _no_temps(tmp_path)


def test_two_writers_never_interleave(tmp_path):
    """Two fits with different settings race to the same path: the result is one of them, whole."""
    out = tmp_path / "corr.usda"
    refs = {}
    for kernel in ("gaussian", "inverse_quadratic"):  # at the same path: the layer records its command line
        subprocess.run(_cmd(out, "--kernel", kernel), check=True, cwd=ROOT)
        refs[kernel] = out.read_bytes()
    for _ in range(3):
        procs = [subprocess.Popen(_cmd(out, "--kernel", k), cwd=ROOT) for k in refs]
        assert all(p.wait(timeout=60) == 0 for p in procs)
        assert out.read_bytes() in refs.values()
    _no_temps(tmp_path)


# --- commands with several outputs: all land or none ---------------------------------------

ANIM = fixture("arm_anim.usda")


def _multi_output(tmp_path, command: str) -> tuple[list[str], list]:
    """(argv, outputs) of a multi-output command, every output already holding an old file."""
    if command == "fit --report":
        outputs = [tmp_path / "corr.usda", tmp_path / "fit.json"]
        argv = _cmd(outputs[0], "--report", str(outputs[1]))
    elif command == "eval --points-cache":
        corr = tmp_path / "in_corr.usda"
        subprocess.run(_cmd(corr), check=True, cwd=ROOT)
        outputs = [tmp_path / "weights.usda", tmp_path / "cache.usda"]
        argv = [PSDBAKE, "eval", ASSET, str(corr), "--anim", ANIM, "-o", str(outputs[0]), "--points-cache",
                str(outputs[1]), "-q", "--frames", "1:12", "--force"]
    else:  # eval --chunk-size: 2 chunk layers, 2 manifests
        corr = tmp_path / "in_corr.usda"
        subprocess.run(_cmd(corr), check=True, cwd=ROOT)
        out = tmp_path / "weights.usda"
        argv = [PSDBAKE, "eval", ASSET, str(corr), "--anim", ANIM, "-o", str(out), "--chunk-size", "6",
                "--frames", "1:12", "-q", "--force"]
        subprocess.run(argv, check=True, cwd=ROOT)  # learn the file names, then make them all "old"
        outputs = sorted(p for p in tmp_path.iterdir() if p.name.startswith("weights"))
    for i, path in enumerate(outputs):
        path.write_bytes(OLD + f"# old output {i}\n".encode())
    return argv, outputs


MULTI = ["fit --report", "eval --points-cache", "eval --chunk-size"]


def _run_paused(argv, moment: str, marker, sig, release: bool, at_pause=None) -> subprocess.CompletedProcess:
    """Run until MOMENT (``commit`` or ``rename``: psdbake's commit hook; ``start-up``: argv
    pauses itself), prove it got there (the marker), check ``at_pause()`` while it waits
    there, signal it, let it go."""
    env = {**os.environ, "PSDBAKE_PAUSE_AT": f"{moment}:{marker}"} if moment in ("commit", "rename") else None
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    try:
        while not os.path.exists(marker):
            assert proc.poll() is None, f"the run ended before the {moment} moment: {proc.stderr.read()}"
            assert time.monotonic() < deadline, f"never reached the {moment} moment"
            time.sleep(0.01)
        if at_pause is not None:
            at_pause()
    except BaseException:
        proc.kill()
        proc.communicate(timeout=60)
        raise
    proc.send_signal(sig)
    if release:
        os.remove(marker)
    _, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(argv, proc.returncode, "", err)


@pytest.mark.parametrize("command", MULTI)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_killed_before_the_commit_keeps_every_old_output(command, sig, tmp_path):
    """Killed with every new output written to its temporary file but none renamed: the
    run unwinds (exit 130, one line), every old output is intact, no temporary is left."""
    argv, outputs = _multi_output(tmp_path, command)
    old = {p: p.read_bytes() for p in outputs}
    done = _run_paused(argv, "commit", tmp_path / "marker", sig, release=False)
    assert done.returncode == 130, done.stderr
    assert done.stderr.strip() == "psdbake: interrupted"
    assert {p: p.read_bytes() for p in outputs} == old
    _no_temps(tmp_path)


@pytest.mark.parametrize("command", MULTI)
def test_killed_between_renames_lands_every_new_output(command, tmp_path):
    """SIGTERM after the first rename is held until the last one: every output is new."""
    argv, outputs = _multi_output(tmp_path, command)
    old = {p: p.read_bytes() for p in outputs}
    done = _run_paused(argv, "rename", tmp_path / "marker", signal.SIGTERM, release=True)
    assert done.returncode == 130, done.stderr
    assert all(p.read_bytes() != old[p] for p in outputs), "some outputs are old, some new"
    _no_temps(tmp_path)


@pytest.mark.parametrize("command", MULTI)
def test_sigkill_before_the_commit_keeps_every_old_output(command, tmp_path):
    """SIGKILL cannot be handled: temporary files may stay, but no output is touched."""
    argv, outputs = _multi_output(tmp_path, command)
    old = {p: p.read_bytes() for p in outputs}
    done = _run_paused(argv, "commit", tmp_path / "marker", signal.SIGKILL, release=False)
    assert done.returncode == -signal.SIGKILL
    assert {p: p.read_bytes() for p in outputs} == old


@pytest.mark.parametrize("command", MULTI)
@pytest.mark.parametrize("which", ["smallest", "largest"])
def test_file_size_limit_keeps_every_old_output(command, which, tmp_path):
    """A 'full disk' (RLIMIT_FSIZE) part-way through the outputs: the limit is set one byte
    under the smallest output (the first write fails) or the largest (the others are written
    first): exit 6, one line saying why, every old output intact, no temporary left."""
    argv, outputs = _multi_output(tmp_path, command)
    subprocess.run(argv, check=True, cwd=ROOT)
    sizes = [p.stat().st_size for p in outputs]
    limit = (min(sizes) if which == "smallest" else max(sizes)) - 1
    for i, path in enumerate(outputs):
        path.write_bytes(OLD + f"# old output {i}\n".encode())
    old = {p: p.read_bytes() for p in outputs}

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, preexec_fn=small_files)
    assert done.returncode == 6, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("psdbake: error:"), done.stderr
    assert "pxrInternal" not in lines[0] and ".cpp" not in lines[0] and ".tmp" not in lines[0], lines[0]
    assert re.search(r"file-size limit", lines[0]), lines[0]
    assert {p: p.read_bytes() for p in outputs} == old
    _no_temps(tmp_path)
