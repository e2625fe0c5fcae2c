"""Read every value of USD layer files, in a process of its own (``psdbake.usd.integrity``).

Run as ``python _crate_probe.py FILE...`` with nothing but ``pxr`` imported: for each
file it prints ``reading N``, opens the file (each layer inside a ``.usdz`` too), reads
every field and time sample of every spec, composes the layer on a stage of its own and
reads every property there, then prints ``ok N``. An unreadable value prints ``error N
"MESSAGE"`` (JSON) and exits 3. A corrupt crate file can crash USD's reader (SIGSEGV,
abort); the parent sees the signal and the last ``reading N``.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import sys
import tempfile
import zipfile
from collections.abc import Callable, Iterator
from typing import Any

#: Address-space cap of the probe: a corrupt size field must not take the machine's memory.
_MEMORY_LIMIT = 8 << 30


def _identifiers(path: str) -> list[str]:
    if path.lower().endswith(".usdz"):
        with zipfile.ZipFile(path) as package:
            inner = [n for n in package.namelist() if n.lower().endswith((".usda", ".usdc", ".usd"))]
        return [path] + [f"{path}[{name}]" for name in inner]
    return [path]


def read_every_value(identifier: str) -> None:
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(identifier)
    if layer is None:
        raise ValueError("USD cannot open it")
    paths: list = []
    layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
    for path in paths:
        str(path)  # names must be text
        # a relationship target or connection: Python finds no spec there (None), after ~35 us a
        # lookup, and a CORRECTIVES holds one per corrective; its path is read above, its fields are the property's
        if path.IsTargetPath():
            continue
        spec = layer.GetObjectAtPath(path)
        if spec is None:
            continue
        for key in spec.ListInfoKeys():
            _decode(spec.GetInfo(key))
        if path.IsPropertyPath():
            for t in layer.ListTimeSamplesForPath(path):
                _decode(layer.QueryTimeSample(path, t))
    from pxr import UsdUtils

    UsdUtils.ExtractExternalReferences(identifier)  # what psdbake's dependency walk runs next
    _compose(layer)


def _decode(value: Any) -> None:
    """Names and strings as Python text: token and string arrays decode their elements only
    when read, so read them here (a damaged token table is not UTF-8). A dict item by item,
    numeric arrays left out: they hold no text, and ``timeSamples`` is a dict of them (printing
    a million points as text took most of a 1M-point fit; ``QueryTimeSample`` reads their bits)."""
    if isinstance(value, dict):
        for key, item in value.items():
            str(key)
            if isinstance(item, dict):
                _decode(item)
            elif not _numeric_array(item):
                repr(item)  # as str(list) of the values did
    elif type(value).__name__ in ("TokenArray", "StringArray", "list", "tuple"):
        str(list(value))


def _numeric_array(value: Any) -> bool:
    """A Vt array of numbers, vectors, matrices or quaternions: no text in it."""
    return type(value).__module__ == "pxr.Vt" and type(value).__name__ not in ("TokenArray", "StringArray")


def _compose(layer) -> None:
    """The layer on a stage of its own (what psdbake does next): every prim and property
    composed and read, so composition-level faults show here, not half-way through a fit."""
    from pxr import Usd

    stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
    for prim in stage.TraverseAll():
        for prop in prim.GetProperties():
            if isinstance(prop, Usd.Attribute):
                prop.Get()
                prop.GetTimeSamples()
            else:
                prop.GetTargets()


@contextlib.contextmanager
def _stderr_of_usd() -> Iterator[Callable[[], str]]:
    """What USD's C++ code writes straight to file descriptor 2 meanwhile (not a Tf
    diagnostic: e.g. its crate reader's failed posix_madvise of a section past the file)."""
    with tempfile.TemporaryFile() as capture:
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        text: list[str] = []
        try:
            yield lambda: "".join(text)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        text.append(capture.read().decode("utf-8", "replace"))


def main(files: list[str]) -> int:
    try:
        resource.setrlimit(resource.RLIMIT_AS, (_MEMORY_LIMIT, _MEMORY_LIMIT))
    except (ValueError, OSError):
        pass
    for i, path in enumerate(files):
        print(f"reading {i}", flush=True)
        try:
            with _stderr_of_usd() as said:
                for identifier in _identifiers(path):
                    read_every_value(identifier)
            if "posix_madvise" in said():  # USD mapped a section past the file's end: a corrupt size
                raise ValueError("a crate section claims more bytes than the file holds")
        except Exception as exc:  # any failure is the file's: report it, the parent names the file
            try:
                message = str(exc) if not isinstance(exc, UnicodeDecodeError) else "text that is not UTF-8"
            except UnicodeDecodeError:
                message = "text that is not UTF-8"
            print(f"error {i} {json.dumps(message)}", flush=True)
            return 3
        print(f"ok {i}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
