"""The paths a command is given, checked against the operating system before any work.

USD takes every path as UTF-8 text and the kernel every path as at most ``PATH_MAX`` bytes;
a relative path means nothing once the working folder is gone. Each of these, left to the
library, surfaced as an internal error or as a wrong reason ("does not exist"); here each
is one line naming the path (inputs: ``InputError``, exit 3; outputs: ``OutputError``,
exit 6). Light (``os`` only): the CLI runs it before USD loads.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Iterable

from .errors import InputError, OutputError, PsdError


def shown(path: str) -> str:
    """path as it can be printed: bytes that are not UTF-8 (kept by Python as surrogates)
    written as ``\\xe9``, so ``caf\\xe9.usda`` names the file the user typed."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def _is_utf8(text: str) -> bool:
    try:
        os.fsencode(text).decode("utf-8")
    except UnicodeDecodeError:
        return False
    return True


def _limits() -> tuple[int, int]:
    """(longest path, longest name) the kernel takes, in bytes: PATH_MAX counts the NUL."""
    try:
        longest, name = os.pathconf("/", "PC_PATH_MAX") - 1, os.pathconf("/", "PC_NAME_MAX")
    except (OSError, ValueError):
        longest, name = 4095, 255
    return longest, name


def _working_folder() -> str | None:
    """The working folder, None when it no longer exists (deleted or moved away under the shell)."""
    try:
        return os.getcwd()
    except FileNotFoundError:
        return None


def check_path(path: str, error: type[PsdError]) -> None:
    """Refuse path (raising ``error``) if the system cannot use it as given: not UTF-8, relative
    to a working folder that is gone or not UTF-8, or longer than the kernel's limits."""
    if not _is_utf8(path):
        raise error(f"{shown(path)}: the name is not UTF-8 text, and USD reads and writes UTF-8 paths only: rename it")
    if not os.path.isabs(path):
        cwd = _working_folder()
        if cwd is None:
            was = os.environ.get("PWD", "")
            raise error(f"{path}: a relative path, but the working folder{' ' + shown(was) if was else ''} no longer "
                        "exists (deleted or moved away): cd to an existing folder or give absolute paths")
        if not _is_utf8(cwd):
            raise error(f"{path}: a relative path in the working folder {shown(cwd)}, whose name is not UTF-8 text "
                        "(USD takes UTF-8 paths only): give an absolute path or cd elsewhere")
    longest, name_max = _limits()
    full = os.fsencode(os.path.abspath(path))
    if len(full) > longest:
        raise error(f"{path}: the path is {len(full)} bytes long, over this system's limit of {longest} bytes "
                    "(PATH_MAX)")
    too_long = [part for part in full.split(b"/") if len(part) > name_max]
    if too_long:
        raise error(f"{path}: a name in the path is {len(too_long[0])} bytes long, over this system's limit of "
                    f"{name_max} bytes (NAME_MAX)")
    try:
        os.stat(path)
    except OSError as exc:  # what the system says of the path itself (a missing file is the command's to name)
        if exc.errno == errno.ENAMETOOLONG:
            raise error(f"{path}: the path is too long for this system ({exc.strerror})") from None


def check_paths(inputs: Iterable[str], outputs: Iterable[str]) -> None:
    """``check_path`` for a command's inputs (exit 3) and outputs (exit 6)."""
    for path in inputs:
        check_path(path, InputError)
    for path in outputs:
        check_path(path, OutputError)
