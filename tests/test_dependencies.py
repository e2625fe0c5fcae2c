"""The walk over an input's layers (``psdbake.usd.dependencies``) is remembered per file while
the file is unchanged, so a command that walks its inputs twice (checking its outputs, then
writing them) parses a large text layer once; a changed or just-written file is walked again."""

from __future__ import annotations

import os

import pytest

from psdbake.usd import dependencies

EMPTY = "#usda 1.0\n"
WITH_SUBLAYER = '#usda 1.0\n(\n    subLayers = [\n        @./b.usda@\n    ]\n)\n'


@pytest.fixture
def opened(monkeypatch) -> list[str]:
    """The files the walk opens (parses), in order."""
    seen: list[str] = []
    real = dependencies._open

    def counting(path, referrer, kind):
        seen.append(os.path.basename(path))
        return real(path, referrer, kind)

    monkeypatch.setattr(dependencies, "_open", counting)
    return seen


def _replace(path, text: str) -> None:
    """Write text to path as psdbake writes its outputs: a new file renamed over the old one."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def test_unchanged_file_is_walked_once(tmp_path, monkeypatch, opened):
    monkeypatch.setattr(dependencies, "SETTLED_SECONDS", 0.0)  # every file counts as settled
    a, b = tmp_path / "a.usda", tmp_path / "b.usda"
    a.write_text(EMPTY)
    b.write_text(EMPTY)
    assert dependencies.layer_files([str(a)]) == [os.path.realpath(a)]
    assert dependencies.layer_files([str(a)]) == [os.path.realpath(a)]
    assert opened == ["a.usda"]
    _replace(a, WITH_SUBLAYER)  # changed: walked again, its new sublayer found
    assert dependencies.layer_files([str(a)]) == sorted(os.path.realpath(p) for p in (a, b))
    assert opened == ["a.usda", "a.usda", "b.usda"]


def test_a_file_changed_just_now_is_walked_every_time(tmp_path, opened):
    """Within SETTLED_SECONDS of its last change a file could change again in the same
    timestamp tick, size included, and look the same: it is not remembered."""
    a = tmp_path / "a.usda"
    a.write_text(EMPTY)
    for _ in range(2):
        assert dependencies.layer_files([str(a)]) == [os.path.realpath(a)]
    assert opened == ["a.usda", "a.usda"]
