"""The report folder's policy: which folders may be filled, and all files in one commit.

``stats.json`` is the marker that a folder was written by ``psdbake compare``: a non-empty
folder without it is refused, a folder with it is updated in place. Every file of one
report is written to a temporary file first and all are renamed together
(``atomic.Transaction``), so a failed or interrupted run leaves the previous report whole;
files the previous report listed and this one does not write are removed after the commit,
under the folder's update lock with the check and the commit (another run into the same folder
comes wholly before or after).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Iterable, Sequence

from .. import atomic
from ..errors import OutputError

#: Files psdbake compare writes (and may therefore replace or remove in a report folder).
OURS = re.compile(r"^(index\.html|stats\.csv|stats\.json|correction_angle\.png|views_[-+.0-9a-z]+\.png)$")
MARKER = "stats.json"
#: A run killed (SIGKILL) before its commit leaves ``.psdbake-*.tmp*`` files, none of them
#: a report file; they do not make a folder someone else's.
_LEFTOVER = re.compile(r"^\.psdbake-.*\.tmp")

#: Writes one file of the report to the (temporary) path it is given.
Writer = Callable[[str], None]


def previous_files(path: str) -> list[str] | None:
    """Files listed by a previous report in path (None when path holds no psdbake report)."""
    try:
        with open(os.path.join(path, MARKER), encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("command") != "compare" or "psdbake" not in data:
        return None
    return [f for f in data.get("files", []) if isinstance(f, str) and OURS.match(f)]


def check_report_dir(path: str, inputs: Iterable[str] = ()) -> None:
    """Refuse a REPORT_DIR that cannot be written, is a file, or holds someone else's files."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputError(f"{path}: exists and is not a folder (REPORT_DIR is a folder psdbake compare fills)")
    if os.path.isdir(path):
        foreign = [f for f in os.listdir(path) if not _LEFTOVER.match(f)]
        if foreign and previous_files(path) is None:
            raise OutputError(f"{path}: folder is not empty and was not written by psdbake compare; give a new or empty folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputError(f"{path}: folder is not writable")
        real = os.path.realpath(path)
        for src in inputs:
            if src and os.path.dirname(os.path.realpath(src)) == real and OURS.match(os.path.basename(src)):
                raise OutputError(f"{path}: would overwrite the input {src}")
        return
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: cannot create the folder ({parent} is not a writable folder)")


def write_folder(out_dir: str, files: Sequence[tuple[str, Writer]], inputs: Sequence[str] = ()) -> list[str]:
    """Check and create out_dir, write every (name, writer) into one transaction, commit,
    then drop the previous report's files this one no longer has. Returns the names."""
    check_report_dir(out_dir, inputs)
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the folder ({exc.strerror or exc})") from None
    names = [name for name, _ in files]
    # one step for another run into the same folder: the check again, the commit and the removals
    with atomic.updating(os.path.join(out_dir, names[0] if names else "index.html")):
        check_report_dir(out_dir, inputs)
        previous = previous_files(out_dir) or []
        with atomic.Transaction(inputs) as tx:
            for name, write in files:
                dest = os.path.join(out_dir, name)
                tmp = tx.path(dest)
                try:
                    write(tmp)
                except OSError as exc:
                    raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from None
        for stale in sorted(set(previous) - set(names)):
            try:
                os.remove(os.path.join(out_dir, stale))
            except FileNotFoundError:
                pass
    return names


def text_writer(text: str) -> Writer:
    """A Writer for a UTF-8 text file."""

    def write(path: str) -> None:
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(text)

    return write
