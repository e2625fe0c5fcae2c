"""psdbake export-blender without Blender: how the command finds Blender, refuses what it
cannot write, and leaves nothing behind when Blender fails (make interop runs it with bpy).
"""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys

import pytest
from conftest import ROOT, fixture, refused, run_cli


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    """The humanoid fitted with the default options: (asset, correctives, anim)."""
    out = tmp_path_factory.mktemp("export") / "correctives.usda"
    asset = fixture("humanoid", "humanoid.usda")
    code, _, err = run_cli("fit", asset, fixture("humanoid", "humanoid_examples.usda"), "-o", out, "-q")
    assert code == 0, err
    return {"humanoid": (asset, str(out), fixture("humanoid", "humanoid_anim.usda"))}


def failing_blender(folder) -> str:
    """A stand-in that answers ``--version`` as Blender does, then fails running the script
    (as a Blender out of memory would): its last line is what the refusal shows."""
    path = os.path.join(folder, "blender")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write('#!/bin/sh\nif [ "$1" = "--version" ]; then echo "Blender 5.0.1"; exit 0; fi\n'
                 'echo "Error: not enough memory to load the scene" >&2\nexit 1\n')
    os.chmod(path, 0o755)
    return path


def test_a_blender_that_cannot_run_the_script_leaves_nothing(shots, tmp_path):
    """Blender is found, run, fails, and the output is never half there (exit 1: Blender's
    own failure, its last line shown)."""
    asset, correctives, _ = shots["humanoid"]
    out = tmp_path / "rig.blend"
    line = refused(run_cli("export-blender", asset, correctives, "-o", out, "--blender", failing_blender(tmp_path)), 1,
                   says="not enough memory", outputs=[out])
    assert "Blender" in line


def test_a_python_without_bpy_is_refused_before_it_runs(shots, tmp_path):
    """The test suite's own Python (bpy lives in a venv of its own: make interop) is not a
    Blender: bad input (exit 3) naming --blender, not Blender failing (it printed exit 1)."""
    if importlib.util.find_spec("bpy") is not None:
        pytest.skip("this Python has bpy")
    asset, correctives, _ = shots["humanoid"]
    out = tmp_path / "rig.blend"
    refused(run_cli("export-blender", asset, correctives, "-o", out, "--blender", sys.executable), 3,
            names=["--blender"], says="without the bpy module", outputs=[out])


@pytest.mark.parametrize(("args", "code", "says"), [
    (["--blender", "/no/such/blender"], 3, "--blender"),
    (["--blender", os.path.join(ROOT, "README.md")], 3, "--blender"),
])
def test_bad_blender_paths_are_refused(shots, tmp_path, args, code, says):
    asset, correctives, _ = shots["humanoid"]
    out = tmp_path / "rig.blend"
    refused(run_cli("export-blender", asset, correctives, "-o", out, *args), code, says=says, outputs=[out])


def test_outputs_that_cannot_be_a_blend_or_are_inputs_are_refused(shots, tmp_path):
    asset, correctives, _ = shots["humanoid"]
    refused(run_cli("export-blender", asset, correctives, "-o", tmp_path / "rig.usda", "--blender", sys.executable), 6,
            says=".blend", outputs=[tmp_path / "rig.usda"])
    link = tmp_path / "rig.blend"
    os.symlink(correctives, link)
    refused(run_cli("export-blender", asset, correctives, "-o", link, "--blender", sys.executable), 6, says="input")
    assert os.path.islink(link)


def test_correctives_without_psd_data_are_refused(tmp_path):
    out = tmp_path / "rig.blend"
    refused(run_cli("export-blender", fixture("humanoid", "humanoid.usda"), fixture("humanoid", "humanoid_anim.usda"),
                    "-o", out, "--blender", failing_blender(tmp_path)), 3, says="no psd: driver data", outputs=[out])


def test_the_rig_script_is_standalone():
    """Blender runs it as a file: it imports bpy and the standard library, nothing of psdbake."""
    path = os.path.join(ROOT, "psdbake", "export", "blender", "rig_script.py")
    with open(path, encoding="utf-8") as fh:
        tree = ast.parse(fh.read())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not any(isinstance(n, ast.ImportFrom) and n.level for n in ast.walk(tree))
    assert imported <= {"__future__", "bpy", "json", "math", "sys", "time", "traceback"}, imported


def test_psdbake_never_loads_blender_itself():
    code = "import sys, psdbake.export.blender.compiler, psdbake.export.blender.export; assert 'bpy' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
