"""Finite or refused (issue 10): every number psdbake reads from ``psd:`` is validated on read
with the attribute named, a deformer's output must be real numbers within float32's range,
a deformer cannot end the process, time codes must be finite, EXAMPLES cannot change the
skinning that eval and UsdSkel apply, and CORRECTIVES must belong to the asset.

Every refusal is checked against the shared contract (``conftest.refused``): one
``psdbake: error:`` line, the exit code, no traceback, no output or temp file, inputs
byte-identical. The defective files are in ``fixtures/bad`` (``FINITE_CASES`` and the
deformers in ``DEFORMERS`` of ``fixtures/bad/make_bad.py``).
"""

from __future__ import annotations

import os
import shutil
import sys

import numpy as np
import pytest
from conftest import digest, fixture, refused
from pxr import Sdf, Vt

BAD = fixture("bad")
sys.path.insert(0, BAD)
import make_bad  # noqa: E402  (fixtures/bad/make_bad.py)

MESH, SKEL, ANIM_PRIM = make_bad.MESH, make_bad.SKEL, make_bad.ANIM_PRIM
ASSET, EXAMPLES, CORRECTIVES = (os.path.join(BAD, f"good_{k}.usda") for k in ("asset", "examples", "correctives"))
POSES, ANIM = fixture("arm_poses.usda"), fixture("arm_anim.usda")
EXIT_INPUT, EXIT_DEFORMER, EXIT_INTERRUPTED = 3, 5, 130


def bad(name: str) -> str:
    return os.path.join(BAD, name)


def _deformer(name: str) -> str:
    return f"{os.path.join(BAD, 'deformers', name)}:make"


# --- psd: values, validated on read -----------------------------------------------------------

PSD_CASES = {
    # file: (attribute named, what the message must say)
    "psd_sigma_nan.usda": ("sigma", r"nan is not a finite number > 0"),
    "psd_sigma_zero.usda": ("sigma", r"0\.0 is not a finite number > 0"),
    "psd_coefficients_nan.usda": ("coefficients", r"value 4 is nan.*finite"),
    "psd_centers_inf.usda": ("centers", r"value 8 is inf.*finite"),
    "psd_bind_rotation_zero.usda": ("driverBindRotations", r"quaternion 0 .*Shoulder/Elbow.*not a unit quaternion"),
    "psd_swing_twist_no_axis.usda": ("twistAxis", r"missing.*swingTwist"),
    "psd_twist_axis_zero.usda": ("twistAxis", r"not a finite non-zero"),
    "psd_smoothing_negative.usda": ("smoothing", r"-1\.0 is not a finite number >= 0"),
    "psd_example_times_inf.usda": ("exampleTimes", r"value 2 is inf.*finite"),
    "psd_degree_negative.usda": ("degree", r"-2 is not one integer >= -1"),
    "psd_degree_without_powers.usda": ("polyPowers", r"0 monomials .*degree 1 in 6 dimensions.*expected the 7"),
    "psd_poly_scale_zero.usda": ("polyScale", r"value 0 is zero"),
    "psd_poly_scale_wrong_length.usda": ("polyScale", r"1 values for 2 psd:dimensions"),
    "psd_poly_shift_nan.usda": ("polyShift", r"value 1 is nan"),
    "psd_poly_degree_mismatch.usda": ("polyPowers", r"3 monomials .*degree 2 in 2 dimensions.*expected the 6"),
}


@pytest.mark.parametrize("name", list(PSD_CASES))
def test_psd_value_refused_by_eval(name, cli, tmp_path):
    """Before: NaN or zero values gave NaN weights with exit 0, or a ZeroDivisionError /
    scipy ValueError (exit 1). Now: exit 3 naming FILE <MESH.psd:main:attr>."""
    attr, says = PSD_CASES[name]
    w, pc = tmp_path / "weights.usda", tmp_path / "cache.usda"
    before = digest([ASSET, bad(name), ANIM])
    refused(cli("eval", ASSET, bad(name), "--anim", ANIM, "-o", w, "--points-cache", pc), EXIT_INPUT,
            names=[name, f"<{MESH}.psd:main:{attr}>"], says=says, outputs=[w, pc], inputs=before)


@pytest.mark.parametrize("name", ["psd_sigma_nan.usda", "psd_bind_rotation_zero.usda", "psd_poly_scale_zero.usda"])
def test_psd_value_refused_by_fit_group_update(name, cli, tmp_path):
    """``fit --group`` reads the groups already in -o: a tampered one is refused before the fit,
    and the layer is left as it was."""
    out = tmp_path / "corr.usda"
    shutil.copy(bad(name), out)
    before = digest([ASSET, EXAMPLES, out])
    attr = PSD_CASES[name][0]
    refused(cli("fit", ASSET, EXAMPLES, "--group", "elbow", "-o", out), EXIT_INPUT,
            names=["corr.usda", f"<{MESH}.psd:main:{attr}>"], inputs=before)
    assert not [f for f in os.listdir(tmp_path) if ".tmp" in f]


def test_polynomial_baseline_evaluates(cli, tmp_path):
    """The psd_poly_* cases' baseline (a --degree 1 fit) is good: its only defect is the one named."""
    layer, _ = make_bad._poly_correctives(BAD, None)
    corr = tmp_path / "poly.usda"
    layer.Export(str(corr))
    w = tmp_path / "weights.usda"
    code, _, err = cli("eval", ASSET, corr, "--anim", ANIM, "-o", w, "-q")
    assert (code, err) == (0, "")
    weights = Sdf.Layer.FindOrOpen(str(w))
    path = Sdf.Path(ANIM_PRIM).AppendProperty("blendShapeWeights")
    values = np.array([list(weights.QueryTimeSample(path, t)) for t in weights.ListTimeSamplesForPath(path)])
    assert values.size and np.all(np.isfinite(values))


def test_finite_psd_values_that_overflow_the_weights(cli, tmp_path):
    """A finite but absurd coefficient (1e300) would write inf into float32 blendShapeWeights."""
    name = "psd_coefficients_huge.usda"
    w = tmp_path / "weights.usda"
    before = digest([ASSET, bad(name), ANIM])
    refused(cli("eval", ASSET, bad(name), "--anim", ANIM, "-o", w), EXIT_INPUT,
            names=[name, f"<{MESH}>", "time 1"], says=r"group 'main'.*beyond float32", outputs=[w], inputs=before)


# --- CORRECTIVES from another asset ------------------------------------------------------------

@pytest.mark.parametrize(("name", "prim", "says"), [
    ("correctives_other_asset.usda", "</Arm/Geo/Sleeve>", r"not a skinned mesh of .*good_asset\.usda"),
    ("correctives_other_point_count.usda", f"<{MESH}/psd_main_Geo_Tube_01_pos.pointIndices>", r"outside the 16 points"),
])
def test_correctives_of_another_asset(name, prim, says, cli, tmp_path):
    """Before: exit 0 with a points cache silently lacking those correctives."""
    w, pc = tmp_path / "weights.usda", tmp_path / "cache.usda"
    before = digest([ASSET, bad(name), ANIM])
    refused(cli("eval", ASSET, bad(name), "--anim", ANIM, "-o", w, "--points-cache", pc), EXIT_INPUT,
            names=[name, prim], says=says, outputs=[w, pc], inputs=before)


# --- time codes -------------------------------------------------------------------------------

def test_example_at_time_code_inf(cli, tmp_path):
    """Before: exit 0 and psd:main:exampleTimes = [1, 2, inf]."""
    name = "example_time_inf.usda"
    out = tmp_path / "corr.usda"
    before = digest([ASSET, bad(name)])
    refused(cli("fit", ASSET, bad(name), "-o", out), EXIT_INPUT, names=[name, f"<{MESH}.points>"],
            says=r"time code inf.*finite", outputs=[out], inputs=before)


def test_example_pose_sample_at_time_code_inf(cli, tmp_path):
    """EXAMPLES whose animation also keys a pose at inf (no sculpt there): refused like eval's."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(EXAMPLES))
    layer.SetTimeSample(make_bad.ROTATIONS, float("inf"), layer.QueryTimeSample(make_bad.ROTATIONS, 3.0))
    path = tmp_path / "examples_pose_inf.usda"
    layer.Export(str(path))
    out = tmp_path / "corr.usda"
    before = digest([ASSET, path])
    refused(cli("fit", ASSET, path, "-o", out), EXIT_INPUT, names=["examples_pose_inf.usda", f"<{ANIM_PRIM}.rotations>"],
            says=r"time code inf", outputs=[out], inputs=before)


@pytest.mark.parametrize("points_cache", [False, True])
def test_animation_sample_at_time_code_inf(points_cache, cli, tmp_path):
    """USD's queries skip a sample keyed at inf: the pose there would be silently dropped."""
    name = "anim_time_inf.usda"
    w, pc = tmp_path / "weights.usda", tmp_path / "cache.usda"
    argv = ["eval", ASSET, CORRECTIVES, "--anim", bad(name), "-o", w] + (["--points-cache", pc] if points_cache else [])
    before = digest([ASSET, CORRECTIVES, bad(name)])
    refused(cli(*argv), EXIT_INPUT, names=[name, f"<{ANIM_PRIM}.rotations>"], says=r"time code inf",
            outputs=[w, pc], inputs=before)


# --- EXAMPLES must not change the skinning ------------------------------------------------------

REBIND = {
    "examples_rebind_weights.usda": f"<{MESH}.primvars:skel:jointWeights>",
    "examples_rebind_geom_bind_transform.usda": f"<{MESH}.primvars:skel:geomBindTransform>",
    "examples_rebind_skinning_method.usda": f"<{MESH}.primvars:skel:skinningMethod>",
    "examples_rebind_joints.usda": f"<{MESH}.skel:joints>",
    "examples_rebind_bind_transforms.usda": f"<{SKEL}.bindTransforms>",
}


@pytest.mark.parametrize("name", list(REBIND))
def test_examples_that_rebind_are_refused(name, cli, tmp_path):
    """Before: exit 0 and correctives inverted through a skinning eval never applies (the
    re-weighted case missed the sculpts by 0.91 of the diagonal)."""
    out = tmp_path / "corr.usda"
    before = digest([ASSET, bad(name)])
    refused(cli("fit", ASSET, EXAMPLES, bad(name), "-o", out), EXIT_INPUT, names=[name, REBIND[name]],
            says=r"re-authors the asset's skinning binding.*may only carry the pose .* and the sculpted points",
            outputs=[out], inputs=before)


def test_examples_repeating_the_binding_unchanged_are_accepted(cli, tmp_path):
    """The rule is about the skinning, not about which opinions exist: an EXAMPLES layer that
    repeats the asset's own binding values (a DCC export of the whole mesh) is fitted."""
    asset = Sdf.Layer.FindOrOpen(ASSET)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(EXAMPLES))
    spec = layer.GetPrimAtPath(MESH)
    for name in ("primvars:skel:jointWeights", "primvars:skel:jointIndices"):
        source = asset.GetAttributeAtPath(Sdf.Path(MESH).AppendProperty(name))
        copy = Sdf.AttributeSpec(spec, name, source.typeName)
        copy.default = source.default
    path = tmp_path / "examples_full.usda"
    layer.Export(str(path))
    out = tmp_path / "corr.usda"
    code, _, err = cli("fit", ASSET, path, "-o", out, "-q")
    assert (code, err) == (0, "")
    assert out.exists()


def test_examples_with_their_own_pose_are_accepted(cli, tmp_path):
    """The pose (the bound SkelAnimation, restTransforms of unanimated joints) is EXAMPLES' to carry."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(EXAMPLES))
    anim = layer.GetAttributeAtPath(Sdf.Path(ANIM_PRIM).AppendProperty("translations"))
    anim.default = Vt.Vec3fArray([(2.0, 0.0, 0.0), (2.0, 0.0, 0.0)])  # re-authored, same value
    path = tmp_path / "examples.usda"
    layer.Export(str(path))
    code, _, err = cli("fit", ASSET, path, "-o", tmp_path / "corr.usda", "-q")
    assert (code, err) == (0, "")


# --- deformers: outputs checked, cannot end the process ------------------------------------------

RUNTIME = [f"<{MESH}>", "time 1"]
DEFORMER_CASES = {
    # file: (names, what the message must say)
    "returns_huge.py": (RUNTIME, r"1e\+39.*beyond float32"),
    "returns_strings.py": (RUNTIME, r"returned ndarray of strings.*\(16, 3\) array of numbers"),
    "returns_dict.py": (RUNTIME, r"returned dict.*array of numbers"),
    "returns_none.py": (RUNTIME, r"returned None"),
    "returns_ragged.py": (RUNTIME, r"returned a list that is not an array of numbers"),
    "calls_exit.py": (RUNTIME, r"sys\.exit\(0\)"),
    "factory_exits.py": (RUNTIME, r"set up.*sys\.exit\(0\)"),
    "import_exits.py": ([], r"importing .*sys\.exit\(0\)"),
}


def _deformer_argv(command: str, tmp) -> tuple[list, list, list]:
    """(argv, outputs, inputs) of one command with one --deformer."""
    c, e, w, pc = tmp / "corr.usda", tmp / "examples.usda", tmp / "weights.usda", tmp / "cache.usda"
    return {
        "fit": (["fit", ASSET, EXAMPLES, "-o", c], [c], [ASSET, EXAMPLES]),
        "pose": (["pose", ASSET, "--anim", POSES, "-o", e], [e], [ASSET, POSES]),
        "eval": (["eval", ASSET, CORRECTIVES, "--anim", ANIM, "-o", w, "--points-cache", pc], [w, pc],
                 [ASSET, CORRECTIVES, ANIM]),
    }[command]


@pytest.mark.parametrize(("case", "command"), [
    pytest.param(case, command, id=f"{case[:-3]}-{command}") for case in DEFORMER_CASES
    for command in ("fit", "pose", "eval")
])
def test_deformer_output_or_exit(case, command, cli, tmp_path):
    """Before: 1e39 was written as inf (exit 0), strings/dict/ragged gave exit 1, sys.exit(0)
    ended the run with exit 0 and nothing written. Now: exit 5 naming the deformer."""
    names, says = DEFORMER_CASES[case]
    spec = _deformer(case)
    argv, outputs, inputs = _deformer_argv(command, tmp_path)
    before = digest([*inputs, spec.rsplit(":", 1)[0]])
    refused(cli(*argv, "--deformer", spec), EXIT_DEFORMER, names=[case, *names], says=says, outputs=outputs,
            inputs=before)


@pytest.mark.slow
def test_deformer_exit_in_a_worker_process(cli, tmp_path):
    """--jobs 2: the example solves run in worker processes; sys.exit there is the same exit 5."""
    out = tmp_path / "corr.usda"
    spec = _deformer("calls_exit.py")
    refused(cli("fit", ASSET, EXAMPLES, "-o", out, "--jobs", "2", "--deformer", spec), EXIT_DEFORMER,
            names=["calls_exit.py", f"<{MESH}>"], says=r"sys\.exit\(0\)", outputs=[out])


@pytest.mark.parametrize("command", ["fit", "eval"])
def test_keyboard_interrupt_in_a_deformer_still_interrupts(command, cli, tmp_path):
    """Ctrl-C inside a deformer is not a deformer failure: the run is interrupted (130)."""
    argv, outputs, _ = _deformer_argv(command, tmp_path)
    code, _, err = cli(*argv, "--deformer", _deformer("raises_keyboard_interrupt.py"))
    assert code == EXIT_INTERRUPTED, err
    assert "psdbake: interrupted" in err and "Traceback" not in err
    for path in outputs:
        assert not os.path.exists(path)
