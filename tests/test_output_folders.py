"""Output folders: made when an output is written, removed again when the run fails, and a run
waiting for a folder's lock while another run removes it locks the folder made afresh."""

from __future__ import annotations

import os
import threading

import pytest

from psdbake import atomic
from psdbake.errors import OutputError


def test_transaction_makes_the_folders_and_keeps_them(tmp_path):
    dest = tmp_path / "a" / "b" / "out.usda"
    with atomic.Transaction() as tx:
        with open(tx.path(str(dest)), "w") as fh:
            fh.write("#usda 1.0\n")
    assert dest.read_text() == "#usda 1.0\n"


def test_failed_transaction_removes_the_folders_it_made(tmp_path):
    (tmp_path / "a").mkdir()
    dest = tmp_path / "a" / "b" / "c" / "out.usda"
    with pytest.raises(RuntimeError), atomic.Transaction() as tx:
        tx.path(str(dest))
        assert (tmp_path / "a" / "b" / "c").is_dir()
        raise RuntimeError("the fit failed")
    assert not (tmp_path / "a" / "b").exists()
    assert (tmp_path / "a").is_dir()  # it existed before: not this run's to remove


def test_failed_update_removes_the_folder_it_made(tmp_path):
    dest = tmp_path / "new" / "corr.usda"
    with pytest.raises(RuntimeError), atomic.updating(str(dest)):
        assert dest.parent.is_dir()
        raise RuntimeError("the fit failed")
    assert not dest.parent.exists()


def test_a_folder_another_run_wrote_into_is_kept(tmp_path):
    dest = tmp_path / "shared" / "one.usda"
    with pytest.raises(RuntimeError), atomic.Transaction() as tx:
        tx.path(str(dest))
        (tmp_path / "shared" / "other.usda").write_text("another run's output")
        raise RuntimeError("this run failed")
    assert (tmp_path / "shared" / "other.usda").is_file()


def test_folder_under_a_file_is_refused(tmp_path):
    (tmp_path / "plain").write_text("")
    with pytest.raises(OutputError, match="is not a folder"):
        atomic.check_output(str(tmp_path / "plain" / "x" / "out.usda"))


def test_waiter_locks_the_folder_made_afresh(tmp_path):
    """Run A made the folder and fails while B waits for its lock: A removes the folder under
    the lock, and B makes and locks a new one, so a third run cannot take it beside B."""
    dest = tmp_path / "new" / "corr.usda"
    a_holds, b_locked = threading.Event(), threading.Event()
    locked_is_there: list[bool] = []

    def run_b() -> None:
        a_holds.wait()
        with atomic.updating(str(dest)):
            fd, _ = atomic._HELD.folders[os.path.realpath(dest.parent)]
            held, there = os.fstat(fd), dest.parent.stat()
            locked_is_there.append((held.st_dev, held.st_ino) == (there.st_dev, there.st_ino))
            b_locked.set()

    b = threading.Thread(target=run_b)
    b.start()
    with pytest.raises(RuntimeError), atomic.updating(str(dest)):
        a_holds.set()
        assert not b_locked.wait(0.3)  # B waits for A's lock
        raise RuntimeError("A failed")
    b.join(10)
    assert b_locked.is_set() and locked_is_there == [True]
    assert dest.parent.is_dir()  # B's block succeeded: the folder it made is kept
