"""The OBJ folder's policy: file names, ``manifest.json``, which folders may be filled, and
every file written in one commit with EXAMPLES.

Why a manifest: ``sculpts`` must never guess which mesh and time code a file is; the
manifest lists each file with its mesh, time code, point and face counts, and the sha256 of
the bytes ``pose`` wrote, so ``sculpts`` can tell an edited file from an untouched one and
``pose`` never overwrites a sculpt. As for ``compare``'s report folder
(``report/folder.py``): a missing folder is created, an empty one filled, one holding an
earlier manifest updated in place (the files it listed and this run does not write are
removed after the commit); anything else is refused (exit 6). A listed file whose bytes
changed since ``pose`` wrote it (an artist's sculpt) is refused too, never replaced.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

from ... import __version__, atomic
from ...errors import InputError, OutputError
from ...outputs import OutputKind
from ...shot.frames import frame_label

MANIFEST = "manifest.json"
#: ``<mesh path, '/' -> '.', other bytes -XX>@<time code, 'm' minus, 'p' point>.obj``
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+@(?P<time>m?[0-9]+(?:p[0-9]+)?)\.obj$")
#: A run killed (SIGKILL) before its commit leaves ``.psdbake-*.tmp*`` files, none of them ours.
_LEFTOVER = re.compile(r"^\.psdbake-.*\.tmp")
_SAFE = re.compile(r"[A-Za-z0-9_]")


@dataclass(frozen=True)
class ObjEntry:
    """One file of the folder, as the manifest lists it."""

    file: str  # plain name inside the folder
    mesh: str
    time: float
    points: int
    faces: int
    sha256: str = ""  # of the bytes pose wrote ("" when unknown)


@dataclass(frozen=True)
class Manifest:
    entries: tuple[ObjEntry, ...]
    sources: dict  # asset, poses, examples (as given to pose) and their sha256


def obj_name(mesh: str, time: float) -> str:
    """``/Arm/Geo/Tube`` at 1 -> ``Arm.Geo.Tube@0001.obj``: safe characters only, one name
    per mesh and time code (prim names have no ``.``; other bytes are written ``-XX``)."""
    token = "".join(c if _SAFE.match(c) else "." if c == "/" else "".join(f"-{b:02x}" for b in c.encode())
                    for c in mesh.strip("/"))
    return f"{token}@{frame_label(time, 4)}.obj"


def time_of_name(name: str) -> float | None:
    """The time code an OBJ file name of ours carries (None: not one of our names)."""
    match = _NAME.match(name)
    if not match:
        return None
    return float(match["time"].replace("m", "-").replace("p", "."))


def sha256_file(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# --- reading a manifest ------------------------------------------------------------------

def read_manifest(folder: str) -> Manifest:
    """The folder's manifest, every entry checked, or InputError naming what is wrong."""
    if not os.path.isdir(folder):
        raise InputError(f"{folder}: no such folder (the --obj-dir psdbake pose wrote)")
    path = os.path.join(folder, MANIFEST)
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise InputError(f"{path}: not found: {folder} was not written by psdbake pose --obj-dir") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not a readable manifest ({' '.join(str(exc).split())})") from None
    manifest = _parse(data)
    if manifest is None:
        raise InputError(f"{path}: not a psdbake OBJ manifest (written by psdbake pose --obj-dir)")
    seen: dict[object, str] = {}
    for e in manifest.entries:
        if not _NAME.match(e.file):
            raise InputError(f"{path}: file {e.file!r} is not a name psdbake pose writes (a plain <mesh>@<time>.obj)")
        for key in (e.file, (e.mesh, e.time)):
            if key in seen:
                raise InputError(f"{path}: {e.file} and {seen[key]} are the same file or mesh and time code")
            seen[key] = e.file
    return manifest


def _parse(data: object) -> Manifest | None:
    """A Manifest from JSON data, or None when it is not one of psdbake pose's."""
    if not isinstance(data, dict) or data.get("command") != "pose" or "psdbake" not in data:
        return None
    files, sources = data.get("files"), data.get("sources", {})
    if not isinstance(files, list) or not isinstance(sources, dict):
        return None
    entries = []
    for item in files:
        if not isinstance(item, dict):
            return None
        file, mesh, time = item.get("file"), item.get("mesh"), item.get("time")
        points, faces, sha = item.get("points"), item.get("faces"), item.get("sha256", "")
        if not (isinstance(file, str) and isinstance(mesh, str) and mesh.startswith("/")
                and isinstance(time, (int, float)) and not isinstance(time, bool) and math.isfinite(time)
                and isinstance(points, int) and isinstance(faces, int) and isinstance(sha, str)):
            return None
        entries.append(ObjEntry(file, mesh, float(time), points, faces, sha))
    return Manifest(tuple(entries), {k: v for k, v in sources.items() if isinstance(v, str)})


def manifest_text(entries: Sequence[ObjEntry], sources: dict[str, str]) -> str:
    """The manifest's JSON: sorted keys and entries, no time stamps (same inputs, same bytes)."""
    data = {
        "psdbake": __version__, "command": "pose",
        "about": "OBJ files of psdbake pose --obj-dir: sculpt them keeping the vertex order, then run psdbake sculpts",
        "sources": dict(sorted(sources.items())),
        "files": [{"file": e.file, "mesh": e.mesh, "time": e.time, "points": e.points, "faces": e.faces,
                   "sha256": e.sha256} for e in sorted(entries, key=lambda e: (e.mesh, e.time))],
    }
    return json.dumps(data, indent=2, sort_keys=True) + "\n"


# --- writing a folder --------------------------------------------------------------------

def _previous(folder: str) -> Manifest | None:
    try:
        with open(os.path.join(folder, MANIFEST), encoding="utf-8") as fh:
            return _parse(json.load(fh))
    except (OSError, UnicodeDecodeError, ValueError):
        return None


def check_obj_dir(path: str, inputs: Iterable[str] = (), names: Iterable[str] = ()) -> None:
    """Refuse an OBJ folder that cannot be written, is a file, holds someone else's files,
    or holds a file this run would replace that is not pose's untouched output (a sculpt)."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputError(f"{path}: exists and is not a folder (--obj-dir is a folder psdbake pose fills)")
    if not os.path.isdir(path):
        parent = os.path.dirname(os.path.abspath(path))
        while not os.path.exists(parent):
            parent = os.path.dirname(parent)
        if not os.path.isdir(parent) or not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"{path}: cannot create the folder ({parent} is not a writable folder)")
        return
    present = sorted(f for f in os.listdir(path) if not _LEFTOVER.match(f))
    previous = _previous(path)
    if present and previous is None:
        raise OutputError(f"{path}: folder is not empty and holds no psdbake OBJ manifest ({MANIFEST}); give a new or "
                          "empty folder")
    if not os.access(path, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: folder is not writable")
    listed = {e.file: e.sha256 for e in previous.entries} if previous else {}
    for name in sorted((set(names) | set(listed)) & set(present)):
        full = os.path.join(path, name)
        if name not in listed:
            raise OutputError(f"{full}: exists and was not written by psdbake pose; it would be replaced: move it away "
                              "or give a new folder (--force never replaces files in an OBJ folder)")
        if not os.path.isfile(full) or sha256_file(full) != listed[name]:
            raise OutputError(f"{full}: changed since psdbake pose wrote it (a sculpt?); it would be replaced: move the "
                              "sculpts away or give a new folder (--force never replaces a sculpt)")
    real = os.path.realpath(path)
    for src in inputs:
        if src and os.path.dirname(os.path.realpath(src)) == real and os.path.basename(src) in (*names, MANIFEST):
            raise OutputError(f"{path}: would overwrite the input {src}")


def write_obj_dir(folder: str, examples: str, write_examples: Callable[[str], None], kind: OutputKind,
                  objs: Sequence[tuple[ObjEntry, str]], sources: dict[str, str], inputs: Sequence[str] = ()) -> list[str]:
    """EXAMPLES (written by ``write_examples`` to the temporary path it is given), every OBJ
    text and the manifest, in one ``atomic.Transaction``; then the previous manifest's files
    this run does not write are removed. Returns the OBJ names. The folder is checked again,
    committed and cleaned under the update lock of the folder and EXAMPLES' folder, so two runs
    into one folder are one after the other: neither removes a file the other just wrote."""
    names = [e.file for e, _ in objs]
    check_obj_dir(folder, inputs, names)
    created = not os.path.isdir(folder)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from None
    try:
        # one step for other writers of the folder: the checks again, the commit and the removals
        with atomic.updating(os.path.join(folder, MANIFEST), examples):
            check_obj_dir(folder, inputs, names)
            previous = _previous(folder)
            _commit(folder, examples, write_examples, kind, objs, sources, inputs)
            for stale in sorted({e.file for e in previous.entries} - set(names) if previous else ()):
                with contextlib.suppress(FileNotFoundError):
                    os.remove(os.path.join(folder, stale))
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(folder)  # a failed run leaves no folder it made
        raise
    return names


def _commit(folder: str, examples: str, write_examples: Callable[[str], None], kind: OutputKind,
            objs: Sequence[tuple[ObjEntry, str]], sources: dict[str, str], inputs: Sequence[str]) -> None:
    """EXAMPLES, every OBJ and the manifest in one ``atomic.Transaction``."""
    with atomic.Transaction(inputs) as tx:
        tmp = tx.path(examples, kind=kind)
        write_examples(tmp)
        sources = {**sources, "examples_sha256": sha256_file(tmp)}
        entries = []
        for entry, text in objs:
            data = text.encode("utf-8")
            _write(tx, os.path.join(folder, entry.file), data)
            entries.append(ObjEntry(entry.file, entry.mesh, entry.time, entry.points, entry.faces,
                                    hashlib.sha256(data).hexdigest()))
        _write(tx, os.path.join(folder, MANIFEST), manifest_text(entries, sources).encode("utf-8"))


def _write(tx: atomic.Transaction, dest: str, data: bytes) -> None:
    tmp = tx.path(dest)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
    except OSError as exc:
        raise OutputError(f"{dest}: cannot write ({exc.strerror or exc})") from None


def unlisted_objs(folder: str, manifest: Manifest) -> list[str]:
    """OBJ files in folder the manifest does not list, sorted."""
    listed = {e.file for e in manifest.entries}
    return sorted(f for f in os.listdir(folder) if f.lower().endswith(".obj") and f not in listed)
