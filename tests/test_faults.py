"""Faults: killed at any moment, a full disk, two writers at once. Outputs are either the
old file or the complete new one, never a partial one, and no temporary file is left."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time

import pytest
from conftest import ROOT, fixture

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
OLD = b"#usda 1.0\n(\n    doc = \"an older CORRECTIVES layer\"\n)\n"


PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")  # the console script


def _cmd(out, *extra) -> list[str]:
    return [PSDBAKE, "fit", ASSET, EXAMPLES, "-o", str(out), "-q", *extra]


def _no_temps(folder) -> None:
    left = [f for f in os.listdir(folder) if ".tmp" in f]
    assert not left, f"temporary files left behind: {left}"


@pytest.fixture(scope="module")
def complete(tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("ref") / "corr.usda"
    subprocess.run(_cmd(out), check=True, cwd=ROOT)
    return out.read_bytes()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_killed_at_any_moment_leaves_old_or_complete_file(sig, tmp_path, complete):
    # Delays spread over the whole run (start-up ~0.6 s here, fit + write ~0.1 s). The first
    # ~0.05 s are the interpreter's own start-up, before any psdbake code can handle a signal.
    for delay in (0.1, 0.3, 0.55, 0.65, 0.75, 0.9, 1.2):
        out = tmp_path / "corr.usda"
        out.write_bytes(OLD)
        proc = subprocess.Popen(_cmd(out), cwd=ROOT, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
        assert "Traceback" not in err
        # killed after the rename, the run exits non-zero with the new file complete: fine
        assert out.read_bytes() in (OLD, complete), f"partial output after a kill at {delay} s"
        _no_temps(tmp_path)


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
    for kernel in ("gaussian", "inverse_quadratic"):
        ref = tmp_path / f"ref_{kernel}.usda"
        subprocess.run(_cmd(ref, "--kernel", kernel), check=True, cwd=ROOT)
        refs[kernel] = ref.read_bytes()
    for _ in range(3):
        procs = [subprocess.Popen(_cmd(out, "--kernel", k), cwd=ROOT) for k in refs]
        assert all(p.wait(timeout=60) == 0 for p in procs)
        assert out.read_bytes() in refs.values()
    _no_temps(tmp_path)
