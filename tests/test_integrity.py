"""The crate probe's verdict persists across processes, keyed by content (``psdbake.usd.integrity``).

A "new process" is simulated by clearing ``_checked`` (what a fresh psdbake starts with);
probe runs are counted at ``subprocess.run``, hashes at ``hashlib.file_digest``. One test
lets a real ``psdbake`` process fill the cache. Counts, never times.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
import shutil
import struct
import subprocess
import sys

import pytest
from conftest import fixture, refused

from psdbake.errors import InputError
from psdbake.usd import integrity

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)


BAD = fixture("bad")
PSDBAKE = os.path.join(os.path.dirname(sys.executable), "psdbake")
EXIT_INPUT = 3
#: A double that a float cannot hold, so the crate file stores its 8 bytes as they are:
#: changing one of them changes one value and leaves a readable file.
MARKER = 0.1


def _crate(path, marker: float = MARKER) -> str:
    """A small valid crate file with a double ``marker`` stored out of line."""
    from pxr import Sdf

    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.ImportFromString(f'#usda 1.0\ndef Xform "A"\n{{\n    custom double marker = {marker!r}\n}}\n')
    assert layer.Export(str(path))
    assert pathlib.Path(path).read_bytes().count(struct.pack("<d", marker)) == 1
    return str(path)


@pytest.fixture
def probes(monkeypatch, tmp_path):
    """A cache of this test's own, a fresh process's ``_checked``, and the probe runs
    (their argv lists) and file hashes counted from now on."""
    monkeypatch.setenv(integrity.CACHE_ENV, str(tmp_path / "cache"))
    monkeypatch.setattr(integrity, "_checked", {})
    runs: list[list[str]] = []
    hashed: list[int] = []
    run, file_digest = subprocess.run, hashlib.file_digest

    def counted_run(argv, *args, **kwargs):
        if integrity._PROBE in argv:
            runs.append(list(argv[2:]))
        return run(argv, *args, **kwargs)

    def counted_digest(fh, *args, **kwargs):
        hashed.append(1)
        return file_digest(fh, *args, **kwargs)

    monkeypatch.setattr(subprocess, "run", counted_run)
    monkeypatch.setattr(hashlib, "file_digest", counted_digest)
    return runs, hashed


def _new_process(monkeypatch) -> None:
    monkeypatch.setattr(integrity, "_checked", {})


def _entries(folder) -> list[str]:
    verdicts = os.path.join(str(folder), integrity._VERDICTS)
    return sorted(os.listdir(verdicts)) if os.path.isdir(verdicts) else []


def test_an_unchanged_file_is_probed_once_across_processes(probes, monkeypatch, tmp_path):
    runs, hashed = probes
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    assert runs == [[crate]]
    assert len(_entries(tmp_path / "cache")) == 1
    assert len(hashed) == 2  # before the probe, and again after it (the bytes it read are the ones named)
    integrity.require_readable_crates([crate])  # same process: neither probed nor hashed again
    assert (len(runs), len(hashed)) == (1, 2)
    for _ in range(3):  # every later process: one hash, no probe
        _new_process(monkeypatch)
        integrity.require_readable_crates([crate, crate])
        integrity.require_readable_crates([crate])
    assert (len(runs), len(hashed)) == (1, 5)


def test_the_key_is_the_content_not_the_path(probes, monkeypatch, tmp_path):
    """A copy elsewhere (a farm node's local scratch) is the same bytes: no probe. The same
    bytes under another extension go through another file format: probed."""
    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    copy = tmp_path / "elsewhere" / "b.usdc"
    copy.parent.mkdir()
    shutil.copy(crate, copy)
    os.utime(copy, ns=(1, 1))
    _new_process(monkeypatch)
    integrity.require_readable_crates([str(copy)])
    assert len(runs) == 1
    renamed = shutil.copy(crate, tmp_path / "a.usd")  # a .usd holding crate bytes is a crate file too
    integrity.require_readable_crates([renamed])
    assert runs[1:] == [[renamed]]


def test_one_changed_byte_is_probed_again(probes, monkeypatch, tmp_path):
    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    data = bytearray(pathlib.Path(crate).read_bytes())
    at = bytes(data).index(struct.pack("<d", MARKER))
    data[at] ^= 1  # the lowest mantissa byte: another double, still a readable file
    stat = os.stat(crate)
    pathlib.Path(crate).write_bytes(data)
    os.utime(crate, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # same size and mtime: only the bytes tell
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert runs == [[crate], [crate]]
    assert len(_entries(tmp_path / "cache")) == 2
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert len(runs) == 2


@pytest.fixture
def fresh_key():
    """The reader-and-probe part of the key computed anew now and after the test (which
    changes it), before its monkeypatches are undone."""
    integrity._reader_and_probe.cache_clear()
    yield
    integrity._reader_and_probe.cache_clear()


def test_a_changed_probe_or_reader_is_a_new_key(probes, fresh_key, monkeypatch, tmp_path):
    """Same bytes, another probe (its source changed) or another USD: probed again."""
    from pxr import Usd

    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    edited = tmp_path / "_crate_probe.py"
    edited.write_text(pathlib.Path(integrity._PROBE).read_text() + "\n# edited\n")
    monkeypatch.setattr(integrity, "_PROBE", str(edited))
    integrity._reader_and_probe.cache_clear()
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert len(runs) == 2
    version = Usd.GetVersion()
    monkeypatch.setattr(Usd, "GetVersion", lambda: (version[0], version[1] + 1, 0))
    integrity._reader_and_probe.cache_clear()
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert len(runs) == 3
    assert len(_entries(tmp_path / "cache")) == 3


@pytest.mark.parametrize("name, says", [("crate_value_corrupt.usdc", r"not a readable USD file \(Corrupt"),
                                        ("crate_crashes_reader.usdc", r"crashed .*SIGSEGV")])
def test_a_refused_file_is_never_cached(name, says, probes, monkeypatch, tmp_path, cli):
    """Refused every time, in its one line, by a probe run every time; nothing stored."""
    runs, _ = probes
    path = shutil.copy(os.path.join(BAD, name), tmp_path / name)
    for _ in range(2):
        _new_process(monkeypatch)
        with pytest.raises(InputError, match=says):
            integrity.require_readable_crates([path])
        _new_process(monkeypatch)
        refused(cli("inspect", path), EXIT_INPUT, names=[name], says=says)
    assert len(runs) == 4
    assert _entries(tmp_path / "cache") == []


def test_a_good_file_before_a_refused_one_is_cached(probes, monkeypatch, tmp_path):
    """One probe run, two files: the first passed (its verdict stands), the second did not."""
    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    bad = shutil.copy(os.path.join(BAD, "crate_value_corrupt.usdc"), tmp_path)
    with pytest.raises(InputError, match="crate_value_corrupt"):
        integrity.require_readable_crates([crate, bad])
    _new_process(monkeypatch)
    with pytest.raises(InputError, match="crate_value_corrupt"):
        integrity.require_readable_crates([crate, bad])
    assert runs == [[crate, bad], [bad]]


def test_a_file_replaced_while_probed_is_not_vouched_for(probes, monkeypatch, tmp_path):
    """The probe read other bytes than the ones hashed before it: nothing stored."""
    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    other = _crate(tmp_path / "other.usdc", 0.3)
    run = subprocess.run

    def replaced_during(argv, *args, **kwargs):
        done = run(argv, *args, **kwargs)
        os.replace(other, crate)
        return done

    monkeypatch.setattr(subprocess, "run", replaced_during)
    integrity.require_readable_crates([crate])
    assert _entries(tmp_path / "cache") == []
    monkeypatch.setattr(subprocess, "run", run)
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])  # the bytes now there: probed, and stored
    assert runs == [[crate], [crate]]
    assert len(_entries(tmp_path / "cache")) == 1


@pytest.mark.parametrize("change", [None, "replaced", "rewritten in place, same size and mtime"])
def test_a_settled_file_is_hashed_once_unless_it_changed_while_probed(change, probes, monkeypatch, tmp_path):
    """A file last changed SETTLED_SECONDS ago and found with the same device, inode, size,
    mtime and ctime after the probe holds the bytes hashed before it: stored without a second
    hash. Replaced, or rewritten in place with its size and mtime put back (the ctime moves),
    it is hashed again, and not vouched for."""
    runs, hashed = probes
    monkeypatch.setattr(integrity, "SETTLED_SECONDS", 0.0)  # every file counts as settled
    crate = _crate(tmp_path / "a.usdc")
    other = _crate(tmp_path / "other.usdc", 0.3)
    run = subprocess.run

    def changed_during(argv, *args, **kwargs):
        done = run(argv, *args, **kwargs)
        if change == "replaced":
            os.replace(other, crate)
        elif change:
            stat = os.stat(crate)
            pathlib.Path(crate).write_bytes(pathlib.Path(other).read_bytes())
            os.utime(crate, ns=(stat.st_atime_ns, stat.st_mtime_ns))
            assert os.stat(crate).st_size == stat.st_size
        return done

    monkeypatch.setattr(subprocess, "run", changed_during)
    integrity.require_readable_crates([crate])
    assert len(runs) == 1
    if change is None:
        assert len(hashed) == 1
        assert len(_entries(tmp_path / "cache")) == 1
    else:
        assert len(hashed) == 2
        assert _entries(tmp_path / "cache") == []


def test_an_empty_cache_dir_turns_the_cache_off(probes, monkeypatch, tmp_path):
    runs, hashed = probes
    monkeypatch.setenv(integrity.CACHE_ENV, "")
    assert integrity.cache_folder() is None
    crate = _crate(tmp_path / "a.usdc")
    for _ in range(2):
        _new_process(monkeypatch)
        integrity.require_readable_crates([crate])
    assert (len(runs), len(hashed)) == (2, 0)
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("how", ["a file", "mkstemp refused", "rename refused", "a NUL"])
def test_an_unwritable_cache_is_skipped_silently(how, probes, monkeypatch, tmp_path, cli):
    """Read-only homes (tests run as root, so permissions are simulated): no error, no
    message, no leftover; the probe simply runs every time."""
    runs, _ = probes
    cache = tmp_path / "cache"
    if how == "a file":
        cache.write_text("")
        monkeypatch.setenv(integrity.CACHE_ENV, str(cache / "psdbake"))
    elif how == "a NUL":  # no environment variable holds one: the folder as if it did
        monkeypatch.setattr(integrity, "cache_folder", lambda: str(tmp_path / "ca\0che"))
    else:
        def refuse(*args, **kwargs):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(integrity.tempfile if how == "mkstemp refused" else integrity.os,
                            "mkstemp" if how == "mkstemp refused" else "replace", refuse)
    crate = _crate(tmp_path / "a.usdc")
    for _ in range(2):
        _new_process(monkeypatch)
        integrity.require_readable_crates([crate])
    _new_process(monkeypatch)
    code, _, err = cli("inspect", crate)
    assert (code, err) == (0, ""), err
    assert len(runs) == 3
    if cache.is_dir():
        assert os.listdir(cache / integrity._VERDICTS) == []  # no temporary file left behind


def test_a_psdbake_process_fills_the_cache_for_the_next(probes, monkeypatch, tmp_path):
    """Across real processes: ``psdbake inspect`` verifies the file, this process does not probe it."""
    runs, _ = probes
    crate = _crate(tmp_path / "a.usdc")
    done = subprocess.run([PSDBAKE, "inspect", crate], capture_output=True, text=True, check=False,
                          env={**os.environ, integrity.CACHE_ENV: str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    assert len(_entries(tmp_path / "cache")) == 1
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert runs == []


def test_cache_folder_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.delenv(integrity.CACHE_ENV)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    assert integrity.cache_folder() == str(tmp_path / "home" / ".cache" / "psdbake")
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    assert integrity.cache_folder() == str(tmp_path / "home" / ".cache" / "psdbake")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert integrity.cache_folder() == str(tmp_path / "xdg" / "psdbake")
    monkeypatch.setenv(integrity.CACHE_ENV, str(tmp_path / "mine"))
    assert integrity.cache_folder() == str(tmp_path / "mine")


def test_the_session_never_caches_in_the_home():
    """conftest points every test and every psdbake they start at a temporary folder."""
    folder = os.environ[integrity.CACHE_ENV]
    assert os.path.isabs(folder) and os.path.basename(folder).startswith("psdbake-test-cache-")


def _shortcuts(folder) -> list[str]:
    found = os.path.join(str(folder), integrity._BY_IDENTITY)
    return sorted(os.listdir(found)) if os.path.isdir(found) else []


def test_a_settled_unchanged_file_is_found_without_hashing(probes, monkeypatch, tmp_path):
    """Every process after the first finds a settled, unchanged file by its identity: neither
    probed nor hashed (a farm chunk reading a large CORRECTIVES pays nothing per file)."""
    runs, hashed = probes
    monkeypatch.setattr(integrity, "SETTLED_SECONDS", 0.0)
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    assert (len(runs), len(hashed)) == (1, 1)
    assert len(_entries(tmp_path / "cache")) == 1 and len(_shortcuts(tmp_path / "cache")) == 1
    for _ in range(3):
        _new_process(monkeypatch)
        integrity.require_readable_crates([crate])
    assert (len(runs), len(hashed)) == (1, 1)


def test_a_file_not_settled_gets_no_shortcut(probes, monkeypatch, tmp_path):
    """Changed less than SETTLED_SECONDS ago, a file may change again within the same
    timestamp tick: it is looked up by its bytes every time."""
    runs, hashed = probes
    crate = _crate(tmp_path / "a.usdc")
    for _ in range(2):
        _new_process(monkeypatch)
        integrity.require_readable_crates([crate])
    assert _shortcuts(tmp_path / "cache") == []
    assert (len(runs), len(hashed)) == (1, 3)  # the first process hashes twice (around the probe)


@pytest.mark.parametrize("change", ["rewritten in place, same size and mtime", "copied over", "renamed over"])
def test_a_changed_file_misses_its_shortcut(change, probes, monkeypatch, tmp_path):
    """Rewritten in place with its size and mtime put back, or replaced: another identity
    (the ctime or the inode moved), so the bytes are hashed and, being other bytes, probed."""
    runs, hashed = probes
    monkeypatch.setattr(integrity, "SETTLED_SECONDS", 0.0)
    crate = _crate(tmp_path / "a.usdc")
    other = _crate(tmp_path / "other.usdc", 0.3)
    integrity.require_readable_crates([crate])
    stat = os.stat(crate)
    if change == "renamed over":
        os.replace(other, crate)
    else:
        pathlib.Path(crate).write_bytes(pathlib.Path(other).read_bytes())
        if change.startswith("rewritten"):
            os.utime(crate, ns=(stat.st_atime_ns, stat.st_mtime_ns))
            assert (os.stat(crate).st_size, os.stat(crate).st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)
    _new_process(monkeypatch)
    integrity.require_readable_crates([crate])
    assert runs == [[crate], [crate]]
    assert len(hashed) == 2


def test_a_settled_copy_is_found_by_its_bytes_then_by_its_identity(probes, monkeypatch, tmp_path):
    """A copy (another inode) is hashed once, found by content (no probe), and from then on by
    its own identity."""
    runs, hashed = probes
    monkeypatch.setattr(integrity, "SETTLED_SECONDS", 0.0)
    crate = _crate(tmp_path / "a.usdc")
    integrity.require_readable_crates([crate])
    copy = shutil.copy(crate, tmp_path / "b.usdc")
    for _ in range(3):
        _new_process(monkeypatch)
        integrity.require_readable_crates([copy])
    assert (len(runs), len(hashed)) == (1, 2)
    assert len(_shortcuts(tmp_path / "cache")) == 2
