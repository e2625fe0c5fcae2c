"""Start-up loads only what the command runs (issue 16): properties, never wall-clock times.

``psdbake --help`` and option parsing import click and psdbake's light modules, not numpy,
SciPy or USD; ``eval`` never imports SciPy (``scipy.spatial`` cost ~0.3 s and
``scipy.interpolate``, the fit's, ~0.2 s of every farm chunk). Each check runs in a fresh
interpreter, since this one has long loaded everything. ``python -m benchmarks.startup``
measures the times.
"""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest
from conftest import ROOT, fixture

from psdbake import names
from psdbake.cli import cli
from psdbake.model import posespace
from psdbake.model import rbf as rbf_model
from psdbake.usd import write as usdwrite

HEAVY = ("numpy", "scipy", "pxr")

#: Prints the heavy top-level packages loaded by the time argv's command has run through
#: click's CliRunner (the CLI as a library sees it: no signal handling, no USD trap).
_AFTER_CLI_RUNNER = """
import json, sys
from click.testing import CliRunner
import psdbake.cli
result = CliRunner().invoke(psdbake.cli.cli, sys.argv[1:])
loaded = sorted({m.split(".")[0] for m in sys.modules} & {"numpy", "scipy", "pxr"})
print(json.dumps({"exit": result.exit_code, "loaded": loaded, "output": result.output[:200]}))
"""

#: Runs argv through ``psdbake.cli.main`` (as the ``psdbake`` command does) and prints the
#: exit code and the SciPy modules loaded by then.
_AFTER_MAIN = """
import json, sys
from psdbake.cli import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"exit": code, "scipy": sorted(m for m in sys.modules if m.split(".")[0] == "scipy")}))
"""


def _fresh(script: str, *argv: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True, cwd=ROOT, check=False)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["eval", "--help"], ["fit", "--help"],
                                  ["batch", "--help"], ["fit", "--kernel", "nope", "a.usda", "b.usda"]],
                         ids=lambda a: " ".join(a))
def test_help_and_option_parsing_load_no_numerics_and_no_usd(argv):
    done = _fresh(_AFTER_CLI_RUNNER, *argv)
    assert done["exit"] == (2 if "nope" in argv else 0), done["output"]
    assert done["loaded"] == [], f"psdbake {' '.join(argv)} loaded {done['loaded']}"


def test_importing_the_cli_loads_no_numerics_and_no_usd():
    code = "import sys, psdbake.cli; print(sorted({m.split('.')[0] for m in sys.modules} & {'numpy', 'scipy', 'pxr'}))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]"


@pytest.mark.slow
def test_eval_loads_no_scipy(run, tmp_path):
    """eval evaluates the stored formula with numpy (pose space: ``psdbake.model.quaternions``,
    distances: ``rbf_model.distances``); SciPy's interpolation and spatial modules are the fit's."""
    corr = tmp_path / "correctives.usda"
    assert run("fit", fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), "-o", corr, "-q")[0] == 0
    done = _fresh(_AFTER_MAIN, "eval", fixture("arm_lbs.usda"), str(corr), "--anim", fixture("arm_anim.usda"),
                  "-o", str(tmp_path / "weights.usda"), "--points-cache", str(tmp_path / "cache.usda"), "-q")
    assert done["exit"] == 0
    assert not [m for m in done["scipy"] if m.startswith("scipy.interpolate")], "eval imported scipy.interpolate"
    assert done["scipy"] == [], f"eval imported {done['scipy'][:5]} ..."


def _choices(command: str, option: str) -> list[str]:
    param = next(p for p in cli.commands[command].params if p.name == option)
    assert isinstance(param.type, click.Choice)
    return list(param.type.choices)


def test_the_cli_offers_exactly_the_registries_names():
    """The light names the CLI reads (``psdbake.names``) are the keys of the registries that give
    them meaning, so no choice lacks an implementation and no implementation lacks a choice."""
    assert _choices("fit", "pose_space") == list(posespace.POSE_SPACES)
    assert sorted(_choices("fit", "kernel")) == sorted(rbf_model.KERNELS)
    assert names.LAYER_FORMATS == tuple(usdwrite.FORMATS)
