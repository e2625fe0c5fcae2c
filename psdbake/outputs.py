"""The kinds of file psdbake writes, and how to tell an existing file's kind.

A command replaces only its own earlier output: a file of the same kind that psdbake wrote
(``atomic.check_output``). Anything else at an output path (an asset, a sculpted EXAMPLES
layer, someone's notes, a WEIGHTS layer given to ``fit -o``) is refused, exit 6, unless the
user asks with ``--force``. Each kind knows its extensions and how to read the kind of a file
already there; the readers load USD or JSON only when a file exists, so this module is cheap
to import (the CLI names kinds while it parses options).
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import shlex
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

from .names import LAYER_FORMATS

#: Largest JSON side file whose kind is read (reports are kilobytes; anything bigger is not ours).
_MAX_JSON_BYTES = 64 << 20


@dataclass(frozen=True)
class OutputKind:
    """One kind of output: its name (as stamped in the file), what users call it, the
    extensions it may be written with, and how to read the kind of an existing file."""

    name: str
    label: str
    extensions: tuple[str, ...]
    identify: Callable[[str], str | None]  # existing file -> the kind psdbake stamped in it, or None

    def describe(self, path: str) -> str:
        """What the file at path is, in a user's words (for a refusal)."""
        found = self.identify(path)
        if found is not None:
            return f"a psdbake {LABELS.get(found, found)}"
        return _foreign(path)


def _layer_kind(path: str) -> str | None:
    from .usd.provenance import existing_kind

    return existing_kind(path)


def _foreign(path: str) -> str:
    if os.path.splitext(path)[1].lower() in (*LAYER_FORMATS, ".usdz"):
        from .usd.provenance import describe_foreign

        return describe_foreign(path)
    return "not a file psdbake wrote"


def _json_kind(path: str) -> str | None:
    """A JSON report psdbake wrote carries ``"psdbake": version`` and ``"command"``."""
    try:
        if os.path.getsize(path) > _MAX_JSON_BYTES:
            return None
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError):
        return None
    if isinstance(data, dict) and isinstance(data.get("psdbake"), str) and isinstance(data.get("command"), str):
        return f"{data['command']}_report"
    return None


def _glb_kind(path: str) -> str | None:
    """A .glb psdbake wrote names it as the glTF ``asset.generator`` ("psdbake VERSION export-gltf")."""
    try:
        with open(path, "rb") as fh:
            header = fh.read(20)
            if len(header) < 20 or header[:4] != b"glTF":
                return None
            length, kind = struct.unpack("<II", header[12:20])
            if kind != 0x4E4F534A or length > _MAX_JSON_BYTES:  # "JSON"
                return None
            data = json.loads(fh.read(length).decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    generator = data.get("asset", {}).get("generator", "") if isinstance(data, dict) else ""
    return "gltf" if isinstance(generator, str) and generator.startswith("psdbake") else None


#: The scene property a rig written by ``export-blender`` carries (``psdbake VERSION export-blender``),
#: uncompressed, so its bytes are in the file.
BLEND_MARKER = b"export-blender"


def _blend_kind(path: str) -> str | None:
    """A .blend psdbake wrote: Blender's header, and the scene's psdbake property in its bytes."""
    try:
        with open(path, "rb") as fh:
            if fh.read(7) != b"BLENDER":
                return None
            tail = b""
            for block in iter(lambda: fh.read(1 << 20), b""):
                if b"psdbake" in tail + block and BLEND_MARKER in tail + block:
                    return "blend"
                tail = block[-64:]
    except OSError:
        return None
    return None


#: Layer kinds: the name stamped in ``customLayerData["psdbake"]["kind"]`` -> what users call it.
LABELS = {
    "examples": "EXAMPLES layer (psdbake pose)",
    "sculpted_examples": "sculpted EXAMPLES layer (psdbake sculpts)",
    "correctives": "CORRECTIVES layer",
    "weights": "WEIGHTS layer",
    "points_cache": "points cache",
    "clip_manifest": "value-clip manifest",
    "stack": "stack",
    "fit_report": "fit report",
    "gltf": "glTF binary (psdbake export-gltf)",
    "blend": "live Blender rig (psdbake export-blender)",
}

EXAMPLES = OutputKind("examples", LABELS["examples"], LAYER_FORMATS, _layer_kind)
SCULPTED_EXAMPLES = OutputKind("sculpted_examples", LABELS["sculpted_examples"], LAYER_FORMATS, _layer_kind)
CORRECTIVES = OutputKind("correctives", LABELS["correctives"], LAYER_FORMATS, _layer_kind)
WEIGHTS = OutputKind("weights", LABELS["weights"], LAYER_FORMATS, _layer_kind)
POINTS_CACHE = OutputKind("points_cache", LABELS["points_cache"], LAYER_FORMATS, _layer_kind)
CLIP_MANIFEST = OutputKind("clip_manifest", LABELS["clip_manifest"], LAYER_FORMATS, _layer_kind)
STACK = OutputKind("stack", LABELS["stack"], LAYER_FORMATS, _layer_kind)
FIT_REPORT = OutputKind("fit_report", LABELS["fit_report"], (".json",), _json_kind)
GLTF = OutputKind("gltf", LABELS["gltf"], (".glb",), _glb_kind)
BLEND = OutputKind("blend", LABELS["blend"], (".blend",), _blend_kind)

#: Every kind by name: a layer's stamped kind finds its rule here (``usd.write.export_all``).
KINDS = {k.name: k for k in (EXAMPLES, SCULPTED_EXAMPLES, CORRECTIVES, WEIGHTS, POINTS_CACHE, CLIP_MANIFEST, STACK,
                             FIT_REPORT, GLTF, BLEND)}


#: The command line of the running ``psdbake`` command and which of its values are file or
#: folder paths (set by the CLI, which knows its parameters), for provenance.
_COMMAND_LINE: contextvars.ContextVar[tuple[tuple[str, ...], frozenset[str]] | None] = contextvars.ContextVar(
    "psdbake_command_line", default=None)


@contextlib.contextmanager
def invoked_as(argv: Sequence[str], paths: Iterable[str] = ()) -> Iterator[None]:
    """Within the block, outputs record ``psdbake ARGV`` as the command that made them, each of
    ``paths`` (values in ARGV that name files or folders) relative to the output."""
    token = _COMMAND_LINE.set((("psdbake", *argv), frozenset(paths)))
    try:
        yield
    finally:
        _COMMAND_LINE.reset(token)


#: Options that change what a command prints, how fast it runs or which farm task writes which
#: part, never what it writes: left out of the recorded command line, so that ``-j 2``, ``-q`` or
#: ``--chunk 6`` gives the same bytes as the whole run.
_UNRECORDED_FLAGS = frozenset({"-q", "--quiet", "-v", "-vv", "-vvv", "--verbose", "--json", "--force"})
_UNRECORDED_OPTIONS = frozenset({"-j", "--jobs", "-w", "--workers", "--chunk"})


def _recorded(argv: Sequence[str]) -> list[str]:
    kept, skip = [], False
    for token in argv:
        name = token.split("=", 1)[0]
        if skip:
            skip = False
        elif token in _UNRECORDED_FLAGS:
            pass
        elif name in _UNRECORDED_OPTIONS:
            skip = "=" not in token
        else:
            kept.append(token)
    return kept


def command_line(output: str) -> str | None:
    """The running command's line with its file arguments relative to output's folder, so
    the record does not depend on where the command ran, and without the options that only
    change what it prints or how fast it runs (None outside the CLI)."""
    invoked = _COMMAND_LINE.get()
    if invoked is None:
        return None
    argv, paths = invoked
    folder = os.path.dirname(os.path.abspath(output))

    def shown(token: str) -> str:
        name, eq, value = token.partition("=")
        if token in paths:
            return os.path.relpath(os.path.abspath(token), folder).replace(os.sep, "/")
        if eq and name.startswith("--") and value in paths:
            return f"{name}={shown(value)}"
        return token

    return shlex.join([argv[0], *(shown(t) for t in _recorded(argv[1:]))])
