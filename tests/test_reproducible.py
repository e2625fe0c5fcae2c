"""The BLAS kernel pinned before numpy loads (psdbake.reproducible): the coupled inverse's
decisions turn on the last bits of BLAS sums, and OpenBLAS picks its kernel by the CPU, so
without the pin two farm nodes wrote different layers from the same inputs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from psdbake import reproducible

AVX2 = {"avx2", "fma"} <= reproducible._cpu_flags()
PINNED = pytest.mark.skipif(not AVX2 or sys.platform != "linux", reason="the pin applies to x86-64 Linux with AVX2 and FMA")
SHOW = "import psdbake, numpy; from psdbake import reproducible; import json; print(json.dumps(reproducible.describe()))"


def _describe(code: str, **env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "NPY_DISABLE_CPU_FEATURES")}
    out = subprocess.run([sys.executable, "-W", "error", "-c", code], env={**clean, **env}, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout)


@PINNED
def test_importing_psdbake_first_pins_the_haswell_kernel_without_a_warning():
    shown = _describe(SHOW)
    assert shown["blas"] == reproducible.BLAS_CORE and shown["OPENBLAS_CORETYPE"] == reproducible.BLAS_CORE


def test_a_kernel_the_user_chose_is_kept():
    assert _describe(SHOW, OPENBLAS_CORETYPE="Sandybridge")["OPENBLAS_CORETYPE"] == "Sandybridge"


def test_numpy_loaded_before_psdbake_is_left_as_it_is():
    shown = _describe("import numpy; " + SHOW)
    assert shown["OPENBLAS_CORETYPE"] is None and shown["NPY_DISABLE_CPU_FEATURES"] is None


@PINNED
def test_the_test_run_itself_is_pinned():
    """pytest loads psdbake.reproducible as a plugin (pyproject's addopts), before any conftest
    imports numpy: the budgets the tests pin were measured with this kernel."""
    assert reproducible.describe()["blas"] == reproducible.BLAS_CORE
