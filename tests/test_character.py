"""A whole character (fixtures/character/): three correctives groups on the body fitted by
three ``fit --group`` runs into one CORRECTIVES layer, a sleeve with its own skel:joints
and its own examples, and a brow with an animated blend shape and no examples.

Pixar's ``UsdSkel.BakeSkinning`` of ASSET + CORRECTIVES + pose + WEIGHTS must reproduce
every sculpt within 1e-5 of the mesh's diagonal (as in test_roundtrip: the inverse stops
at 1e-6, the rest is float32 storage and float32 skinning), and leave the brow's baked
points bit-for-bit as plain UsdSkel gives them.
"""

from __future__ import annotations

import filecmp
import json
import os
import subprocess
import sys

import character
import numpy as np
import pytest
from conftest import ROOT, bake, diagonal, fixture, points, pose_only, run_cli, sculpt
from pxr import Sdf, Usd

from psdbake.tolerances import ROUNDTRIP_RTOL

ASSET = fixture("character", "character.usda")
ANIM = fixture("character", "character_anim.usda")


def examples_of(group: str) -> list[str]:
    return [fixture("character", character.EXAMPLE_SETS[name]["file"]) for name in character.FIT_GROUPS[group]]


def fit_groups(run, out, order=("l_elbow", "r_elbow", "neck")) -> None:
    for group in order:
        code, _, err = run("fit", ASSET, *examples_of(group), "--group", group, "-o", out, "-q")
        assert code == 0, err


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The three group fits into one layer (an in-process CLI call each)."""
    out = tmp_path_factory.mktemp("character") / "correctives.usda"
    fit_groups(run_cli, out)
    return out


def test_three_group_fits_land_in_one_layer(fitted, run):
    code, out, _ = run("inspect", fitted, "--json")
    info = json.loads(out)
    assert code == 0
    groups = {(c["mesh"], c["group"]): c for c in info["correctives"]}
    assert sorted(groups) == [
        (character.BODY, "l_elbow"), (character.BODY, "neck"), (character.BODY, "r_elbow"), (character.SLEEVE, "l_elbow"),
    ]
    assert groups[(character.BODY, "neck")]["drivers"] == ["Hips/Spine/Neck"]
    assert groups[(character.SLEEVE, "l_elbow")]["drivers"] == ["Hips/Spine/L_Shoulder/L_Elbow"]
    # the brow keeps its own blend shape and gets no correctives
    assert not any(c["mesh"] == character.BROW for c in info["correctives"])


@pytest.mark.parametrize("example_set", sorted(character.EXAMPLE_SETS))
def test_bake_of_stack_reproduces_every_sculpt(example_set, fitted, run, tmp_path):
    examples = fixture("character", character.EXAMPLE_SETS[example_set]["file"])
    weights = tmp_path / "weights.usda"
    code, _, err = run("eval", ASSET, fitted, "--anim", examples, "-o", weights, "-q")
    assert code == 0, err
    for t in sorted(character.EXAMPLE_SETS[example_set]["poses"]):
        baked = bake([str(weights), pose_only(examples), str(fitted), ASSET], t)
        plain = bake([pose_only(examples), ASSET], t)
        for mesh in character.EXAMPLE_SETS[example_set]["meshes"]:
            target = sculpt(examples, mesh, t)
            err_rel = np.abs(points(baked, mesh, t) - target).max() / diagonal(target)
            assert err_rel <= ROUNDTRIP_RTOL, f"{example_set} {mesh} t={t}: {err_rel:.2e}"
            assert np.abs(points(plain, mesh, t) - target).max() / diagonal(target) > 100 * ROUNDTRIP_RTOL


def test_brow_animation_is_exactly_as_before(fitted, run, tmp_path):
    weights = tmp_path / "weights.usda"
    assert run("eval", ASSET, fitted, "--anim", ANIM, "-o", weights, "-q")[0] == 0
    frames = sorted(Sdf.Layer.FindOrOpen(ANIM).ListTimeSamplesForPath(f"{character.ANIM}.blendShapeWeights"))
    moved = []
    for t in frames:
        with_psd = points(bake([str(weights), ANIM, str(fitted), ASSET], t), character.BROW, t)
        before = points(bake([ANIM, ASSET], t), character.BROW, t)
        assert np.array_equal(with_psd, before), f"frame {t}"
        moved.append(with_psd)
    # and the brow's blend shape really animates over the shot (the check is not vacuous)
    assert np.ptp(np.array(moved)[:, :, 1]) > 0.05


def test_group_order_does_not_matter(fitted, run, tmp_path):
    """Groups are stored sorted by name: fitting them in another order gives the same bytes."""
    other = tmp_path / "correctives.usda"
    fit_groups(run, other, order=("neck", "l_elbow", "r_elbow"))
    assert filecmp.cmp(fitted, other, shallow=False)


def test_refitting_a_group_leaves_the_others_untouched(fitted, run, tmp_path):
    out = tmp_path / "correctives.usda"
    out.write_bytes(fitted.read_bytes())
    code, _, err = run("fit", ASSET, *examples_of("neck"), "--group", "neck", "--kernel", "thin_plate_spline",
                       "-o", out, "-q")
    assert code == 0, err
    before, after = Sdf.Layer.FindOrOpen(str(fitted)), Sdf.Layer.FindOrOpen(str(out))
    for group in ("l_elbow", "r_elbow"):
        for attr in ("kernel", "sigma", "coefficients", "centers", "shapes", "channels", "channelScales"):
            path = f"{character.BODY}.psd:{group}:{attr}"
            assert before.GetAttributeAtPath(path).default == after.GetAttributeAtPath(path).default, path
        channels = before.GetAttributeAtPath(f"{character.BODY}.psd:{group}:channels").default
        assert len(channels) >= 2
        for channel in channels:
            shape = f"{character.BODY}/{channel}.offsets"
            assert before.GetAttributeAtPath(shape).default == after.GetAttributeAtPath(shape).default
    assert after.GetAttributeAtPath(f"{character.BODY}.psd:neck:kernel").default == "thin_plate_spline"
    assert before.GetAttributeAtPath(f"{character.BODY}.psd:neck:kernel").default == "gaussian"


def test_fit_without_group_replaces_the_layer_only_when_asked(fitted, run, tmp_path):
    """The layer holds groups of --group fits: a plain fit would drop them, so it is refused
    (exit 6, naming them, the file unchanged) until --force says to replace the layer."""
    out = tmp_path / "correctives.usda"
    out.write_bytes(fitted.read_bytes())
    code, _, err = run("fit", ASSET, *examples_of("neck"), "-o", out, "-q")
    assert code == 6 and "would drop: l_elbow (fit --group of" in err and "--force" in err, err
    assert out.read_bytes() == fitted.read_bytes()
    assert run("fit", ASSET, *examples_of("neck"), "-o", out, "-q", "--force")[0] == 0
    stage = Usd.Stage.Open(str(out))
    groups = stage.GetPrimAtPath(character.BODY).GetAttribute("psd:groups").Get()
    assert list(groups) == ["Neck"]  # the neck examples move one joint: one local group, the others dropped


def test_mesh_restricted_group_fit_keeps_the_group_on_other_meshes(fitted, run, tmp_path):
    out = tmp_path / "correctives.usda"
    out.write_bytes(fitted.read_bytes())
    code, _, err = run("fit", ASSET, *examples_of("l_elbow"), "--group", "l_elbow", "--mesh", character.SLEEVE,
                       "--kernel", "linear", "-o", out, "-q")
    assert code == 0, err
    stage = Usd.Stage.Open(str(out))
    assert stage.GetPrimAtPath(character.SLEEVE).GetAttribute("psd:l_elbow:kernel").Get() == "linear"
    assert stage.GetPrimAtPath(character.BODY).GetAttribute("psd:l_elbow:kernel").Get() == "gaussian"


def test_a_group_that_would_double_another_is_refused(fitted, run, tmp_path):
    """A second group driven by the same joint would add its correction to the first's at every
    pose of that joint: refused (exit 4) naming both, the layer unchanged."""
    out = tmp_path / "correctives.usda"
    out.write_bytes(fitted.read_bytes())
    code, _, err = run("fit", ASSET, *examples_of("r_elbow"), "--group", "r_elbow_again", "-o", out)
    assert code == 4, err
    assert "group 'r_elbow_again'" in err and "double the correction of group 'r_elbow'" in err
    assert out.read_bytes() == fitted.read_bytes()


@pytest.mark.slow
def test_concurrent_group_fits_all_land(tmp_path):
    """Two processes updating one CORRECTIVES layer: the update is locked, both groups land."""
    out = tmp_path / "correctives.usda"
    env = {**os.environ, "PYTHONPATH": ROOT}
    procs = [
        subprocess.Popen([sys.executable, "-m", "psdbake", "fit", ASSET, *examples_of(g), "--group", g, "-o", str(out),
                          "-q"], env=env, stderr=subprocess.PIPE)
        for g in ("r_elbow", "neck")
    ]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err.decode()
    stage = Usd.Stage.Open(str(out))
    groups = stage.GetPrimAtPath(character.BODY).GetAttribute("psd:groups").Get()
    assert list(groups) == ["neck", "r_elbow"]


@pytest.mark.parametrize(("args", "code", "says"), [
    (["--group", "l elbow"], 3, r"--group 'l elbow': must be an identifier"),
    (["--group", "version"], 3, r"must be an identifier"),
])
def test_bad_group_names(args, code, says, run, tmp_path):
    import re

    out = tmp_path / "c.usda"
    rc, _, err = run("fit", ASSET, *examples_of("neck"), *args, "-o", out)
    assert rc == code and re.search(says, err) and not out.exists()


def test_group_update_of_a_file_that_is_not_correctives_is_refused(run, tmp_path):
    out = tmp_path / "c.usda"
    with open(ANIM, "rb") as fh:
        out.write_bytes(fh.read())
    before = out.read_bytes()
    rc, _, err = run("fit", ASSET, *examples_of("neck"), "--group", "neck", "-o", out)
    assert rc == 6 and "is a USD animation layer" in err and "not a psdbake CORRECTIVES layer" in err, err
    assert str(out) in err and "--force" in err
    assert out.read_bytes() == before


def test_psd_v1_layers_still_evaluate(run, tmp_path):
    """A CORRECTIVES layer from psdbake 0.1 (psd: v1, one flat group) gives the same weights
    as today's v2 fit of the same examples."""
    from conftest import fixture as fx

    asset, examples, anim = fx("bad", "good_asset.usda"), fx("bad", "good_examples.usda"), fx("arm_anim.usda")
    v1 = os.path.join(ROOT, "tests", "data", "correctives_v1.usda")
    v2 = tmp_path / "v2.usda"
    assert run("fit", asset, examples, "-o", v2, "-q", "--group", "main")[0] == 0  # v1's one flat group
    from psdbake import api

    w1 = api.evaluate(asset, v1, anim).animations[0]
    w2 = api.evaluate(asset, str(v2), anim).animations[0]
    from psdbake.fitting.groups import read_correctives
    from psdbake.model.channels import column_weights

    ((data, _),) = next(iter(read_correctives(asset, str(v2)).values())).values()
    assert w1.channels == tuple(c.replace("psd_main_", "psd_") for c in data.shapes)
    b2 = column_weights(data, w2.weights[:, [w2.channels.index(c) for c in data.channels]])
    np.testing.assert_allclose(w1.weights, b2, rtol=0, atol=1e-9)
