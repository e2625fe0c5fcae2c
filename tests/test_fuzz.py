"""A bounded fuzz run of each mode in make test (make fuzz runs 20,000 cases of each): every
mutated input ends in finite output or a clean one-line refusal, inputs byte-identical and no
file left; never an internal error, traceback, C++ location, crash or hang. Cases run in
worker subprocesses (tests/fuzz.py), so a crash inside USD fails one case, not the session."""

from __future__ import annotations

import pytest

from tests import fuzz

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)


# cases per mode: together under a minute on two cores (a usdc case costs most: psdbake
# reads every crate input in a probe process of its own)
BOUNDED = {"text": 150, "sdf": 500, "usdc": 80}


@pytest.mark.parametrize("mode", fuzz.MODES)
def test_mutated_inputs_end_cleanly(mode):
    outcomes = fuzz.run(cases=BOUNDED[mode], seed=2026, mode=mode)
    assert len(outcomes) == BOUNDED[mode]
    failures = [f"case {o.case} ({o.target}): {o.what}\n    mutations: {'; '.join(o.mutations)}\n"
                f"    command: {o.command}\n    replay: python -m tests.fuzz --mode {mode} --seed 2026 --only {o.case}"
                for o in outcomes if not o.ok]
    assert not failures, f"{len(failures)} failures:\n" + "\n".join(failures[:20])
    # the mutations do reach both outcomes, so the run tests something
    assert any(o.what.startswith("eval ok") for o in outcomes)
    assert any("refused" in o.what for o in outcomes)
    skipped = [o for o in outcomes if o.what.startswith("skipped")]
    assert len(skipped) < BOUNDED[mode] * 0.02, skipped[:3]


@pytest.mark.parametrize("mode", ["sdf", "usdc"])
def test_cases_replay(mode):
    """A case's mutations depend only on (mode, seed, case): --only N replays what a run did."""
    run = {o.case: o for o in fuzz.run(cases=4, seed=7, mode=mode, first=40)}
    again = fuzz.run(cases=0, seed=7, mode=mode, only=43)[0]
    assert again.mutations == run[43].mutations and again.what == run[43].what
    other = fuzz.run(cases=0, seed=8, mode=mode, only=43)[0]
    assert other.mutations != run[43].mutations


def test_crate_regions_cover_the_file():
    """usdc mutations aim at the value area and the sections, found from the table of contents."""
    data = fuzz._crates()["asset"]
    regions = fuzz.crate_regions(data)
    assert {"header", "values", "TOKENS", "PATHS", "SPECS", "toc"} <= set(regions)
    assert regions["values"][0] == 88 and regions["values"][1] > 1000
