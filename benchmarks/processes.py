"""Measurements in a fresh Python process: a module's ``child`` function, and its peak memory.

A benchmark that times imports, compares two psdbake trees or reads a process's peak resident
memory needs each measurement in a process of its own: ``in_child`` runs
``benchmarks.<module>.child(*args)`` there and returns the JSON object the child printed last.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Mapping, Sequence
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def peak_rss_mib() -> float:
    """This process's peak resident memory so far (``VmHWM``), MiB; NaN where /proc has none."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def in_child(module: str, args: Sequence[str], *, env: Mapping[str, str] | None = None, cwd: str = ROOT
             ) -> dict[str, Any]:
    """``benchmarks.<module>.child(*args)`` in a new interpreter: the last line it printed, as JSON."""
    code = f"import sys, benchmarks.{module} as m; m.child(*sys.argv[1:])"
    proc = subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=None if env is None else dict(env),
                          capture_output=True, text=True, check=False)
    if proc.returncode:
        raise RuntimeError(proc.stderr[-2000:])
    return json.loads(proc.stdout.strip().splitlines()[-1])
