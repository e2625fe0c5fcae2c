"""A hostile environment: closed standard streams, file names that are not UTF-8, a working
folder deleted under the shell, paths over the kernel's limits. Each is one line and a
documented exit code (a closed stderr: the run goes on, its messages lost), never an
internal error."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import ROOT, fixture, refused

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")
EXIT_INPUT, EXIT_OUTPUT = 3, 6


@pytest.fixture(scope="module")
def complete(tmp_path_factory) -> bytes:
    out = tmp_path_factory.mktemp("ref") / "corr.usda"
    subprocess.run([PSDBAKE, "fit", ASSET, EXAMPLES, "-o", str(out), "-q"], check=True, cwd=ROOT)
    return out.read_bytes()


def _closing(*fds: int):
    def close() -> None:
        for fd in fds:
            os.close(fd)
    return close


@pytest.mark.parametrize("closed", [(2,), (1,), (0, 1, 2)], ids=["stderr", "stdout", "all"])
def test_closed_standard_streams_run_as_usual(closed, tmp_path, complete):
    """``fit 2>&-`` once crashed on ``sys.stderr.isatty()`` (exit 1, nothing written): now the
    closed stream is /dev/null, the fit writes the same bytes as a normal run and exits 0, and a
    closed stdout alone is said in one warning line."""
    out = tmp_path / "corr.usda"
    done = subprocess.run([PSDBAKE, "fit", ASSET, EXAMPLES, "-o", str(out)], cwd=ROOT, preexec_fn=_closing(*closed),
                          stdout=None if 1 in closed else subprocess.PIPE,
                          stderr=None if 2 in closed else subprocess.PIPE, text=True)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == complete
    if closed == (1,):
        assert done.stderr == "psdbake: warning: stdout is closed: the summary is not shown\n"
    assert [f for f in os.listdir(tmp_path) if ".tmp" in f] == []


@pytest.mark.parametrize("role", ["input", "output"])
def test_a_file_name_that_is_not_utf8_is_named_in_one_line(role, run, tmp_path):
    """``caf\\xe9.usda`` was an internal UnicodeEncodeError; USD takes UTF-8 paths only."""
    name = os.fsdecode(b"caf\xe9.usda")
    path = os.path.join(str(tmp_path), name)
    out = tmp_path / "corr.usda"
    if role == "input":
        with open(ASSET, "rb") as src, open(path, "wb") as dst:
            dst.write(src.read())
        argv, code, outputs = ["fit", path, EXAMPLES, "-o", out], EXIT_INPUT, [out]
    else:
        argv, code, outputs = ["fit", ASSET, EXAMPLES, "-o", path], EXIT_OUTPUT, [path]
    line = refused(run(*argv), code, names=["caf\\xe9.usda"], says="not UTF-8 text", outputs=outputs)
    assert "\\udce9" not in line


def test_a_relative_path_in_a_deleted_working_folder(run, tmp_path, monkeypatch):
    """The working folder deleted under the shell: relative paths cannot mean anything (an
    internal FileNotFoundError naming no file before); absolute ones still work."""
    gone = tmp_path / "gone"
    gone.mkdir()
    monkeypatch.chdir(gone)
    monkeypatch.setenv("PWD", str(gone))  # as the shell that cd'ed there says
    os.rmdir(gone)
    out = tmp_path / "corr.usda"
    refused(run("fit", "arm_lbs.usda", EXAMPLES, "-o", out), EXIT_INPUT, names=["arm_lbs.usda", str(gone)],
            says="working folder .* no longer exists", outputs=[out])
    code, _, err = run("fit", ASSET, EXAMPLES, "-o", out, "-q")
    assert code == 0, err


@pytest.mark.parametrize("role", ["input", "output"])
def test_paths_over_the_kernels_limits(role, run, tmp_path):
    """A folder path over 4,096 bytes was "does not exist"; a name over 255 bytes too."""
    deep = os.path.join(str(tmp_path), *["d" * 200] * 21, "x.usda")
    wide = os.path.join(str(tmp_path), "n" * 300 + ".usda")
    out = tmp_path / "corr.usda"
    code = EXIT_INPUT if role == "input" else EXIT_OUTPUT
    for path, says in ((deep, r"bytes long, over this system's limit of 4095 bytes \(PATH_MAX\)"),
                       (wide, r"a name in the path is 305 bytes long, over this system's limit of 255 bytes")):
        argv = ["fit", path, EXAMPLES, "-o", out] if role == "input" else ["fit", ASSET, EXAMPLES, "-o", path]
        refused(run(*argv), code, names=[path], says=says, outputs=[out])
