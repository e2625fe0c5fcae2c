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
        "stack LAYER": (["stack", ASSET, path, "-o", s], [s]),
        "inspect": (["inspect", path], []),
        "compare ASSET": (["compare", path, EXAMPLES, "--anim", ANIM, "-o", tmp / "report"], [tmp / "report"]),
    }


ROLES = ["fit ASSET", "fit EXAMPLES", "eval CORRECTIVES", "eval --anim", "pose ASSET", "pose --anim", "stack LAYER",
         "inspect", "compare ASSET"]


@pytest.mark.slow
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


CRATES = {
    # file: what the line says (the probe reads every value in a child process first)
    "crate_value_corrupt.usdc": r"not a readable USD file \(Corrupt",
    "crate_name_not_utf8.usdc": r"not UTF-8",
    "crate_crashes_reader.usdc": r"crashed .*SIGSEGV",
    "crate_value_bad_type.usdc": r"not a readable USD file",
}


@pytest.mark.slow
@pytest.mark.parametrize("role", ["fit ASSET", "pose ASSET", "stack LAYER", "inspect"])
@pytest.mark.parametrize("name", list(CRATES))
def test_corrupt_crate_file(name, role, cli, tmp_path):
    """Bits flipped in a binary layer: refused in one line before any work, whether the
    damage would show late (a value read half-way through a fit) or crash USD's reader."""
    argv, outputs = _roles(os.path.join(BAD, name), tmp_path)[role]
    before = digest([os.path.join(BAD, name)])
    refused(cli(*argv), EXIT_INPUT, names=[name], says=CRATES[name], outputs=outputs, inputs=before)


def test_corrupt_crate_reached_through_a_sublayer(cli, tmp_path):
    top = tmp_path / "top.usda"
    top.write_text(f"#usda 1.0\n(\n    subLayers = [@{os.path.join(BAD, 'crate_crashes_reader.usdc')}@]\n)\n")
    out = tmp_path / "corr.usda"
    refused(cli("fit", top, EXAMPLES, "-o", out), EXIT_INPUT, names=["top.usda", "crate_crashes_reader.usdc"],
            says=r"sublayer .*crashed", outputs=[out])


def test_good_crate_file_is_accepted(cli, tmp_path):
    """The probe does not refuse what is fine: the good asset as a crate file fits."""
    from pxr import Sdf

    crate = tmp_path / "asset.usdc"
    Sdf.Layer.FindOrOpen(ASSET).Export(str(crate))
    out = tmp_path / "corr.usda"
    code, _, err = cli("fit", crate, EXAMPLES, "-o", out, "-q")
    assert (code, err) == (0, "")
    assert out.exists()


def test_usd_refusing_data_late_names_the_inputs(cli, tmp_path, monkeypatch):
    """A Tf.ErrorException past psdbake's own checks (USD refusing data half-way through a
    command) is bad input naming the command's files, never an internal error or C++ text."""
    from pxr import Tf

    import psdbake.api

    def refuse(*args, **kwargs):
        raise Tf.ErrorException("Error in 'pxrInternal_v0_26_11__pxrReserved__::UsdStage::Foo' at line 5 in file "
                                "/opt/USD/pxr/usd/usd/stage.cpp : 'Failed verification: ' value is corrupt ''")

    monkeypatch.setattr(psdbake.api, "fit", refuse)
    out = tmp_path / "corr.usda"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out), EXIT_INPUT, names=["good_asset.usda", "good_examples.usda"],
            says=r"USD could not use the data \(Failed verification: ' value is corrupt", outputs=[out])
