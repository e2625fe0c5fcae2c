"""The documentation stays true: README as a front page, the site builds with --strict, the
generated references cover what the code offers, and the benchmark pages match their records.

- the site (mkdocs.yml, docs/) builds with ``mkdocs build --strict``: no warning, no broken
  link or anchor, no page left out of the navigation;
- every command of ``psdbake --help`` and every option of ``psdbake COMMAND --help`` appears
  on the built CLI reference (generated from click by mkdocs-click);
- the API reference documents exactly ``psdbake.__all__``, by public names only;
- docs/benchmarks.md and docs/fidelity.md are what ``python -m benchmarks.pages`` makes of the
  committed records in benchmarks/results/;
- every repository path the README and docs/ name exists (so moving a module fails here until
  the documentation follows).
"""

from __future__ import annotations

import html
import os
import re
import subprocess
import sys

import pytest
from click.testing import CliRunner

from benchmarks import pages
from benchmarks import results as bench_results
from psdbake.cli import cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
README = os.path.join(ROOT, "README.md")


def _doc_files() -> list[str]:
    out = [README]
    for folder, _, files in os.walk(DOCS):
        out += [os.path.join(folder, f) for f in sorted(files) if f.endswith(".md")]
    return out


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        return f.read()


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> str:
    """The site built as ``make docs`` builds it (strict), into a temporary folder."""
    out = str(tmp_path_factory.mktemp("site"))
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", out], cwd=ROOT,
                          capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    warnings = [line for line in done.stderr.splitlines() if line.startswith(("WARNING", "ERROR"))]
    assert not warnings, "\n".join(warnings)
    return out


def _text(page: str) -> str:
    """A built page's text, tags removed (what a reader sees)."""
    return html.unescape(re.sub(r"<[^>]+>", " ", _read(page)))


def _help(args: list[str]) -> str:
    done = CliRunner().invoke(cli, [*args, "--help"], prog_name="psdbake")
    assert done.exit_code == 0, done.output
    return done.output


def _commands() -> list[str]:
    text = _help([])
    block = text.split("Commands:", 1)[1]
    return [line.split()[0] for line in block.splitlines() if line.startswith("  ") and line.split()]


def _options(help_text: str) -> set[str]:
    """Every flag in an ``--help`` text's Options section (``-o``, ``--output``, ...)."""
    block = help_text.split("Options:", 1)[1]
    flags = set()
    for line in block.splitlines():
        head = line.strip().split("  ")[0]  # the flags column, before the help text
        if line.startswith("  ") and head.startswith("-"):
            flags.update(re.findall(r"(?<![\w-])(--?[A-Za-z][\w-]*)", head))
    return flags


@pytest.mark.slow
def test_site_builds_strict_and_the_cli_reference_covers_help(site):
    """Every command and option ``--help`` prints is on the generated CLI reference."""
    text = _text(os.path.join(site, "reference", "cli", "index.html"))
    commands = _commands()
    assert {"pose", "sculpts", "fit", "eval", "mirror", "groups", "stack", "batch"} <= set(commands), commands
    missing = []
    for command in commands:
        if not re.search(rf"psdbake {re.escape(command)}\b", text):
            missing.append(f"command {command}")
        for flag in sorted(_options(_help([command]))):
            if not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", text):
                missing.append(f"{command} {flag}")
    assert not missing, f"on --help but not in docs/reference/cli.md's built page: {missing}"


def test_options_parser_sees_every_flag():
    """The helper above is itself checked: it finds short and long flags, and nothing from help text."""
    flags = _options(_help(["fit"]))
    assert {"-o", "--output", "--group", "--allow-degraded", "-j", "--jobs", "--force", "-h", "--help"} <= flags
    assert "--tolerance" in flags and "--strict" in flags
    assert not any(f.startswith("--poses") for f in flags)  # pose's option, not fit's


def test_api_reference_documents_exactly_the_public_names(site):
    import psdbake

    source = _read(os.path.join(DOCS, "reference", "api.md"))
    documented = re.findall(r"^::: psdbake\.(\w+)\s*$", source, flags=re.MULTILINE)
    assert len(documented) == len(set(documented)), "a name documented twice"
    public = set(psdbake.__all__) - {"__version__"}
    assert set(documented) == public, (sorted(public - set(documented)), sorted(set(documented) - public))
    built = _read(os.path.join(site, "reference", "api", "index.html"))
    for name in documented:
        assert f'id="psdbake.{name}"' in built, name


def test_docs_name_no_internal_module_for_mkdocstrings():
    """Module paths inside the package are internal (they are being regrouped): the API pages
    reference the top-level ``psdbake`` namespace and ``psdbake.cli`` only."""
    bad = []
    for path in _doc_files():
        for m in re.finditer(r"^\s*::: (psdbake(?:\.\w+)*)", _read(path), flags=re.MULTILINE):
            parts = m.group(1).split(".")
            if len(parts) > 2 or (len(parts) == 2 and parts[1] not in set(__import__("psdbake").__all__)):
                bad.append((os.path.relpath(path, ROOT), m.group(1)))
        for m in re.finditer(r":module: (\S+)", _read(path)):
            if m.group(1) != "psdbake.cli":
                bad.append((os.path.relpath(path, ROOT), m.group(1)))
    assert not bad, bad


def test_benchmark_pages_are_generated_from_the_committed_records():
    for path, text in pages.render_all().items():
        assert os.path.exists(path), f"{path}: missing; run python -m benchmarks.pages"
        assert _read(path) == text, f"{os.path.relpath(path, ROOT)} is stale: run python -m benchmarks.pages"


def test_every_record_has_date_machine_and_command():
    names = sorted(f[:-5] for f in os.listdir(bench_results.FOLDER) if f.endswith(".json"))
    shown = {name for _, _, sections in pages.PAGES.values() for name, _ in sections}
    assert set(names) == shown, "a results record that no page shows, or a page section without its record"
    for name in names:
        record = bench_results.load(os.path.join(bench_results.FOLDER, f"{name}.json"))
        assert record["command"].startswith(f"python -m benchmarks.{record['benchmark']}"), name
        assert record.get("raw") is not None or record.get("source"), f"{name}: figures with neither raw data nor source"


def test_a_record_without_its_machine_is_refused(tmp_path):
    record = {"benchmark": "x", "date": "2026-11-27", "machine": {"cores": 2}, "command": "python -m benchmarks.x",
              "about": "x", "tables": [{"title": "t", "columns": ["a"], "rows": [["1"]]}]}
    with pytest.raises(ValueError, match="machine without cpu_model"):
        bench_results.check(record)
    record["machine"]["cpu_model"] = "some CPU"
    bench_results.check(record)
    record["tables"][0]["rows"].append(["1", "2"])
    with pytest.raises(ValueError, match="row 2: 2 cells for 1 columns"):
        bench_results.check(record)


def test_a_page_shows_date_machine_and_command_under_every_table(tmp_path):
    record = {"benchmark": "startup", "date": "2026-01-02", "command": "python -m benchmarks.startup --runs 3",
              "machine": {"cpu_model": "Test CPU 9000", "cores": 3}, "about": "About it.",
              "tables": [{"title": "One", "columns": ["a | b"], "rows": [["x"]], "notes": ""},
                         {"title": "Two", "columns": ["c"], "rows": [["y"]], "date": "2025-12-31",
                          "command": "python -m benchmarks.startup --runs 1"}]}
    lines = pages.render_record(record, "Start-up")
    text = "\n".join(lines)
    assert "| a \\| b |" in text
    assert "*Measured 2026-01-02 on 3 cores, Test CPU 9000. Command: `python -m benchmarks.startup --runs 3`.*" in text
    assert "*Measured 2025-12-31 on 3 cores, Test CPU 9000. Command: `python -m benchmarks.startup --runs 1`.*" in text


_PATH = re.compile(r"(?<![\w./-])((?:psdbake|tests|benchmarks|fixtures|interop|docs)/[\w./-]*[\w/])")


def test_every_repository_path_the_docs_name_exists():
    missing = []
    for path in _doc_files():
        for m in _PATH.finditer(_read(path)):
            name = m.group(1).rstrip("/.")
            if "*" in name or "<" in name:
                continue
            if not os.path.exists(os.path.join(ROOT, name)):
                missing.append(f"{os.path.relpath(path, ROOT)}: {name}")
    assert not missing, "\n".join(missing)


def test_readme_is_a_front_page():
    text = _read(README)
    lines = text.splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines"
    assert "make test" in text and "make demo" in text
    links = re.findall(r"\]\((docs/[^)#]+)", text)
    assert links, "README links into docs/"
    for link in links:
        assert os.path.exists(os.path.join(ROOT, link)), link
    for command in ("pose", "sculpts", "fit", "mirror", "eval"):  # the loop in five commands
        assert f"psdbake {command} " in text, command


def _command_lines(text: str) -> list[str]:
    """Command lines of the shell code blocks (```sh): the ones that start with ``psdbake``, continuations joined."""
    out, fence = [], None
    for line in re.sub(r"\\\n\s*", " ", text).splitlines():
        if line.lstrip().startswith("```"):
            fence = line.strip()[3:] if fence is None else None
        elif fence in ("sh", "bash", "shell", "console") and line.lstrip().removeprefix("$ ").startswith("psdbake "):
            out.append(line.split("#")[0].strip().removeprefix("$ "))
    return out


def test_every_command_line_in_the_docs_runs_today():
    """Each ``psdbake COMMAND --flag ...`` in a code block names a command and flags that exist."""
    commands = set(_commands())
    flags = {c: _options(_help([c])) for c in commands}
    wrong, seen = [], 0
    for path in _doc_files():
        for line in _command_lines(_read(path)):
            seen += 1
            words = line.split()
            if words[1] not in commands:
                wrong.append(f"{os.path.relpath(path, ROOT)}: {line}  (no command {words[1]})")
                continue
            for word in words[2:]:
                flag = word.split("=")[0]
                if re.fullmatch(r"--?[A-Za-z][\w-]*", flag) and flag not in flags[words[1]]:
                    wrong.append(f"{os.path.relpath(path, ROOT)}: {line}  (no option {flag})")
    assert seen >= 10, seen
    assert not wrong, "\n".join(wrong)
