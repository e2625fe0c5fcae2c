"""The bad-input catalogue: every defective input is refused in ONE line, with the right
exit code, naming the file (and the prim, where there is one) and what is wrong; no
traceback; no output file left behind. Warnings-only cases succeed with a
``psdbake: warning:`` line.

The defective files live in ``fixtures/bad/`` (one defect each, written from small good
baselines by ``fixtures/bad/make_bad.py``). Permission cases (chmod 000, read-only
folders) are made in ``tmp_path`` because git cannot carry them.

The CLI runs in-process with its output captured at the file descriptors (conftest's
``run_cli``, as ``capfd`` does): USD prints its own warnings from C++ straight to file
descriptor 2, and users see those lines too.
"""

from __future__ import annotations

import filecmp
import os
import re
import shutil
import stat
import sys

import pytest
from conftest import fixture, refused, warned

BAD = fixture("bad")
sys.path.insert(0, BAD)
import make_bad  # noqa: E402  (fixtures/bad/make_bad.py)

MESH, SKEL, ANIM_PRIM = make_bad.MESH, make_bad.SKEL, make_bad.ANIM_PRIM
ASSET, EXAMPLES, CORRECTIVES = (os.path.join(BAD, f"good_{k}.usda") for k in ("asset", "examples", "correctives"))
POSES, ANIM = fixture("arm_poses.usda"), fixture("arm_anim.usda")
DEFORMERS = os.path.join(BAD, "deformers")

EXIT_INPUT, EXIT_FIT, EXIT_DEFORMER, EXIT_OUTPUT = 3, 4, 5, 6


def bad(name: str) -> str:
    return os.path.join(BAD, name)


# --- files that are missing, not files, or not USD ----------------------------------------

def _roles(path: str, tmp) -> dict[str, tuple[list, list]]:
    """The bad file in every input position: role -> (argv, outputs)."""
    c, w, e = tmp / "corr.usda", tmp / "weights.usda", tmp / "examples.usda"
    return {
        "fit ASSET": (["fit", path, EXAMPLES, "-o", c], [c]),
        "fit EXAMPLES": (["fit", ASSET, path, "-o", c], [c]),
        "eval CORRECTIVES": (["eval", ASSET, path, "--anim", ANIM, "-o", w], [w]),
        "eval --anim": (["eval", ASSET, CORRECTIVES, "--anim", path, "-o", w], [w]),
        "pose --anim": (["pose", ASSET, "--anim", path, "-o", e], [e]),
    }


ROLES = ["fit ASSET", "fit EXAMPLES", "eval CORRECTIVES", "eval --anim", "pose --anim"]

FILE_DEFECTS = {
    # name: (file, what the message must say)
    "missing": ("does_not_exist.usda", r"not found|does not exist|no such file"),
    "not_usd": ("not_usd.usda", r"not a (readable|valid) USD|not a valid usda"),
    "empty": ("empty.usda", r"empty|not a (readable|valid) USD|not a valid usda"),
    "truncated_usdc": ("truncated.usdc", r"truncated|corrupt"),
    "wrong_extension": ("wrong_extension.txt", r"file format|extension"),
    "folder": ("folder.usda", r"folder|directory"),
    "sublayer_missing": ("sublayer_missing.usda", r"sublayer.*missing_sublayer\.usda|missing_sublayer\.usda.*sublayer"),
    "reference_missing": ("reference_missing.usda", r"missing_reference\.usda"),
}


@pytest.mark.parametrize(("defect", "role"), [
    pytest.param(defect, role, id=f"{defect}-{role.replace(' ', '_')}") for defect in FILE_DEFECTS for role in ROLES
])
@pytest.mark.slow
def test_unusable_file(defect, role, cli, tmp_path):
    name, says = FILE_DEFECTS[defect]
    argv, outputs = _roles(bad(name), tmp_path)[role]
    line = refused(cli(*argv), EXIT_INPUT, names=[name], says=says, outputs=outputs)
    if defect == "reference_missing":
        assert "</Arm/Geo>" in line


@pytest.mark.parametrize("role", ROLES)
def test_unreadable_file(role, cli, tmp_path):
    path = tmp_path / "unreadable.usda"
    shutil.copy(ASSET if role != "eval CORRECTIVES" else CORRECTIVES, path)
    os.chmod(path, 0)
    try:
        if os.access(path, os.R_OK):
            pytest.skip("chmod 000 does not stop this user (root) from reading")
        argv, outputs = _roles(str(path), tmp_path)[role]
        refused(cli(*argv), EXIT_INPUT, names=["unreadable.usda"], says=r"permission|not readable", outputs=outputs)
    finally:
        os.chmod(path, stat.S_IRUSR | stat.S_IWUSR)


# --- assets ----------------------------------------------------------------------------

ASSET_ROLES = ["fit", "pose", "eval --points-cache"]


def _asset_argv(command: str, asset: str, tmp) -> tuple[list, list]:
    c, e, w, pc = tmp / "corr.usda", tmp / "examples.usda", tmp / "weights.usda", tmp / "cache.usda"
    return {
        "fit": (["fit", asset, EXAMPLES, "-o", c], [c]),
        "pose": (["pose", asset, "--anim", POSES, "-o", e], [e]),
        "eval --points-cache": (["eval", asset, CORRECTIVES, "--anim", ANIM, "-o", w, "--points-cache", pc], [w, pc]),
    }[command]


# The baselines are good, so every failure here is its file's one defect.
@pytest.mark.parametrize("command", ["fit", "pose", "eval --points-cache"])
def test_good_baselines_pass(command, cli, tmp_path):
    argv, outputs = _asset_argv(command, ASSET, tmp_path)
    code, _, err = cli(*argv, "-q")
    assert (code, err) == (0, ""), f"the good baseline fails (re-run fixtures/bad/make_bad.py?): {err}"
    assert all(os.path.exists(p) for p in outputs)


ASSET_DEFECTS = {
    # name: (file, prim named, what it must say)
    "no_skelroot": ("no_skelroot.usda", None, r"SkelRoot"),
    "mesh_no_skeleton": ("mesh_no_skeleton.usda", "</Arm>", r"no skinned mesh|skel:skeleton"),
    "mesh_no_joint_influences": ("mesh_no_joint_influences.usda", f"<{MESH}", r"jointIndices|jointWeights"),
    "joint_indices_out_of_range": ("joint_indices_out_of_range.usda", f"<{MESH}",
                                   r"joint ?ind(ex|ices).*\b7\b.*\b4\b|\b7\b.*out of range"),
    "joint_weights_count_mismatch": ("joint_weights_count_mismatch.usda", f"<{MESH}", r"jointWeights.*(60|15)"),
    "negative_weights": ("negative_weights.usda", f"<{MESH}", r"negative"),
    "nan_weights": ("nan_weights.usda", f"<{MESH}", r"NaN"),
    "zero_weights": ("zero_weights.usda", f"<{MESH}", r"zero"),
    "bind_transforms_count_mismatch": ("bind_transforms_count_mismatch.usda", f"<{SKEL}", r"bindTransforms"),
    "rest_points_nan": ("rest_points_nan.usda", f"<{MESH}", r"NaN"),
    "joint_weights_element_size_mismatch": ("joint_weights_element_size_mismatch.usda", f"<{MESH}",
                                            r"jointWeights has elementSize 2 .* jointIndices 4"),
}


@pytest.mark.parametrize(("defect", "role"), [
    pytest.param(defect, role, id=f"{defect}-{role.split()[0]}") for defect in ASSET_DEFECTS for role in ASSET_ROLES
])
def test_bad_asset(defect, role, cli, tmp_path):
    name, prim, says = ASSET_DEFECTS[defect]
    argv, outputs = _asset_argv(role, bad(name), tmp_path)
    refused(cli(*argv), EXIT_INPUT, names=[name] + ([prim] if prim else []), says=says, outputs=outputs)


@pytest.mark.parametrize("role", ASSET_ROLES)
def test_weights_not_summing_to_one_warns(role, cli, tmp_path):
    argv, outputs = _asset_argv(role, bad("weights_not_normalized.usda"), tmp_path)
    warned(cli(*argv), names=["weights_not_normalized.usda", f"<{MESH}"], says=r"sum|normali[sz]", outputs=outputs)


# --- examples ----------------------------------------------------------------------------

EXAMPLE_DEFECTS = {
    # name: (file, exit code, things named, what it must say)
    "point_count_mismatch": ("example_point_count_mismatch.usda", EXIT_INPUT, [f"<{MESH}"], r"\b15\b.*\b16\b"),
    "no_animation": ("example_no_animation.usda", EXIT_INPUT, [f"<{SKEL}"], r"SkelAnimation|animationSource"),
    "anim_unknown_joint": ("anim_unknown_joint.usda", EXIT_INPUT, [f"<{ANIM_PRIM}"], r"Wirst"),
    "nan_points": ("example_nan_points.usda", EXIT_INPUT, [f"<{MESH}"], r"NaN"),
    "inf_points": ("example_inf_points.usda", EXIT_INPUT, [f"<{MESH}"], r"\binf\b"),
    "huge_points": ("example_huge_points.usda", EXIT_INPUT, [f"<{MESH}"],
                    r"time 2.*(1e\+?30|far|huge|absurd|magnitude|units|too large|outside)"),
    "duplicate_poses": ("duplicate_poses.usda", EXIT_FIT, ["duplicate_poses.usda@1", "duplicate_poses.usda@4"],
                        r"same pose"),
    "zero_scale_joint": ("zero_scale_joint.usda", EXIT_FIT, ["zero_scale_joint.usda", "Shoulder"],
                         r"time 2.*scale|scale.*time 2"),
    "all_bind_pose": ("examples_all_bind_pose.usda", EXIT_FIT, [f"<{MESH}"], r"bind pose"),
    "unsculpted": ("examples_unsculpted.usda", EXIT_FIT, [f"<{MESH}"], r"plain skinning|nothing to correct"),
    "stray_points": ("stray_points.usda", EXIT_INPUT, ["</Arm/Geo/TubeSculpt"], r"not a skinned mesh"),
}


@pytest.mark.parametrize("defect", list(EXAMPLE_DEFECTS))
def test_bad_examples(defect, cli, tmp_path):
    name, code, names, says = EXAMPLE_DEFECTS[defect]
    out = tmp_path / "corr.usda"
    names = names if any(name in n for n in names) else [name, *names]
    refused(cli("fit", ASSET, bad(name), "-o", out), code, names=names, says=says, outputs=[out])


def test_near_duplicate_poses_warn(cli, tmp_path):
    out = tmp_path / "corr.usda"
    warned(cli("fit", ASSET, bad("near_duplicate_poses.usda"), "-o", out),
           names=["near_duplicate_poses.usda@1", "near_duplicate_poses.usda@4", f"<{MESH}>"],
           says=r"apart", outputs=[out])


def test_duplicate_examples_across_files(cli, tmp_path):
    """The same EXAMPLES file given twice: every pose is duplicated."""
    copy = tmp_path / "again.usda"
    shutil.copy(EXAMPLES, copy)
    out = tmp_path / "corr.usda"
    refused(cli("fit", ASSET, EXAMPLES, copy, "-o", out), EXIT_FIT,
            names=["good_examples.usda@1", "again.usda@1"], says=r"same pose", outputs=[out])


# --- animations (eval --anim, pose --anim) -------------------------------------------------

@pytest.mark.parametrize(("command", "name", "prim", "says"), [
    ("pose", "anim_not_bound.usda", None, r"animationSource"),
    ("eval", "anim_not_bound.usda", f"<{SKEL}>", r"animationSource"),
    ("pose", "anim_no_time_samples.usda", f"<{ANIM_PRIM}>", r"no time samples"),
    ("eval", "anim_no_time_samples.usda", f"<{ANIM_PRIM}>", r"no time samples"),
    ("pose", "anim_unknown_joint.usda", f"<{ANIM_PRIM}>", r"Wirst"),
    ("eval", "anim_unknown_joint.usda", f"<{ANIM_PRIM}>", r"Wirst"),
])
def test_bad_animation(command, name, prim, says, cli, tmp_path):
    out = tmp_path / "out.usda"
    argv = ["pose", ASSET, "--anim", bad(name), "-o", out] if command == "pose" else \
        ["eval", ASSET, CORRECTIVES, "--anim", bad(name), "-o", out]
    refused(cli(*argv), EXIT_INPUT, names=[name] + ([prim] if prim else []), says=says, outputs=[out])


# --- correctives (eval) ----------------------------------------------------------------------

@pytest.mark.parametrize(("name", "prim", "says"), [
    ("psd_version_99.usda", f"<{MESH}.psd:version>", r"\b99\b.*(upgrade|not supported)"),
    ("psd_missing.usda", None, r"no psd: driver data"),
    ("psd_unknown_kernel.usda", f"<{MESH}", r"banana"),
    ("psd_groups_missing.usda", f"<{MESH}.psd:groups>", r"missing"),
    ("psd_unknown_driver.usda", f"<{MESH}.psd:main:drivers>", r"Knee"),
    ("psd_coefficients_truncated.usda", f"<{MESH}.psd:main:coefficients>", r"expected .* got 11"),
    ("psd_gate_group_missing.usda", f"<{MESH}.psd:main:gateGroups>", r"'l_elbow' is not one of psd:groups"),
    ("psd_gate_group_self.usda", f"<{MESH}.psd:main:gateGroups>", r"'main' is the group itself"),
])
def test_bad_correctives(name, prim, says, cli, tmp_path):
    out = tmp_path / "weights.usda"
    refused(cli("eval", ASSET, bad(name), "--anim", ANIM, "-o", out), EXIT_INPUT,
            names=[name] + ([prim] if prim else []), says=says, outputs=[out])


def test_examples_given_as_correctives(cli, tmp_path):
    """A plausible mix-up: EXAMPLES where CORRECTIVES belongs."""
    out = tmp_path / "weights.usda"
    refused(cli("eval", ASSET, EXAMPLES, "--anim", ANIM, "-o", out), EXIT_INPUT,
            names=["good_examples.usda"], says=r"psd", outputs=[out])


# --- options ---------------------------------------------------------------------------------

@pytest.mark.parametrize("frames", [
    "1-10", "10:1", "a:b", "1:", "", ":5", "1:2:3", "0.2:0.8",
])
def test_malformed_frames(frames, cli, tmp_path):
    out = tmp_path / "weights.usda"
    refused(cli("eval", ASSET, CORRECTIVES, "--anim", ANIM, "-o", out, "--frames", frames), EXIT_INPUT,
            names=["--frames"], outputs=[out])


@pytest.mark.parametrize(("option", "value"), [
    ("--driver", "Knee"),
    ("--mesh", "/Arm/Geo/Nope"),
    ("--sigma", "-1"),
    ("--smoothing", "nan"),
    ("--tolerance", "nan"),
    ("--tolerance", "-1"),
])
def test_bad_fit_option(option, value, cli, tmp_path):
    out = tmp_path / "corr.usda"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out, option, value), EXIT_INPUT, names=[value.lstrip("-")],
            says=re.escape(option.lstrip("-")), outputs=[out])


# --- deformers -------------------------------------------------------------------------------

def _deformer(name: str, factory: str = "make") -> str:
    return f"{os.path.join(DEFORMERS, name)}:{factory}"


RUNTIME = [f"<{MESH}>", "time 1"]
DEFORMER_CASES = {
    # id: (spec, names, what it must say)
    "raises": (_deformer("raises.py"), ["raises.py", *RUNTIME], r"RuntimeError: studio rig exploded"),
    "wrong_shape": (_deformer("wrong_shape.py"), ["wrong_shape.py", *RUNTIME], r"\(15, 3\).*\(16, 3\)"),
    "returns_nan": (_deformer("returns_nan.py"), ["returns_nan.py", *RUNTIME], r"NaN"),
    "factory_raises": (_deformer("factory_raises.py"), ["factory_raises.py", *RUNTIME], r"no rig data"),
    "import_error": (_deformer("import_error.py"), ["import_error.py"], r"psdbake_no_such_studio_module"),
    "not_callable": (_deformer("not_callable.py"), ["not_callable.py"], r"no callable 'make'"),
    "missing_factory": (_deformer("raises.py", "nope"), ["raises.py"], r"no callable 'nope'"),
    "missing_file": (_deformer("no_such_file.py"), ["no_such_file.py"], r"not found"),
    "missing_module": ("psdbake_no_such_module.deform:make", ["psdbake_no_such_module"], r"cannot import"),
    "no_factory_in_spec": ("just_a_module", ["just_a_module"], r"expected .*:factory"),
}


@pytest.mark.parametrize("case", list(DEFORMER_CASES))
def test_bad_deformer_fit(case, cli, tmp_path):
    spec, names, says = DEFORMER_CASES[case]
    out = tmp_path / "corr.usda"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out, "--deformer", spec), EXIT_DEFORMER, names=names, says=says,
            outputs=[out])


@pytest.mark.parametrize("case", ["raises", "wrong_shape", "returns_nan", "missing_module"])
def test_bad_deformer_pose(case, cli, tmp_path):
    spec, names, says = DEFORMER_CASES[case]
    out = tmp_path / "examples.usda"
    refused(cli("pose", ASSET, "--anim", POSES, "-o", out, "--deformer", spec), EXIT_DEFORMER, names=names,
            says=says, outputs=[out])


@pytest.mark.parametrize("case", ["raises", "factory_raises", "returns_nan", "missing_module"])
def test_bad_deformer_eval_points_cache(case, cli, tmp_path):
    spec, names, says = DEFORMER_CASES[case]
    w, pc = tmp_path / "weights.usda", tmp_path / "cache.usda"
    refused(cli("eval", ASSET, CORRECTIVES, "--anim", ANIM, "-o", w, "--points-cache", pc, "--deformer", spec),
            EXIT_DEFORMER, names=names, says=says, outputs=[w, pc])


# --- outputs ---------------------------------------------------------------------------------

@pytest.fixture
def inputs(tmp_path):
    """Copies of the good inputs, so a psdbake bug can never overwrite the fixtures."""
    folder = tmp_path / "in"
    folder.mkdir()
    for src in (ASSET, EXAMPLES, CORRECTIVES, POSES, ANIM):
        shutil.copy(src, folder)
    return {k: str(folder / os.path.basename(v)) for k, v in
            {"asset": ASSET, "examples": EXAMPLES, "correctives": CORRECTIVES, "poses": POSES, "anim": ANIM}.items()}


def _unchanged(paths) -> None:
    for copy in paths:
        original = {os.path.basename(p): p for p in (ASSET, EXAMPLES, CORRECTIVES, POSES, ANIM)}[os.path.basename(copy)]
        assert filecmp.cmp(copy, original, shallow=False), f"input {copy} was modified"


@pytest.mark.parametrize("which", ["asset", "examples", "symlink"])
def test_fit_output_is_an_input(which, inputs, cli, tmp_path):
    target = inputs["examples" if which == "symlink" else which]
    out = target
    if which == "symlink":
        out = str(tmp_path / "link.usda")
        os.symlink(target, out)
    refused(cli("fit", inputs["asset"], inputs["examples"], "-o", out), EXIT_OUTPUT,
            names=[os.path.basename(out)], says=r"also an input")
    _unchanged([inputs["asset"], inputs["examples"]])


@pytest.mark.parametrize("which", ["-o anim", "-o correctives", "--points-cache asset", "--points-cache -o"])
def test_eval_output_is_an_input(which, inputs, cli, tmp_path):
    option, what = which.split()
    w = str(tmp_path / "weights.usda")
    argv = ["eval", inputs["asset"], inputs["correctives"], "--anim", inputs["anim"]]
    if option == "-o":
        argv += ["-o", inputs[what]]
        out = inputs[what]
    else:
        out = w if what == "-o" else inputs[what]
        argv += ["-o", w, "--points-cache", out]
    refused(cli(*argv), EXIT_OUTPUT, names=[os.path.basename(out)], says=r"also an input|two outputs")
    _unchanged([inputs["asset"], inputs["correctives"], inputs["anim"]])
    if what != "-o":
        assert not os.path.exists(w)


def test_pose_output_is_an_input(inputs, cli):
    refused(cli("pose", inputs["asset"], "--anim", inputs["poses"], "-o", inputs["poses"]), EXIT_OUTPUT,
            names=["arm_poses.usda"], says=r"also an input")
    _unchanged([inputs["asset"], inputs["poses"]])


def test_output_folder_missing(cli, tmp_path):
    out = tmp_path / "no" / "such" / "corr.usda"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out), EXIT_OUTPUT, names=[str(out)], says=r"does not exist")
    assert not (tmp_path / "no").exists()


def test_output_folder_read_only(cli, tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    os.chmod(folder, stat.S_IRUSR | stat.S_IXUSR)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("a read-only folder is still writable for this user (root)")
        out = folder / "corr.usda"
        refused(cli("fit", ASSET, EXAMPLES, "-o", out), EXIT_OUTPUT, names=[str(out)], says=r"not writable",
                outputs=[out])
    finally:
        os.chmod(folder, stat.S_IRWXU)


def test_output_wrong_extension(cli, tmp_path):
    out = tmp_path / "corr.txt"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out), EXIT_OUTPUT, names=["corr.txt"], says=r"\.usda", outputs=[out])


def test_output_is_a_folder(cli, tmp_path):
    out = tmp_path / "corr.usda"
    out.mkdir()
    refused(cli("fit", ASSET, EXAMPLES, "-o", out), EXIT_OUTPUT, names=["corr.usda"], says=r"folder|directory")
    assert out.is_dir() and not os.listdir(out)


def test_report_folder_missing(cli, tmp_path):
    out, report = tmp_path / "corr.usda", tmp_path / "no" / "report.json"
    refused(cli("fit", ASSET, EXAMPLES, "-o", out, "--report", report), EXIT_OUTPUT, names=[str(report)],
            says=r"does not exist", outputs=[out, report])


def test_points_cache_folder_missing(cli, tmp_path):
    w, pc = tmp_path / "weights.usda", tmp_path / "no" / "cache.usda"
    refused(cli("eval", ASSET, CORRECTIVES, "--anim", ANIM, "-o", w, "--points-cache", pc), EXIT_OUTPUT,
            names=[str(pc)], says=r"does not exist", outputs=[w, pc])


@pytest.mark.parametrize("failure", ["duplicate_poses", "bad_deformer", "bad_asset"])
def test_failed_fit_keeps_old_output(failure, cli, tmp_path):
    """A failing fit leaves a pre-existing CORRECTIVES byte-identical (the old file is kept)."""
    out = tmp_path / "corr.usda"
    code, _, err = cli("fit", ASSET, EXAMPLES, "-o", out, "-q")
    assert code == 0, err
    before = out.read_bytes()
    examples, extra, expected = bad("duplicate_poses.usda"), [], EXIT_FIT
    if failure == "bad_deformer":
        examples, extra, expected = EXAMPLES, ["--deformer", DEFORMER_CASES["raises"][0]], EXIT_DEFORMER
    asset = bad("no_skelroot.usda") if failure == "bad_asset" else ASSET
    if failure == "bad_asset":
        examples, expected = EXAMPLES, EXIT_INPUT
    code, _, err = cli("fit", asset, examples, "-o", out, *extra)
    assert code == expected, err
    assert out.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["corr.usda"]


# --- the catalogue itself ----------------------------------------------------------------

#: Derived from psdbake's own fit: the RBF solve's last bits depend on the CPU's BLAS kernel
#: (measured: OpenBLAS's SkylakeX and Haswell kernels differ in the 16th digit of two coefficients).
FIT_DERIVED = ("good_correctives.usda", "correctives_", "psd_", "crate_")


def _tree(folder: str) -> set[str]:
    skip = {"make_bad.py", "__pycache__"}
    found = set()
    for here, dirs, files in os.walk(folder):
        dirs[:] = [d for d in dirs if d not in skip]
        found |= {os.path.relpath(os.path.join(here, f), folder) for f in files if f not in skip}
    return found


def test_catalogue_is_up_to_date(tmp_path):
    """fixtures/bad/ is exactly what make_bad.py writes (files, and bytes where deterministic)."""
    make_bad.generate(str(tmp_path))
    fresh, committed = _tree(str(tmp_path)), _tree(BAD)
    assert fresh == committed, "fixtures/bad/ is stale: run python fixtures/bad/make_bad.py"
    for rel in sorted(fresh):
        if rel.startswith(FIT_DERIVED):
            continue
        same = filecmp.cmp(tmp_path / rel, os.path.join(BAD, rel), shallow=False)
        assert same, f"fixtures/bad/{rel} is stale: run python fixtures/bad/make_bad.py"
