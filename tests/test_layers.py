"""Layers USD would block on or cannot read whole: every input position, every command.

USD opens the layers an input reaches by itself while composing, so a FIFO (or a device)
anywhere in the layer stack, the file given or a sublayer inside a regular file, would
block it forever: psdbake checks every layer file before composing. Text that is not
UTF-8 and composition cycles are refused in one line naming the file.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
from conftest import ROOT, digest, fixture, refused

BAD = fixture("bad")
ASSET, EXAMPLES, CORRECTIVES = (os.path.join(BAD, f"good_{k}.usda") for k in ("asset", "examples", "correctives"))
ANIM, POSES = fixture("arm_anim.usda"), fixture("arm_poses.usda")
PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")
EXIT_INPUT = 3


def _roles(path: str, tmp) -> dict[str, tuple[list, list]]:
    """The file under test in every input position: role -> (argv, outputs)."""
    c, w, e, s = tmp / "corr.usda", tmp / "weights.usda", tmp / "examples.usda", tmp / "shot.usda"
    return {
        "fit ASSET": (["fit", path, EXAMPLES, "-o", c], [c]),
        "fit EXAMPLES": (["fit", ASSET, path, "-o", c], [c]),
        "eval CORRECTIVES": (["eval", ASSET, path, "--anim", ANIM, "-o", w], [w]),
        "eval --anim": (["eval", ASSET, CORRECTIVES, "--anim", path, "-o", w], [w]),
        "pose ASSET": (["pose", path, "--anim", POSES, "-o", e], [e]),
        "pose --anim": (["pose", ASSET, "--anim", path, "-o", e], [e]),
        "stack LAYER": (["stack", s, ASSET, path], [s]),
        "inspect": (["inspect", path], []),
        "compare ASSET": (["compare", path, EXAMPLES, "--anim", ANIM, "-o", tmp / "report"], [tmp / "report"]),
    }


ROLES = ["fit ASSET", "fit EXAMPLES", "eval CORRECTIVES", "eval --anim", "pose ASSET", "pose --anim", "stack LAYER",
         "inspect", "compare ASSET"]


@pytest.mark.parametrize("where", ["given", "sublayer"])
@pytest.mark.parametrize("role", ROLES)
def test_fifo_never_blocks(role, where, tmp_path):
    """A FIFO nobody writes to, given directly or sublayered by a regular file: refused at once."""
    fifo = tmp_path / "pipe.usda"
    os.mkfifo(fifo)
    path = fifo
    if where == "sublayer":
        path = tmp_path / "top.usda"
        path.write_text("#usda 1.0\n(\n    subLayers = [@./pipe.usda@]\n)\n")
    argv, outputs = _roles(str(path), tmp_path)[role]
    before = digest([path])
    try:
        done = subprocess.run([PSDBAKE, *map(str, argv)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"psdbake {role} blocked on a FIFO ({where})")
    refused((done.returncode, done.stdout, done.stderr), EXIT_INPUT, names=[os.path.basename(path), "pipe.usda"],
            says=r"FIFO", outputs=outputs, inputs=before)


DEFECTS = {
    # file: (what else is named, what the line says)
    "not_utf8.usda": ([], r"not UTF-8"),
    "sublayer_not_utf8.usda": (["not_utf8.usda"], r"sublayer .*not UTF-8"),
    "sublayer_cycle.usda": ([], r"cycle"),
    "reference_cycle.usda": (["reference_cycle_partner.usda", "</Arm/Geo>"], r"cycle"),
    "sublayer_is_folder.usda": (["folder.usda"], r"sublayer"),
}


@pytest.mark.parametrize("role", ROLES)
@pytest.mark.parametrize("name", list(DEFECTS))
def test_layer_usd_cannot_read_whole(name, role, cli, tmp_path):
    others, says = DEFECTS[name]
    argv, outputs = _roles(os.path.join(BAD, name), tmp_path)[role]
    before = digest([os.path.join(BAD, f) for f in os.listdir(BAD) if f.endswith(".usda")])
    refused(cli(*argv), EXIT_INPUT, names=[name, *others], says=says, outputs=outputs, inputs=before)


def test_device_as_layer_is_refused(cli, tmp_path):
    """/dev/zero behind a layer name: never read (it would be read without end)."""
    link = tmp_path / "zero.usda"
    os.symlink("/dev/zero", link)
    out = tmp_path / "corr.usda"
    refused(cli("fit", link, EXAMPLES, "-o", out), EXIT_INPUT, names=["zero.usda"], says=r"device|not a regular",
            outputs=[out])


def test_regular_sublayer_chain_still_composes(cli, tmp_path):
    """The checks do not refuse what is fine: an asset reached through two sublayer hops fits."""
    shutil.copy(ASSET, tmp_path / "asset.usda")
    (tmp_path / "mid.usda").write_text("#usda 1.0\n(\n    subLayers = [@./asset.usda@]\n)\n")
    (tmp_path / "top.usda").write_text("#usda 1.0\n(\n    subLayers = [@./mid.usda@]\n)\n")
    out = tmp_path / "corr.usda"
    code, _, err = cli("fit", tmp_path / "top.usda", EXAMPLES, "-o", out, "-q")
    assert (code, err) == (0, "")
    assert out.exists()
