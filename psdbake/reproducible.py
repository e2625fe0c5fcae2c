"""The same bytes on every x86-64 machine: OpenBLAS's kernel and numpy's widest loops pinned.

The coupled inverse is an iterative solve whose decisions (a step kept, a vertex above the
tolerance) turn on the last bits of BLAS sums, and OpenBLAS picks its kernels by the CPU it
finds: measured on the 1.3k bench rig's 80 degree elbow through LBS + Delta Mush, the Haswell
kernel (AVX2) took 128 calls, Sandybridge's (AVX) 151, and the machine the budget tests were
first measured on 113, each with every vertex within the tolerance but other offsets, so other
bytes. A farm of mixed nodes
then wrote different layers from the same inputs. Pinned to the Haswell kernel (AVX2 and FMA,
on every x86-64 server since 2013) and numpy's loops to at most x86-64-v3 (its AVX-512 loops
for exp, sin and the like round differently), every such machine computes the same sums.

This must run before numpy loads, so ``psdbake/__init__.py`` calls it first. It only sets
defaults: an ``OPENBLAS_CORETYPE`` or ``NPY_DISABLE_CPU_FEATURES`` already in the environment
is kept (set ``OPENBLAS_CORETYPE=SkylakeX`` for AVX-512 speed on a farm of such machines
alone), and where numpy was imported before psdbake, or the CPU lacks AVX2 and FMA, or it is
not x86-64 Linux, nothing changes. ``describe()`` says what is in force (``fit --report``).
The variables are inherited by the processes psdbake starts (its ``--jobs`` workers), as they
must be for those to agree.
"""

from __future__ import annotations

import os
import platform
import sys

#: OpenBLAS's kernel for every x86-64 CPU with AVX2 and FMA (Intel from Haswell, AMD from Zen).
BLAS_CORE = "Haswell"
#: numpy's dispatched loops beyond x86-64-v3 (AVX-512), by the names of numpy 2.4 and later. A
#: name numpy does not dispatch makes its import warn (numpy 1.26 dispatches AVX512F ... by older
#: names and no X86_V4), so older numpys are left as they are.
NUMPY_WIDEST = "X86_V4 AVX512_ICL AVX512_SPR"
NUMPY_NAMES_SINCE = (2, 4)


def _cpu_flags() -> set[str]:
    """The CPU's feature flags from /proc/cpuinfo (empty where it cannot be read)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            for line in info:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split())
    except OSError:
        pass
    return set()


def pin() -> bool:
    """Set the kernel defaults where they can still take effect; whether they were set."""
    if "numpy" in sys.modules or sys.platform != "linux" or platform.machine() != "x86_64":
        return False
    if not {"avx2", "fma"} <= _cpu_flags():
        return False
    os.environ.setdefault("OPENBLAS_CORETYPE", BLAS_CORE)
    if _numpy_version() >= NUMPY_NAMES_SINCE:
        os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", NUMPY_WIDEST)
    return True


def _numpy_version() -> tuple[int, ...]:
    """numpy's (major, minor) from its installed metadata, without importing it ((0,) if unknown)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return tuple(int(part) for part in version("numpy").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return (0,)


def describe() -> dict[str, str | None]:
    """What the numerics run on, for a report: BLAS kernels in use (threadpoolctl's
    ``architecture``), and the pin's variables as the process sees them."""
    import numpy  # noqa: F401  (its BLAS loaded, so that threadpoolctl sees it)
    from threadpoolctl import threadpool_info

    kernels = sorted({str(i.get("architecture")) for i in threadpool_info() if i.get("user_api") == "blas"})
    return {"blas": ", ".join(kernels) or None, "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE"),
            "NPY_DISABLE_CPU_FEATURES": os.environ.get("NPY_DISABLE_CPU_FEATURES")}
