"""The output guard: no command can overwrite any file it reads.

Every command x every output x every way an input can reach a file: the input itself
composes it (as a sublayer, a reference or a payload), or the output is a symbolic or a
hard link to an input. Each case must be refused before any work (exit 6, one line naming
the output), with every input byte-identical and no file or temporary left behind.
"""

from __future__ import annotations

import os
import shutil

import pytest
from conftest import digest, fixture, refused

BAD = fixture("bad")
SOURCES = {
    "asset": os.path.join(BAD, "good_asset.usda"),
    "examples": os.path.join(BAD, "good_examples.usda"),
    "correctives": os.path.join(BAD, "good_correctives.usda"),
    "anim": fixture("arm_anim.usda"),
    "poses": fixture("arm_poses.usda"),
}
EXIT_OUTPUT = 6
WAYS = ["sublayer", "reference", "payload", "symlink", "hardlink"]

# command -> (argv template, the output options it writes); {role} is an input, {out} the output under test
COMMANDS = {
    "pose -o": (["pose", "{asset}", "--anim", "{poses}", "-o", "{out}"], ["asset", "poses"]),
    "fit -o": (["fit", "{asset}", "{examples}", "-o", "{out}"], ["asset", "examples"]),
    "eval -o": (["eval", "{asset}", "{correctives}", "--anim", "{anim}", "-o", "{out}"],
                ["asset", "correctives", "anim"]),
    "eval --points-cache": (["eval", "{asset}", "{correctives}", "--anim", "{anim}", "-o", "{other}",
                             "--points-cache", "{out}"], ["asset", "correctives", "anim"]),
    "eval --chunk-size -o": (["eval", "{asset}", "{correctives}", "--anim", "{anim}", "-o", "{out}",
                              "--chunk-size", "10", "--frames", "1:20"], ["asset", "correctives", "anim"]),
    "stack OUT": (["stack", "{asset}", "{correctives}", "{anim}", "-o", "{out}"], ["asset", "correctives", "anim"]),
}


def _wrapper(kind: str, target: str) -> str:
    """A layer that reads target through one composition arc."""
    name = os.path.basename(target)
    if kind == "sublayer":
        return f"#usda 1.0\n(\n    subLayers = [@./{name}@]\n)\n"
    arc = "references" if kind == "reference" else "payload"
    return f'#usda 1.0\n(\n    defaultPrim = "Arm"\n)\n\ndef "Arm" (\n    {arc} = @./{name}@</Arm>\n)\n{{\n}}\n'


def _case(tmp_path, command: str, role: str, way: str) -> tuple[list[str], str, list[str]]:
    """(argv, the output under test, every file of the case) for one combination."""
    template, _ = COMMANDS[command]
    files = {k: str(tmp_path / os.path.basename(v)) for k, v in SOURCES.items()}
    for k, v in SOURCES.items():
        shutil.copy(v, files[k])
    if way in ("symlink", "hardlink"):
        out = str(tmp_path / f"link_to_{role}.usda")
        (os.symlink if way == "symlink" else os.link)(files[role], out)
    else:
        out = files[role]  # the file the wrapper reaches is what the output would overwrite
        wrapper = tmp_path / f"wrap_{role}.usda"
        wrapper.write_text(_wrapper(way, out))
        files[role] = str(wrapper)
    values = {**files, "out": out, "other": str(tmp_path / "weights.usda")}
    argv = [a.format(**values) for a in template]
    every = [str(p) for p in tmp_path.iterdir()]
    return argv, out, every


@pytest.mark.parametrize(("command", "role", "way"), [
    pytest.param(c, r, w, id=f"{c.replace(' ', '_')}-{r}-{w}") for c, (_, roles) in COMMANDS.items()
    for r in roles for w in WAYS
])
def test_no_command_overwrites_what_it_reads(command, role, way, cli, tmp_path):
    argv, out, every = _case(tmp_path, command, role, way)
    before = digest(every)
    listing = sorted(os.listdir(tmp_path))
    refused(cli(*argv), EXIT_OUTPUT, names=[os.path.basename(out)], says=r"also an input", inputs=before)
    assert sorted(os.listdir(tmp_path)) == listing, "a failed run left a file behind"


@pytest.mark.parametrize("way", ["symlink", "hardlink", "same path"])
@pytest.mark.parametrize("target", ["deformer", "asset"])
def test_fit_report_never_replaces_an_input(target, way, cli, tmp_path):
    """--report is compared with every input too: the deformer's source and the asset."""
    deformer = tmp_path / "mydeformer.py"
    deformer.write_text("def make(stage, mesh, time):\n    return lambda points: points\n")
    asset = tmp_path / "asset.usda"
    shutil.copy(SOURCES["asset"], asset)
    source = deformer if target == "deformer" else asset
    report = tmp_path / "report.json"
    if way == "symlink":
        os.symlink(source, report)
    elif way == "hardlink":
        os.link(source, report)
    else:
        report = source
    before = digest([deformer, asset, report])
    expected = r"also an input" if way != "same path" else r"also an input|must end in \.json"
    refused(cli("fit", asset, SOURCES["examples"], "-o", tmp_path / "corr.usda", "--report", report,
                "--deformer", f"{deformer}:make"),
            EXIT_OUTPUT, names=[os.path.basename(str(report))], says=expected, inputs=before)
    assert not (tmp_path / "corr.usda").exists()


def test_report_needs_json_extension(cli, tmp_path):
    out, report = tmp_path / "corr.usda", tmp_path / "report.txt"
    refused(cli("fit", SOURCES["asset"], SOURCES["examples"], "-o", out, "--report", report), EXIT_OUTPUT,
            names=["report.txt"], says=r"\.json", outputs=[out, report])


def test_output_named_twice_is_refused(cli, tmp_path):
    out = tmp_path / "same.usda"
    refused(cli("eval", SOURCES["asset"], SOURCES["correctives"], "--anim", SOURCES["anim"], "-o", out,
                "--points-cache", out), EXIT_OUTPUT, names=["same.usda"], says=r"two outputs", outputs=[out])


def test_long_legal_output_name(cli, tmp_path):
    """A 250-byte file name is legal; the temporary file beside it must be too."""
    out = tmp_path / ("c" * 245 + ".usda")
    code, _, err = cli("fit", SOURCES["asset"], SOURCES["examples"], "-o", out, "-q")
    assert (code, err) == (0, "")
    assert out.exists() and not [f for f in os.listdir(tmp_path) if ".tmp" in f]


def test_guard_allows_unrelated_outputs(cli, tmp_path):
    """The guard is not over-eager: an output beside a composed input, under another name, is written."""
    wrapper = tmp_path / "asset_top.usda"
    shutil.copy(SOURCES["asset"], tmp_path / "good_asset.usda")
    wrapper.write_text(_wrapper("sublayer", str(tmp_path / "good_asset.usda")))
    out = tmp_path / "corr.usda"
    code, _, err = cli("fit", wrapper, SOURCES["examples"], "-o", out, "-q")
    assert (code, err) == (0, "")
    assert out.exists()
