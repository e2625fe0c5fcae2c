"""Benchmark results files: one JSON record per benchmark in ``benchmarks/results/``.

Every benchmark of ``make bench`` and ``make fidelity`` ends by writing its record here, and
``python -m benchmarks.pages`` turns the committed records into docs/benchmarks.md and
docs/fidelity.md. A record says when, where and how its figures were measured, so that every
table on those pages carries its date, machine and command:

- ``benchmark``: the module's name (``coupled`` for ``python -m benchmarks.coupled``);
- ``date`` (ISO, the day the run finished), ``machine`` (``cpu_model``, ``cores``, and what
  else is known: memory, library versions, git revision, load) and ``command`` (as typed);
- ``about``: what the benchmark measures, one paragraph of Markdown;
- ``tables``: each with ``title``, ``columns``, ``rows`` (cells as text, formatted by the
  benchmark) and ``notes``; a table may carry its own ``date``, ``machine`` and ``command``
  when it comes from another run than the record's;
- ``raw``: the benchmark's full record, for anyone who wants more than the tables (``None``
  for figures carried over from an earlier README: then ``source`` says from where).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
FOLDER = os.path.join(HERE, "results")

REQUIRED = ("benchmark", "date", "machine", "command", "about", "tables")
TABLE_REQUIRED = ("title", "columns", "rows")
MACHINE_REQUIRED = ("cpu_model", "cores")


def path_of(name: str) -> str:
    """Where benchmark ``name`` writes its record by default."""
    return os.path.join(FOLDER, f"{name}.json")


def command(module: str, argv: Sequence[str] | None) -> str:
    """The command line that ran ``python -m benchmarks.<module>`` with ``argv`` (default: this process's)."""
    args = list(sys.argv[1:] if argv is None else argv)
    return " ".join(["python", "-m", f"benchmarks.{module}", *(shlex.quote(a) for a in args)])


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what platform knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _memory_gib() -> float | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def git_revision() -> str:
    """The short commit of the checkout, +dirty with uncommitted changes to tracked files."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                               text=True, check=True).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict[str, Any]:
    """This machine, as the pages show it: CPU model, cores, memory, versions, load."""
    import numpy
    import scipy
    from pxr import Usd

    import psdbake

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu_model": cpu_model(),
        "cores": cores,
        "memory_gib": _memory_gib(),
        "load_average": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "usd": ".".join(map(str, Usd.GetVersion())).removeprefix("0."),
        "psdbake": psdbake.__version__,
        "git": git_revision(),
    }


def table(title: str, columns: Sequence[str], rows: Sequence[Sequence[Any]], notes: str = "",
          **provenance: Any) -> dict[str, Any]:
    """One table of a record; cells are turned into text here (the benchmark formats numbers)."""
    out: dict[str, Any] = {"title": title, "columns": list(columns), "rows": [[str(c) for c in r] for r in rows],
                           "notes": notes}
    out.update(provenance)
    return out


def check(record: Mapping[str, Any], where: str = "record") -> None:
    """Refuse a record the pages cannot show truthfully: a field missing, a ragged table."""
    missing = [k for k in REQUIRED if not record.get(k)]
    if missing:
        raise ValueError(f"{where}: missing {', '.join(missing)}")
    try:
        datetime.date.fromisoformat(record["date"])
    except (TypeError, ValueError):
        raise ValueError(f"{where}: date {record['date']!r} is not an ISO date (YYYY-MM-DD)") from None
    for i, t in enumerate(record["tables"], 1):
        label = f"{where}: table {i}"
        for k in TABLE_REQUIRED:
            if k not in t:
                raise ValueError(f"{label}: missing {k}")
        for r, row in enumerate(t["rows"], 1):
            if len(row) != len(t["columns"]):
                raise ValueError(f"{label} ({t['title']!r}), row {r}: {len(row)} cells for {len(t['columns'])} columns")
        mach = t.get("machine", record["machine"])
        for k in MACHINE_REQUIRED:
            if not mach.get(k):
                raise ValueError(f"{label}: machine without {k}")
        if "date" in t:
            datetime.date.fromisoformat(t["date"])


def write(name: str, argv: Sequence[str] | None, about: str, tables: Sequence[Mapping[str, Any]],
          raw: Any = None, path: str | None = None) -> str:
    """Write benchmark ``name``'s record (to ``path``, default ``benchmarks/results/<name>.json``)."""
    record = {
        "benchmark": name,
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "command": command(name, argv),
        "about": about,
        "tables": list(tables),
        "raw": raw,
    }
    check(record, name)
    path = path or path_of(name)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(record, f, indent=1, sort_keys=False, default=_plain)
        f.write("\n")
    os.replace(tmp, path)
    print(f"wrote {os.path.relpath(path)}", file=sys.stderr, flush=True)
    return path


def _plain(x: Any) -> Any:
    """numpy scalars and arrays as JSON (non-finite floats as null)."""
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON: {type(x).__name__}")


def load(path: str) -> dict[str, Any]:
    with open(path) as f:
        record = json.load(f)
    check(record, os.path.relpath(path, ROOT))
    return record
