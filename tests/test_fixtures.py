"""The committed fixtures are exactly what fixtures/generate.py makes (no drift)."""

from __future__ import annotations

import os

from conftest import FIXTURES, generate


def test_generator_reproduces_committed_fixtures(tmp_path):
    os.makedirs(tmp_path / "cesiumman")
    os.symlink(os.path.join(FIXTURES, "cesiumman", generate.CESIUM), tmp_path / "cesiumman" / generate.CESIUM)
    written = generate.generate(str(tmp_path))
    assert len(written) == 18
    for path in written:
        rel = os.path.relpath(path, tmp_path)
        with open(path, "rb") as new, open(os.path.join(FIXTURES, rel), "rb") as old:
            assert new.read() == old.read(), f"fixtures/{rel} is stale: run make fixtures"
