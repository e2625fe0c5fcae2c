"""Two writers of one output, interleaved at exact moments (tests/pausing.py): every output is
byte-identical to what the two runs give one after the other, in the order the interleaving
forces, or the later run is refused (exit 6) and the output is the earlier run's alone.

The contract (docs/reference/failure.md, "Several runs writing one output"): every commit renames its outputs under the lock
of their folders, so two commits never interleave; a read-modify-write (``fit``, ``fit
--group``, ``mirror`` in place, a chunked eval's manifest) reads the file afresh under that
lock and holds it until its rename. Which run comes first is decided by the lock, never by
whose copy of the file is older. No sleeps: a run is held at a marker, or seen waiting for the
lock in /proc/locks.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pausing
import pytest
from conftest import fixture, run_cli, stitched_chunks

HUMANOID, HUMANOID_EXAMPLES = fixture("humanoid", "humanoid.usda"), fixture("humanoid", "humanoid_examples.usda")
ARM, ARM_EXAMPLES, ARM_ANIM = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), fixture("arm_anim.usda")
EXIT_OUTPUT = 6

pytestmark = pytest.mark.slow  # psdbake processes racing each other: make test runs them, make test-fast does not


class Held:
    """One psdbake run, held at the moments given."""

    def __init__(self, folder: Path, name: str, moments: tuple[str, ...], *args) -> None:
        self.markers = {m: str(folder / f".{name}-{m}") for m in moments}
        self.proc = subprocess.Popen(pausing.argv(self.markers, *map(str, args)), stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)

    def at(self, moment: str) -> Held:
        pausing.wait_for(self.markers[moment], self.proc, moment)
        return self

    def go(self, moment: str) -> Held:
        pausing.release(self.markers[moment])
        return self

    def blocked(self) -> Held:
        """Until the run waits for a folder lock another run holds."""
        pausing.wait_blocked(self.proc)
        return self

    def done(self) -> tuple[int, str]:
        _, err = self.proc.communicate(timeout=300)
        return self.proc.returncode, err


def _run(*args) -> tuple[int, str]:
    code, _, err = run_cli(*args)
    return code, err


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under folder by relative path (no temporary may be left; markers left out), the
    folder's own path in them written FOLDER (an OBJ manifest names its EXAMPLES by absolute path)."""
    found = {}
    for here, _, names in os.walk(folder):
        assert not [n for n in names if ".tmp" in n], names
        for n in names:
            if not n.startswith("."):
                data = (Path(here) / n).read_bytes().replace(str(folder).encode(), b"FOLDER")
                found[os.path.relpath(os.path.join(here, n), folder)] = data
    return dict(sorted(found.items()))


def _serial(folder: Path, initial: dict[str, bytes], *commands) -> tuple[list[int], dict[str, bytes]]:
    """The runs one after the other, in folder holding initial: (exit codes, files after)."""
    folder.mkdir(parents=True)
    for name, data in initial.items():
        (folder / name).write_bytes(data)
    codes = [_run(*command(folder))[0] for command in commands]
    return codes, _files(folder)


# --- CORRECTIVES: fit --group, plain fit and mirror in place -------------------------------------

def _fit_group(group: str, driver: str):
    return lambda d: ("fit", HUMANOID, HUMANOID_EXAMPLES, "--group", group, "--driver", driver, "-o", d / "c.usda",
                      "-q")


def _mirror(d):
    return ("mirror", HUMANOID, d / "c.usda", "--joints", "L_=R_", "-o", d / "c.usda", "-q")


def _plain_fit(d, kernel: str = "gaussian"):
    """A plain fit (no --group): one group, ``main``, driven by the left elbow and knee."""
    return ("fit", HUMANOID, HUMANOID_EXAMPLES, "--driver", "L_Elbow", "--driver", "L_Knee", "--kernel", kernel,
            "-o", d / "c.usda", "-q")


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> dict[str, bytes]:
    """A CORRECTIVES layer with one group, L_Elbow, fitted with --group."""
    folder = tmp_path_factory.mktemp("base") / "run"
    folder.mkdir()
    assert _run(*_fit_group("L_Elbow", "L_Elbow")(folder))[0] == 0
    return _files(folder)


def _start(folder: Path, initial: dict[str, bytes]) -> Path:
    folder.mkdir(parents=True)
    for name, data in initial.items():
        (folder / name).write_bytes(data)
    return folder


def test_mirror_in_place_waiting_for_a_group_fit_keeps_its_group(base, tmp_path):
    """Issue 24's data loss: ``fit --group Neck`` commits while ``mirror ... -o`` (in place) waits
    for the lock, and both exit 0. Mirror's copy of the layer, loaded before it waited, lacked the
    Neck group, and the layer it wrote dropped it. Mirror now reads the layer afresh under the lock
    (and holds the lock from that read to its rename): the result is the two runs in that order."""
    race = _start(tmp_path / "a" / "race", base)
    fit = Held(race, "fit", ("commit",), *_fit_group("Neck", "Neck")(race)).at("commit")  # written, lock held
    mirror = Held(race, "mirror", (), *_mirror(race)).blocked()  # its inputs loaded: waits for the lock
    fit.go("commit")
    assert fit.done()[0] == 0 and mirror.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", base, _fit_group("Neck", "Neck"), _mirror)
    assert codes == [0, 0]
    assert _files(race) == expected


def test_a_group_fit_waiting_for_mirror_in_place_keeps_the_mirrored_groups(base, tmp_path):
    """The other order: mirror holds the lock (read, not yet written) while the fit waits to
    commit; the fit then merges its group into mirror's layer."""
    race = _start(tmp_path / "a" / "race", base)
    mirror = Held(race, "mirror", ("locked",), *_mirror(race)).at("locked")
    fit = Held(race, "fit", (), *_fit_group("Neck", "Neck")(race)).blocked()
    mirror.go("locked")
    assert mirror.done()[0] == 0 and fit.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", base, _mirror, _fit_group("Neck", "Neck"))
    assert codes == [0, 0]
    assert _files(race) == expected


def _remove_group(group: str):
    return lambda d: ("groups", d / "c.usda", "--remove", group, "--asset", HUMANOID, "-q")


def test_groups_remove_in_place_waiting_for_a_group_fit(base, tmp_path):
    """``psdbake groups --remove`` in place is a read-modify-write too: waiting while a group fit
    commits, it removes its group from the fit's layer, not from its own stale copy."""
    race = _start(tmp_path / "a" / "race", base)
    fit = Held(race, "fit", ("commit",), *_fit_group("Neck", "Neck")(race)).at("commit")
    remove = Held(race, "remove", (), *_remove_group("L_Elbow")(race)).blocked()
    fit.go("commit")
    assert fit.done()[0] == 0 and remove.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", base, _fit_group("Neck", "Neck"), _remove_group("L_Elbow"))
    assert codes == [0, 0]
    assert _files(race) == expected


def test_two_group_fits_both_land(base, tmp_path):
    """Group updates: the second fit waits at its commit and merges into the first's layer."""
    race = _start(tmp_path / "a" / "race", base)
    first = Held(race, "first", ("commit",), *_fit_group("Neck", "Neck")(race)).at("commit")
    second = Held(race, "second", (), *_fit_group("L_Knee", "L_Knee")(race)).blocked()
    first.go("commit")
    assert first.done()[0] == 0 and second.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", base, _fit_group("Neck", "Neck"),
                              _fit_group("L_Knee", "L_Knee"))
    assert codes == [0, 0]
    assert _files(race) == expected


@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> dict[str, bytes]:
    """A CORRECTIVES layer from a plain fit (all its groups are a plain fit's)."""
    folder = tmp_path_factory.mktemp("plain") / "run"
    folder.mkdir()
    assert _run(*_plain_fit(folder, "inverse_quadratic"))[0] == 0
    return _files(folder)


@pytest.mark.parametrize("first", ["plain", "group"])
def test_a_plain_fit_and_a_group_fit_serialise(first, plain, tmp_path):
    """Issue 24: a plain ``fit -o c.usda`` racing ``fit --group Neck -o c.usda`` both exited 0 and
    the plain fit's layer was replaced by the old groups (the group fit had read them first). Now
    whichever commits first, the other reads its result under the lock: plain then group gives
    the plain fit's layer with the group merged in; group then plain refuses the plain fit (exit 6:
    it would drop the --group fit's group) and leaves the group fit's layer."""
    commands = {"plain": _plain_fit, "group": _fit_group("Neck", "Neck")}
    second = "group" if first == "plain" else "plain"
    race = _start(tmp_path / "a" / "race", plain)
    held = Held(race, first, ("commit",), *commands[first](race)).at("commit")
    waiting = Held(race, second, (), *commands[second](race)).blocked()
    held.go("commit")
    codes = [held.done()[0], waiting.done()[0]]
    expected_codes, expected = _serial(tmp_path / "b" / "race", plain, commands[first], commands[second])
    assert codes == expected_codes == ([0, 0] if first == "plain" else [0, EXIT_OUTPUT])
    assert _files(race) == expected


# --- eval: WEIGHTS and points cache; chunked evals into one manifest ----------------------------

@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> dict[str, Path]:
    """Two CORRECTIVES of the arm (two kernels): two shots of one animation."""
    folder = tmp_path_factory.mktemp("shots")
    out = {}
    for kernel in ("gaussian", "inverse_quadratic"):
        out[kernel] = folder / f"{kernel}.usda"
        assert _run("fit", ARM, ARM_EXAMPLES, "--kernel", kernel, "-o", out[kernel], "-q")[0] == 0
    return out


def _eval(correctives: Path, *extra):
    return lambda d: ("eval", ARM, correctives, "--anim", ARM_ANIM, "-o", d / "w.usda", "--frames", "1:12", "-q",
                      *extra)


def test_weights_and_points_cache_come_from_one_run(shots, tmp_path):
    """Issue 24: interleaved ``eval --points-cache`` runs could leave the weights of one and the
    cache of the other. The first is held after renaming its WEIGHTS (its cache not yet renamed);
    the second waits for the folder lock instead of renaming both of its files in between: both
    files end up the second run's."""
    first = _eval(shots["gaussian"], "--points-cache", "CACHE")
    second = _eval(shots["inverse_quadratic"], "--points-cache", "CACHE")

    def command(make, d):
        return [str(d / "c.usda") if a == "CACHE" else a for a in make(d)]

    race = _start(tmp_path / "a" / "race", {})
    held = Held(race, "first", ("rename",), *command(first, race)).at("rename")
    assert [n for n in sorted(os.listdir(race)) if not n.startswith(".")] == ["w.usda"]  # the cache not yet renamed
    waiting = Held(race, "second", (), *command(second, race)).blocked()
    held.go("rename")
    assert held.done()[0] == 0 and waiting.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", {}, lambda d: command(first, d), lambda d: command(second, d))
    assert codes == [0, 0]
    assert _files(race) == expected
    alone = _serial(tmp_path / "c" / "race", {}, lambda d: command(second, d))[1]
    assert expected == alone


def _chunk(correctives: Path, k: int):
    return _eval(correctives, "--chunk-size", "6", "--chunk", str(k))


def test_chunked_evals_of_two_shots_never_share_a_manifest(shots, tmp_path):
    """Issue 24: chunked evals of two shots into one output left a manifest stitching chunks of
    both. A chunk of shot B arriving while shot A's chunks are being written is refused (exit 6);
    A's chunks all land and the output is A's complete run. Once A is complete, B starts the
    manifest over, and the manifest stitches B's chunks only."""
    a, b = shots["gaussian"], shots["inverse_quadratic"]
    race = _start(tmp_path / "a" / "race", {})
    a1 = Held(race, "a1", ("commit",), *_chunk(a, 1)(race)).at("commit")
    b1 = Held(race, "b1", (), *_chunk(b, 1)(race)).blocked()
    a1.go("commit")
    assert a1.done()[0] == 0
    code, err = b1.done()
    assert code == EXIT_OUTPUT and err.count("\n") == 1, err
    assert f"psdbake: error: {race / 'w.usda'}: the manifest of another shot, 1 of its 2 chunk(s) written so far" in err
    assert _run(*_chunk(a, 2)(race))[0] == 0
    whole_a = _serial(tmp_path / "b" / "race", {}, lambda d: _eval(a, "--chunk-size", "6")(d))[1]
    assert _files(race) == whole_a
    # A complete: B starts over, its manifest stitching its own chunk only, then both
    assert _run(*_chunk(b, 2)(race))[0] == 0
    assert stitched_chunks(race / "w.usda") == ["./w.f0007-0012.usda"]
    assert _run(*_chunk(b, 1)(race))[0] == 0
    whole_b = _serial(tmp_path / "c" / "race", {}, lambda d: _eval(b, "--chunk-size", "6")(d))[1]
    assert _files(race) == whole_b


def test_chunks_of_one_shot_in_any_order_give_the_one_run(shots, tmp_path):
    """Chunk 2 held in its commit while chunk 1 waits: the manifest ends as one run of both."""
    a = shots["gaussian"]
    race = _start(tmp_path / "a" / "race", {})
    c2 = Held(race, "c2", ("commit",), *_chunk(a, 2)(race)).at("commit")
    c1 = Held(race, "c1", (), *_chunk(a, 1)(race)).blocked()
    c2.go("commit")
    assert c2.done()[0] == 0 and c1.done()[0] == 0
    whole = _serial(tmp_path / "b" / "race", {}, lambda d: _eval(a, "--chunk-size", "6")(d))[1]
    assert _files(race) == whole


# --- pose --obj-dir: two runs filling one OBJ folder -----------------------------------------------

def test_two_poses_into_one_obj_folder_are_one_after_the_other(tmp_path):
    """Each run checks the folder, commits its OBJs and removes the files of the previous manifest
    it does not write. Without the folder's lock around all three, the second run checked (and
    listed the previous manifest) before the first committed, and kept the first run's extra OBJs
    beside a manifest that does not list them."""
    asset, poses = fixture("bad", "good_asset.usda"), fixture("arm_poses.usda")

    def pose(anim: str, name: str):
        return lambda d: ("pose", asset, "--anim", anim, "-o", d / name, "--obj-dir", d / "objs", "-q")

    race = _start(tmp_path / "a" / "race", {})
    first = Held(race, "first", ("commit",), *pose(ARM_ANIM, "e1.usda")(race)).at("commit")
    second = Held(race, "second", (), *pose(poses, "e2.usda")(race)).blocked()
    first.go("commit")
    assert first.done()[0] == 0 and second.done()[0] == 0
    codes, expected = _serial(tmp_path / "b" / "race", {}, pose(ARM_ANIM, "e1.usda"), pose(poses, "e2.usda"))
    assert codes == [0, 0]
    assert _files(race) == expected
    assert sum(name.startswith("objs/") for name in expected) == 4  # the second run's three OBJs and manifest


def test_chunks_evaluating_other_meshes_are_another_shot(tmp_path):
    """``eval --mesh`` chooses the channels a chunk holds: chunks of one shot evaluated for other
    meshes are another shot, refused while the first is incomplete, never stitched with it."""
    character, folder = fixture("character", "character.usda"), tmp_path / "shot"
    folder.mkdir()
    corr = folder / "corr.usda"
    examples = [fixture("character", f"character_{name}_examples.usda") for name in ("l_elbow", "sleeve")]
    assert _run("fit", character, *examples, "--group", "l_elbow", "-o", corr, "-q")[0] == 0

    def chunk(k: int, mesh: str):
        return ("eval", character, corr, "--anim", fixture("character", "character_anim.usda"), "-o",
                folder / "w.usda", "--frames", "1:24", "--chunk-size", "12", "--chunk", str(k), "--mesh", mesh, "-q")

    assert _run(*chunk(1, "Body"))[0] == 0
    code, err = _run(*chunk(2, "Sleeve"))
    assert code == EXIT_OUTPUT and "the manifest of another shot, 1 of its 2 chunk(s) written so far" in err
    assert stitched_chunks(folder / "w.usda") == ["./w.f0001-0012.usda"]
    assert _run(*chunk(2, "Body"))[0] == 0
    assert stitched_chunks(folder / "w.usda") == ["./w.f0001-0012.usda", "./w.f0013-0024.usda"]
