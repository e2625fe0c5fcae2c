"""The three commands end to end, as a user runs them."""

from __future__ import annotations

import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT, bake, corrective_weights, diagonal, fixture, generate, points, sculpt
from pxr import Sdf, Usd, UsdGeom

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
POSES, ANIM = fixture("arm_poses.usda"), fixture("arm_anim.usda")
SWIRL = os.path.join(ROOT, "tests", "data", "swirl_deformer.py") + ":factory"


def test_pose_writes_plain_skinning_and_the_pose(run, tmp_path):
    out = tmp_path / "to_sculpt.usda"
    code, stdout, err = run("pose", ASSET, "--anim", POSES, "-o", out)
    assert code == 0, err
    assert "3 time code" in stdout
    for t in (1.0, 2.0, 3.0):
        ours = sculpt(str(out), generate.MESH, t)
        # the pose layer alone (over ASSET) is enough for Pixar's bake to pose the same way
        pixar = points(bake([POSES, ASSET], t), generate.MESH, t)
        assert np.abs(ours - pixar).max() <= 1e-6 * diagonal(pixar)  # float32 round-off of both
    # fitting the unsculpted poses finds nothing to correct: a clear refusal
    code, _, err = run("fit", ASSET, out, "-o", tmp_path / "c.usda")
    assert code == 4 and "no example differs from plain skinning" in err
    for group in ("group 'Elbow' (Elbow)", "group 'Wrist' (Wrist)", "group 'combo_Elbow_Wrist' (Elbow, Wrist)"):
        assert group in err  # the groups a sculpt would make, and their joints
    assert not (tmp_path / "c.usda").exists()


def test_fit_report_and_summary(run, tmp_path):
    out, report = tmp_path / "corr.usda", tmp_path / "report.json"
    code, stdout, err = run("fit", ASSET, EXAMPLES, "-o", out, "--report", report)
    assert code == 0, err
    assert "wrote" in stdout and "max/diag" in stdout
    data = json.loads(report.read_text())
    ex = data["meshes"][0]["examples"]
    assert [e["time"] for e in ex] == [1.0, 2.0, 3.0]
    for e in ex:
        assert e["vertices_solved"] > 0 and e["evaluations"] > 0 and e["missed"] == 0
        assert e["max_residual_rel"] <= 1e-6
    # the elbow is sculpted alone, the wrist only with it: a group per joint and one for the pair
    assert {m["group"]: m["drivers"] for m in data["meshes"]} == {
        "Elbow": ["Shoulder/Elbow"], "Wrist": ["Shoulder/Elbow/Wrist"],
        "combo_Elbow_Wrist": ["Shoulder/Elbow", "Shoulder/Elbow/Wrist"]}
    # per group its role and the points it moves; per example what the terms explain
    assert {m["group"]: m["role"] for m in data["meshes"]} == {"Elbow": "joint", "Wrist": "joint",
                                                               "combo_Elbow_Wrist": "combination"}
    assert all(0 < m["vertices_moved"] <= m["points"] for m in data["meshes"])
    assert [e["time"] for e in data["explained"]] == [1.0, 2.0, 3.0]
    for e in data["explained"]:
        assert 0.0 <= e["interaction"] <= 1.0 and e["additive"] + e["interaction"] == pytest.approx(1.0)
    assert data["explained"][0]["interaction"] < 1e-9  # the elbow sculpted alone: its term is the sculpt
    assert "additive" in stdout and "interaction" in stdout and "points:" in stdout


@pytest.mark.slow
def test_outputs_are_byte_identical_across_runs(run, tmp_path):
    for ext in ("usda", "usdc"):
        outs = []
        for k in range(2):  # the same command line in two folders (the output records its command)
            (tmp_path / f"run{k}").mkdir(exist_ok=True)
            corr, weights = tmp_path / f"run{k}" / f"c.{ext}", tmp_path / f"run{k}" / f"w.{ext}"
            assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
            assert run("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "-q")[0] == 0
            outs.append((corr.read_bytes(), weights.read_bytes()))
        assert outs[0] == outs[1]


def test_eval_frames_and_points_cache_match_bakeskinning_of_the_stack(run, tmp_path):
    corr, weights, cache = tmp_path / "c.usda", tmp_path / "w.usda", tmp_path / "cache.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    code, _, err = run("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "--frames", "10:20", "--points-cache", cache)
    assert code == 0, err
    layer = Sdf.Layer.FindOrOpen(str(weights))
    times = layer.ListTimeSamplesForPath(Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights"))
    assert list(times) == [float(f) for f in range(10, 21)]
    for t in (10.0, 15.0, 20.0):
        pixar = points(bake([str(weights), ANIM, str(corr), ASSET], t), generate.MESH, t)
        cached = sculpt(str(cache), generate.MESH, t)
        assert np.abs(cached - pixar).max() <= 1e-6 * diagonal(pixar)
    # the cache needs no UsdSkel: its SkelRoot is an Xform
    stage = Usd.Stage.Open(str(cache))
    assert stage.GetPrimAtPath(generate.ROOT).GetTypeName() == "Xform"


def test_existing_blend_shapes_are_kept_everywhere(run, tmp_path):
    asset = tmp_path / "arm_flex.usda"
    generate.build_arm(str(asset), generate.ArmSpec(blend_shapes=True))
    poses = tmp_path / "poses.usda"
    generate.write_animation(str(poses), generate.EXAMPLE_POSES, blend_shapes={1.0: 0.5, 2.0: 1.0, 3.0: 0.0})
    sculpts = generate.bake_sculpt(str(asset), str(poses), [1.0, 2.0, 3.0], generate.example_offsets(generate.ArmSpec()))
    examples = tmp_path / "examples.usda"
    generate.write_examples(str(examples), str(poses), sculpts)
    corr, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    assert run("fit", asset, examples, "-o", corr, "-q")[0] == 0
    assert run("eval", asset, corr, "--anim", poses, "-o", weights, "-q")[0] == 0
    stage = Usd.Stage.Open(str(corr))
    channels = list(stage.GetPrimAtPath(generate.MESH).GetAttribute("skel:blendShapes").Get())
    assert channels[0] == "flex" and all(c.startswith("psd_") for c in channels[1:]) and len(channels) >= 4
    wlayer = Sdf.Layer.FindOrOpen(str(weights))
    anim = wlayer.GetPrimAtPath(generate.ANIM)
    assert anim.properties["blendShapes"].default[0] == "flex"
    for t, w in ((1.0, 0.5), (2.0, 1.0)):
        # the animation's own channel keeps its exact weight
        assert wlayer.QueryTimeSample(anim.properties["blendShapeWeights"].path, t)[0] == pytest.approx(w, abs=0)
        baked = points(bake([str(weights), _points_removed(examples), str(corr), str(asset)], t), generate.MESH, t)
        target = sculpts[t]
        assert np.abs(baked - target).max() <= 1e-5 * diagonal(target)


_KEEP = []


def _points_removed(examples) -> str:
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(str(examples)))
    prim = layer.GetPrimAtPath(generate.MESH)
    prim.RemoveProperty(prim.properties["points"])
    _KEEP.append(layer)
    return layer.identifier


def test_deformer_chain_in_pose_fit_eval(run, tmp_path):
    """Sculpts made through a non-linear deformer are inverted through it (no closed form)."""
    to_sculpt = tmp_path / "to_sculpt.usda"
    assert run("pose", ASSET, "--anim", POSES, "-o", to_sculpt, "--deformer", SWIRL, "-q")[0] == 0
    # an artist's sculpt: move a third of the vertices of each pose a little
    layer = Sdf.Layer.FindOrOpen(str(to_sculpt))
    path = Sdf.Path(generate.MESH).AppendProperty("points")
    rng = np.random.default_rng(4)
    for t in layer.ListTimeSamplesForPath(path):
        pts = np.array(layer.QueryTimeSample(path, t), dtype=np.float64)
        moved = rng.random(len(pts)) < 0.33
        pts[moved] += rng.normal(scale=0.01, size=(moved.sum(), 3))
        layer.SetTimeSample(path, t, pts.astype(np.float32).tolist())
    layer.Save()
    corr, report = tmp_path / "c.usda", tmp_path / "r.json"
    code, _, err = run("fit", ASSET, to_sculpt, "-o", corr, "--deformer", SWIRL, "--report", report, "-q")
    assert code == 0, err
    for ex in json.loads(report.read_text())["meshes"][0]["examples"]:
        assert ex["missed"] == 0 and ex["max_residual_rel"] <= 1e-5


@pytest.mark.slow
def test_console_script_and_module_entry_points():
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    for cmd in ([exe, "--help"], [sys.executable, "-m", "psdbake", "--version"]):
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([exe, "fit", "missing.usda", "nope.usda", "-o", "x.usda"], capture_output=True, text=True)
    assert proc.returncode == 3
    assert proc.stderr.strip().count("\n") == 0 and "Traceback" not in proc.stderr
    assert "missing.usda: file not found" in proc.stderr


def test_inputs_are_never_modified(run, tmp_path):
    before = {p: Path(p).read_bytes() for p in (ASSET, EXAMPLES, ANIM)}
    corr = tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    assert run("eval", ASSET, corr, "--anim", ANIM, "-o", tmp_path / "w.usda", "-q")[0] == 0
    assert {p: Path(p).read_bytes() for p in before} == before


@pytest.mark.slow
def test_jobs_do_not_change_the_output(run, tmp_path):
    """Examples solved in worker processes give byte-identical CORRECTIVES."""
    outs = []
    for jobs in ("1", "2"):
        (tmp_path / jobs).mkdir()
        out = tmp_path / jobs / "c.usdc"
        code, _, err = run("fit", ASSET, EXAMPLES, fixture("arm_lbs_examples.usda"), "-o", out, "-j", jobs, "-q")
        assert code == 4 and "same pose" in err  # the same file twice: duplicate poses, named
        code, _, err = run("fit", ASSET, EXAMPLES, "-o", out, "-j", jobs, "-q")
        assert code == 0, err
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


@pytest.mark.parametrize("space", [["--pose-space", "quaternion"], ["--pose-space", "swingTwist", "--twist-axis", "1", "0", "0"]])
def test_pose_spaces_are_stored_and_reproduced_by_eval(run, tmp_path, space):
    """Whatever the pose space, eval (reading only psd:) gives each example weight 1 at its
    own pose, and the round trip through BakeSkinning still reproduces the sculpts."""
    corr, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q", "--group", "main", *space)[0] == 0  # one cardinal RBF
    assert run("eval", ASSET, corr, "--anim", POSES, "-o", weights, "-q")[0] == 0
    b = corrective_weights(ASSET, corr, weights, generate.ANIM, (1.0, 2.0, 3.0))
    # float32 storage of channel weights (in [0, 1]) times scales of a few units: 1e-6
    np.testing.assert_allclose(np.stack([b[s] for s in sorted(b)], axis=1), np.eye(3), atol=1e-6)
    assert Usd.Stage.Open(str(corr)).GetPrimAtPath(generate.MESH).GetAttribute("psd:main:poseSpace").Get() == space[1]


def test_clamp_and_normalize_are_explicit_stored_options(run, tmp_path):
    plain, clamped = tmp_path / "p.usda", tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", plain, "-q", "--group", "main")[0] == 0  # one cardinal RBF
    assert run("fit", ASSET, EXAMPLES, "-o", clamped, "-q", "--group", "main", "--clamp-weights",
               "--normalize-weights")[0] == 0
    w = {}
    for name, corr in (("plain", plain), ("clamped", clamped)):
        out = tmp_path / f"w_{name}.usda"
        assert run("eval", ASSET, corr, "--anim", ANIM, "-o", out, "-q")[0] == 0
        layer = Sdf.Layer.FindOrOpen(str(out))
        path = Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights")
        written = np.array([layer.QueryTimeSample(path, t) for t in layer.ListTimeSamplesForPath(path)])
        assert written.min() >= 0.0 and written.max() <= 1.0  # client-safe channels, either way
        b = corrective_weights(ASSET, corr, out, generate.ANIM, layer.ListTimeSamplesForPath(path))
        w[name] = np.stack([b[s] for s in sorted(b)], axis=1)
    assert w["plain"].min() < 0.0  # cardinal Gaussian weights do go negative: nothing hides it by default
    assert w["clamped"].min() >= 0.0 and w["clamped"].sum(axis=1).max() <= 1.0 + 1e-6


def test_inspect_reports_what_a_file_holds(run, tmp_path):
    corr = tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q", "--group", "main")[0] == 0
    code, out, _ = run("inspect", corr, "--json")
    info = json.loads(out)
    assert code == 0 and info["correctives"][0]["mesh"] == generate.MESH
    assert info["correctives"][0]["drivers"] == ["Shoulder/Elbow", "Shoulder/Elbow/Wrist"]
    assert info["correctives"][0]["group"] == "main"
    group = info["correctives"][0]
    assert group["shapes"] == [f"psd_main_Geo_Tube_{k:02d}" for k in range(3)]
    assert sorted(group["offsets"]) == sorted(group["channels"])  # one BlendShape per written channel
    assert {c.rsplit("_", 1)[0] for c in group["channels"]} == set(group["shapes"])
    code, out, _ = run("inspect", EXAMPLES)
    assert code == 0 and "examples of </Arm/Geo/Tube> at time codes 1, 2, 3" in out
    code, out, _ = run("inspect", ASSET, "--json")
    assert json.loads(out)["meshes"][0]["influences"] == 4


# --- terminal mode: progress bars on a pseudo-terminal -----------------------------------

HIDE_CURSOR, SHOW_CURSOR = "\x1b[?25l", "\x1b[?25h"  # what click writes around a bar


def _on_terminal(argv: list[str], timeout: float = 120.0) -> tuple[int, str]:
    """Run the console script with stdout and stderr on a pseudo-terminal, as in a shell:
    (exit code, everything it printed, the terminal's CR LF turned back into LF)."""
    exe = os.path.join(os.path.dirname(sys.executable), "psdbake")
    master, slave = os.openpty()
    try:
        proc = subprocess.Popen([exe, *map(str, argv)], cwd=ROOT, stdin=subprocess.DEVNULL, stdout=slave, stderr=slave,
                                env={**os.environ, "TERM": "xterm"})
    finally:
        os.close(slave)  # the child holds its own copies: EOF (EIO) on master once it exits
    printed = b""
    deadline = time.monotonic() + timeout
    try:
        while True:
            ready, _, _ = select.select([master], [], [], max(0.0, deadline - time.monotonic()))
            assert ready, f"psdbake {argv[0]} still running after {timeout:g} s; printed {printed[-300:]!r}"
            try:
                data = os.read(master, 1 << 16)
            except OSError:  # EIO: no process has the terminal open any more
                break
            if not data:
                break
            printed += data
    finally:
        os.close(master)
        if proc.poll() is None:
            proc.kill()
        code = proc.wait(timeout=60)
    return code, printed.decode("utf-8", "replace").replace("\r\n", "\n")


def _assert_bars(text: str, bars: dict[str, int], lines: tuple[str, ...]) -> None:
    """Each bar is drawn, reaches its total and is closed right there (cursor shown, a new
    line) before anything else is printed; each of ``lines`` (the summary, a warning)
    starts on a line of its own, never run onto a bar ("48/48psdbake eval: ..."); the
    cursor that click hides while a bar is drawn is shown again at the end."""
    for label, total in bars.items():
        drawn = list(re.finditer(rf"{re.escape(label)}  \[[#-]+\]  (\d+)/{total}\b", text))
        assert drawn, f"no {label!r} bar to {total} in {text!r}"
        last = drawn[-1]
        assert last[1] == str(total), f"the {label!r} bar stops at {last[1]}/{total}"
        after = text[last.end():last.end() + 80]
        assert after.startswith(SHOW_CURSOR + "\n"), f"the {label!r} bar is not closed when it ends: {after!r}"
    for line in lines:
        found = [m.start() for m in re.finditer(re.escape(line), text)]
        assert found, f"{line!r} not printed: {text[-500:]!r}"
        for at in found:
            before = text[:at].removesuffix(SHOW_CURSOR)
            assert before == "" or before.endswith("\n"), f"{line!r} runs onto the bar: {text[max(0, at - 80):at + 40]!r}"
    assert HIDE_CURSOR in text, "no bar was drawn (stderr not seen as a terminal?)"
    assert text.rfind(HIDE_CURSOR) < text.rfind(SHOW_CURSOR), f"the cursor is left hidden: {text[-200:]!r}"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["eval", "eval --points-cache", "eval --chunk-size", "fit (warning)"])
def test_progress_bars_on_a_terminal(command, run, tmp_path):
    corr = tmp_path / "c.usda"
    assert run("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    if command == "eval":  # one bar, then the summary on stdout (the same terminal)
        argv = ["eval", ASSET, corr, "--anim", ANIM, "-o", tmp_path / "w.usda"]
        bars, lines = {"weights": 48}, ("psdbake eval: 48 frame(s)",)
    elif command == "eval --points-cache":  # two bars one after the other
        argv = ["eval", ASSET, corr, "--anim", ANIM, "-o", tmp_path / "w.usda", "--points-cache", tmp_path / "p.usda"]
        bars, lines = {"weights": 48, "points cache": 48}, ("psdbake eval: 48 frame(s)",)
    elif command == "eval --chunk-size":
        argv = ["eval", ASSET, corr, "--anim", ANIM, "-o", tmp_path / "w.usda", "--chunk-size", "20"]
        bars, lines = {"weights": 48}, ("psdbake eval: 3 of 3 chunk(s)",)
    else:  # heavy smoothing: a warning on stderr right after the bar, then the summary
        argv = ["fit", ASSET, EXAMPLES, "-o", tmp_path / "c2.usda", "--smoothing", "5"]
        bars, lines = {"fitting examples": 3}, ("psdbake: warning: ", "psdbake fit: 1 mesh(es)")
    code, text = _on_terminal(argv)
    assert code == 0, text
    _assert_bars(text, bars, lines)


def test_inspect_warns_of_a_layout_blender_misplaces(run, tmp_path):
    """The arm's mesh parent </Arm/Geo> has another world transform than its skeleton: Blender's
    USD import puts the mesh there (make interop measures 0.48 of the diagonal), so inspect
    warns, naming both prims; the character, whose parent and skeleton agree, gets no warning.
    Giving the parent the skeleton's world transform silences it."""
    code, out, err = run("inspect", ASSET)
    assert code == 0 and err.count("psdbake: warning:") == 1
    assert "</Arm/Geo/Tube>" in err and "</Arm/Geo>" in err and "</Arm/Skel>" in err
    code, out, err = run("inspect", fixture("character", "character.usda"), "--json")
    assert code == 0 and json.loads(out)["warnings"] == [] and "warning" not in err
    fixed = tmp_path / "arm_fixed.usda"
    shutil.copyfile(ASSET, fixed)  # edited as a copy: the fixture's layer stays as on disk for later tests
    stage = Usd.Stage.Open(str(fixed))
    cache = UsdGeom.XformCache()
    skel = cache.GetLocalToWorldTransform(stage.GetPrimAtPath(generate.SKEL))
    geo_parent = cache.GetParentToWorldTransform(stage.GetPrimAtPath("/Arm/Geo"))
    geo = UsdGeom.Xformable(stage.GetPrimAtPath("/Arm/Geo"))
    geo.ClearXformOpOrder()
    geo.AddTransformOp().Set(skel * geo_parent.GetInverse())  # world = local * parent (row vectors)
    stage.GetRootLayer().Save()
    code, out, _ = run("inspect", fixed, "--json")
    assert code == 0 and json.loads(out)["warnings"] == []


def test_a_real_characters_summary_names_each_group_once_in_a_readable_line(run, tmp_path):
    """CesiumMan's combination groups are named after every joint they combine (up to 190
    characters, 11 drivers): the summary shortens such names as the layer does (a prefix and a
    hash, so two groups never show alike), names at most a few drivers and, on a second fit, a
    few of the groups it replaced as it routinely does; ``-v`` shows every name whole."""
    from conftest import CESIUM, CESIUM_EXAMPLES

    out = tmp_path / "c.usda"
    code, first, err = run("fit", CESIUM, CESIUM_EXAMPLES, "-o", out)
    assert code == 0, err
    rows = [line.split()[0] for line in first.splitlines() if re.search(r"^    \S+ +(joint|combination) ", line)]
    assert len(rows) == len(set(rows)) == 34  # every group, each shown differently
    assert max(map(len, rows)) <= 48 and max(len(line) for line in first.splitlines()) < 300
    code, again, err = run("fit", CESIUM, CESIUM_EXAMPLES, "-o", out, "--force")
    assert code == 0, err
    (changes,) = [line for line in again.splitlines() if "groups: replaced" in line]
    assert changes.endswith(" and 26 more") and len(changes) < 300
    code, verbose, err = run("fit", CESIUM, CESIUM_EXAMPLES, "-o", out, "--force", "-v")
    assert code == 0, err
    longest = max((g for g in re.findall(r"combo_\w+", verbose)), key=len)
    assert len(longest) > 150 and f"    {longest} " in verbose  # whole, in the group table
