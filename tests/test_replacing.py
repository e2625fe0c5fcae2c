"""What a TD's first day does to files that are already there: no command replaces a layer it
would empty of someone's work, another asset's layer, or a published file's permissions without
being asked; an eval written anew leaves no chunks of an earlier cut behind; ``inspect`` says
what each kind of output is; ``stack`` refuses or warns where its layers do not belong together.
(An outside audit of the command line found each of these; each test is one of its findings.)"""

from __future__ import annotations

import json
import os
import shutil
import stat
import sys

import pytest
from conftest import digest, fixture, refused, run_cli, warned
from pxr import Sdf

HUMANOID = fixture("humanoid", "humanoid.usda")
HUMANOID_EXAMPLES = fixture("humanoid", "humanoid_examples.usda")
HUMANOID_ANIM = fixture("humanoid", "humanoid_anim.usda")
CHARACTER = fixture("character", "character.usda")
CHARACTER_NECK = fixture("character", "character_neck_examples.usda")


def _ok(result) -> str:
    code, out, err = result
    assert code == 0, err
    assert "Traceback" not in out + err
    return out


def _groups(path) -> list[str]:
    info = json.loads(_ok(run_cli("inspect", path, "--json")))
    return sorted({c["group"] for c in info["correctives"]})


@pytest.fixture(scope="module")
def layers(tmp_path_factory):
    """The humanoid's correctives (one plain fit), the character's, and the humanoid's with a
    group renamed (a layer holding a group no plain fit of these examples writes)."""
    folder = tmp_path_factory.mktemp("replacing")
    humanoid, character, renamed = folder / "humanoid_c.usda", folder / "character_c.usda", folder / "renamed.usda"
    _ok(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", humanoid, "-q"))
    _ok(run_cli("fit", CHARACTER, CHARACTER_NECK, "-o", character, "-q"))
    shutil.copyfile(humanoid, renamed)
    _ok(run_cli("groups", renamed, "--rename", "Neck=neck_fix", "-q"))
    return {"humanoid": humanoid, "character": character, "renamed": renamed}


def test_mirror_onto_another_layer_that_it_would_empty_is_refused(layers, tmp_path):
    """``mirror -o OTHER`` writes CORRECTIVES's groups plus the mirrored ones: over a layer with
    a group it lacks (renamed there by the TD) that group would be lost; over another asset's
    layer every group would. Refused (exit 6) naming what would go, the file unchanged; --force
    replaces it."""
    target = tmp_path / "target.usda"
    shutil.copyfile(layers["renamed"], target)
    before = digest([target])
    refused(run_cli("mirror", HUMANOID, layers["humanoid"], "--joints", "L_=R_", "-o", target, "-q"), 6,
            names=[str(target), "neck_fix"], says="would drop", inputs=before)
    shutil.copyfile(layers["character"], target)
    before = digest([target])
    refused(run_cli("mirror", HUMANOID, layers["humanoid"], "--joints", "L_=R_", "-o", target, "-q"), 6,
            names=[str(target)], says="another asset's", inputs=before)
    _ok(run_cli("mirror", HUMANOID, layers["humanoid"], "--joints", "L_=R_", "-o", target, "-q", "--force"))
    assert _groups(target) == _groups(layers["humanoid"])


def test_mirror_onto_its_own_earlier_output_needs_no_force(layers, tmp_path):
    target = tmp_path / "mirrored.usda"
    _ok(run_cli("mirror", HUMANOID, layers["humanoid"], "--joints", "L_=R_", "-o", target, "-q"))
    first = target.read_bytes()
    _ok(run_cli("mirror", HUMANOID, layers["humanoid"], "--joints", "L_=R_", "-o", target, "-q"))
    assert target.read_bytes() == first


def test_groups_edit_onto_another_layer_that_it_would_empty_is_refused(layers, tmp_path):
    target = tmp_path / "target.usda"
    shutil.copyfile(layers["renamed"], target)
    before = digest([target])
    refused(run_cli("groups", layers["humanoid"], "--remove", "L_Knee", "-o", target), 6,
            names=[str(target), "neck_fix"], says="would drop", inputs=before)
    _ok(run_cli("groups", layers["humanoid"], "--remove", "L_Knee", "-o", target, "--force", "-q"))
    assert "L_Knee" not in _groups(target) and "Neck" in _groups(target)


def test_fit_onto_another_assets_layer_is_an_output_refusal_that_force_overrides(layers, tmp_path):
    """Not bad input (exit 3, as it was): the output is another asset's layer, exit 6 like any
    output that is not this command's own; --force replaces it."""
    target = tmp_path / "target.usda"
    shutil.copyfile(layers["character"], target)
    before = digest([target])
    refused(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", target, "-q"), 6,
            names=[str(target)], says="another asset's.*--force", inputs=before)
    refused(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "--group", "Neck", "-o", target, "-q"), 6,
            names=[str(target)], says="another asset's.*--force", inputs=before)
    _ok(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", target, "-q", "--force"))
    assert _groups(target) == _groups(layers["humanoid"])


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX permissions")
def test_a_replaced_output_keeps_its_permissions(layers, tmp_path):
    target = tmp_path / "c.usda"
    shutil.copyfile(layers["humanoid"], target)
    os.chmod(target, 0o660)  # shared with the department's group
    _ok(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", target, "-q"))
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o660
    os.chmod(target, 0o444)  # published: read-only
    refused(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", target, "-q"), 6, names=[str(target)], says="read-only")
    _ok(run_cli("fit", HUMANOID, HUMANOID_EXAMPLES, "-o", target, "-q", "--force"))
    assert stat.S_IMODE(os.stat(target).st_mode) == 0o444  # still published


def _chunks(folder, stem: str) -> list[str]:
    return sorted(n for n in os.listdir(folder) if n.startswith(stem + ".") and n != stem + ".usda")


def test_eval_written_anew_removes_the_chunks_of_an_earlier_cut(layers, tmp_path):
    """A chunked eval, then the same with another --chunk-size, then unchunked: each run leaves
    only its own files beside the output; a file of someone else's named like a chunk stays."""
    out = tmp_path / "w.usda"
    foreign = tmp_path / "w.f0001-0005.usda"
    foreign.write_text("#usda 1.0\n")  # not psdbake's: never removed
    args = ("eval", HUMANOID, layers["humanoid"], "--anim", HUMANOID_ANIM, "-o", out, "-q")
    _ok(run_cli(*args, "--chunk-size", "25"))
    first = [n for n in _chunks(tmp_path, "w") if n != foreign.name]
    assert len(first) == 5  # four chunks of the 100 frames and the clip manifest
    _ok(run_cli(*args, "--chunk-size", "40"))
    second = [n for n in _chunks(tmp_path, "w") if n != foreign.name]
    assert len(second) == 4 and not set(first) & set(second) - {"w.clipmanifest.usda"}
    _ok(run_cli(*args))
    assert _chunks(tmp_path, "w") == [foreign.name]


def test_an_earlier_chunk_read_as_an_input_is_not_removed(layers, tmp_path):
    """Inputs are never modified: an old chunk given as --anim while its manifest's output is
    written anew stays where it is."""
    out = tmp_path / "w.usda"
    _ok(run_cli("eval", HUMANOID, layers["humanoid"], "--anim", HUMANOID_ANIM, "-o", out, "-q", "--chunk-size", "50"))
    chunk = tmp_path / "w.f0001-0050.usda"
    anim = Sdf.Layer.CreateNew(str(tmp_path / "anim_with_old_weights.usda"))  # the shot, the old weights over it
    for sub in (chunk.name, HUMANOID_ANIM):
        anim.subLayerPaths.append(sub)
    anim.Save()
    before = digest([chunk])
    _ok(run_cli("eval", HUMANOID, layers["humanoid"], "--anim", anim.realPath, "-o", out, "-q"))
    assert digest([chunk]) == before


def test_inspect_names_each_kind_of_output(layers, tmp_path):
    """inspect says what a psdbake file is and what it holds: a WEIGHTS layer its animation's
    channels and frames, a points cache its points over time (not 'examples'), a stack its
    layers with their roles (it crashed on a stack)."""
    weights, cache, view = tmp_path / "w.usda", tmp_path / "cache.usda", tmp_path / "view.usda"
    _ok(run_cli("eval", HUMANOID, layers["humanoid"], "--anim", HUMANOID_ANIM, "-o", weights, "--points-cache", cache,
                "-q"))
    _ok(run_cli("stack", HUMANOID, layers["humanoid"], HUMANOID_ANIM, weights, "-o", view, "-q"))
    anim = Sdf.Layer.FindOrOpen(HUMANOID_ANIM)
    frames = len(anim.ListAllTimeSamples())
    out = _ok(run_cli("inspect", weights))
    assert out.startswith(f"{weights}: WEIGHTS layer")
    assert f"{frames} samples" in out and "blend-shape weights over </Humanoid/Skel/Anim>" in out
    out = _ok(run_cli("inspect", cache))
    assert out.startswith(f"{cache}: points cache") and f"{frames} samples" in out and "examples of" not in out
    out = _ok(run_cli("inspect", view))
    assert out.startswith(f"{view}: stack")
    assert "w.usda (WEIGHTS) > " in out and "humanoid.usda (ASSET)" in out and "(CORRECTIVES)" in out
    info = json.loads(_ok(run_cli("inspect", view, "--json")))
    assert [layer["role"] for layer in info["layers"]] == ["weights", "anim", "correctives", "asset"]
    # a stack given where its CORRECTIVES layer belongs: said so, not "holds no correctives"
    refused(run_cli("mirror", HUMANOID, view, "--joints", "L_=R_", "-o", tmp_path / "m.usda"), 3,
            names=[str(view)], says="a stack, not a CORRECTIVES layer", outputs=[tmp_path / "m.usda"])
    # examples spelled out over an asset that does not skin them: said, not silently skipped
    warned(run_cli("inspect", HUMANOID_EXAMPLES, "--asset", CHARACTER), names=[CHARACTER], says="skins none")


def test_stack_refuses_another_assets_correctives_and_warns_of_weights_over_another_shot(layers, tmp_path):
    view = tmp_path / "view.usda"
    refused(run_cli("stack", CHARACTER, layers["humanoid"], "-o", view), 3,
            names=[str(layers["humanoid"]), CHARACTER], says="does not skin")
    weights = tmp_path / "w_examples.usda"  # evaluated over the examples' poses, stacked over the shot
    _ok(run_cli("eval", HUMANOID, layers["humanoid"], "--anim", HUMANOID_EXAMPLES, "-o", weights, "-q"))
    warned(run_cli("stack", HUMANOID, layers["humanoid"], HUMANOID_ANIM, weights, "-o", view, "-q"),
           names=[str(weights)], says="evaluated over .*humanoid_examples.usda")
    refused(run_cli("stack", HUMANOID, layers["humanoid"], HUMANOID_ANIM, weights, "-o", tmp_path / "strict.usda",
                    "--strict"), 3, names=[str(weights)], says="--strict")


def test_json_summaries_carry_the_warnings(layers, tmp_path):
    weights = tmp_path / "w_examples.usda"
    _ok(run_cli("eval", HUMANOID, layers["humanoid"], "--anim", HUMANOID_EXAMPLES, "-o", weights, "-q"))
    code, out, err = run_cli("stack", HUMANOID, layers["humanoid"], HUMANOID_ANIM, weights, "-o", tmp_path / "v.usda",
                             "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert len(summary["warnings"]) == 1 and summary["warnings"][0] in err

