"""The package's source says why, not when: no comment or docstring narrates the history of a
change ("as it was before ...", "(issue 16)", "used to ...", "was 205"). Measurements and the
story of how a choice was made live in docs/decisions/, where they carry a date and a machine."""

from __future__ import annotations

import os
import re

from conftest import ROOT

HISTORY = re.compile(
    r"\bissues? \d+\b|\bused to\b|\bas it was\b|\b(?:was|were) \d|\bbefore (?:issue|the smooth)|\bthe solver before\b"
    r"|\bearlier psdbake\b(?! compare)|psdbake 0\.\d+ (?:did|had)\b|\(was [\d.]+",
    re.IGNORECASE,
)


def test_no_comment_narrates_history():
    found = []
    for here, dirs, files in os.walk(os.path.join(ROOT, "psdbake")):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(here, name)
                with open(path, encoding="utf-8") as fh:
                    for number, line in enumerate(fh, start=1):
                        if HISTORY.search(line):
                            found.append(f"{os.path.relpath(path, ROOT)}:{number}: {line.strip()}")
    assert not found, "history in the source (move it to docs/decisions/):\n" + "\n".join(found)


def test_the_pattern_finds_what_it_is_for():
    for text in ("as it was before the smooth start came first", "(issue 16)", "They used to take", "was 205 calls"):
        assert HISTORY.search(text), text
    assert not HISTORY.search("a non-empty folder must hold an earlier psdbake compare report")
