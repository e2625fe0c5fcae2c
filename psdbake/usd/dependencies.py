"""Every file a command reads: the given layers and every layer they reach.

Two jobs need the same walk over composition arcs (sublayers, references, payloads,
value clips, variants included):

* **nothing hangs**: USD opens the layers an input reaches by itself while composing, so
  a FIFO or a device behind a sublayer would block it forever; every layer file is
  checked to be a regular file *before* any stage is composed;
* **nothing is lost**: an output must never be one of those files (or a link to one),
  so the output guard (``psdbake.atomic``) compares outputs with this set, not only
  with the paths typed on the command line.

The walk opens layers with ``Sdf`` only (no composition) and follows each layer's
authored asset paths, anchored to that layer, as UsdUtils' dependency extraction does.
Missing files are skipped here: composition reports them with its own message.
"""

from __future__ import annotations

import contextlib
import os
import stat
import time
from collections.abc import Iterable, Iterator

from pxr import Sdf, Tf, UsdUtils

from ..errors import InputError
from .diagnostics import first_line
from .integrity import require_readable_crates
from .nesting import require_shallow

_KIND = ("sublayer", "reference", "payload")  # UsdUtils.ExtractExternalReferences' three lists
#: The layers the walk opened inside ``layers_kept_open`` (innermost context last).
_KEPT: list[list[Sdf.Layer]] = []


@contextlib.contextmanager
def layers_kept_open() -> Iterator[None]:
    """Keep every layer the walk opens open until the context ends. A command walks its
    inputs (to check its outputs) before it composes them, and USD finds a layer that is
    still open instead of reading its file again: without this, a text layer is parsed
    twice per command (a 53 MB CORRECTIVES .usda: 0.25 s each time; 3.0 s for a 1M-point
    asset)."""
    _KEPT.append([])
    try:
        yield
    finally:
        _KEPT.pop()


def fresh(layer: Sdf.Layer | None) -> Sdf.Layer | None:
    """The layer as its file is now. USD keeps one copy of each layer per process, and
    ``FindOrOpen`` returns it even after the file changed: a pipeline that fits, rewrites an
    EXAMPLES file and fits again in one process (keeping the first result, which holds its
    layers open) got the first file's examples. A copy with no edits in memory is read again
    where its file changed (``Reload`` compares the file's time stamp: a stat when it has not);
    one edited in memory is left as it is."""
    if layer is not None and not layer.anonymous and not layer.dirty:
        layer.Reload()
    return layer


def require_regular(path: str, referrer: str | None = None, kind: str = "layer") -> None:
    """Refuse a layer path that exists but is not a regular file (FIFO, device, socket):
    opening it would block or read without end."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # missing or unreadable: open_layer or composition say so, naming it
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return  # folders are refused by open_layer with their own message
    what = "a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a file"
    if referrer:
        raise InputError(f"{referrer}: {kind} {path} is {what}, not a regular file (psdbake reads only regular files)")
    raise InputError(f"{path}: is {what}, not a regular file (psdbake reads only regular files)")


def _is_layer_file(path: str) -> bool:
    ext = os.path.splitext(path)[1].lstrip(".").lower()
    return bool(ext) and Sdf.FileFormat.FindByExtension(ext) is not None


def _innermost(path: str) -> str:
    """The file a (possibly package-relative) path names: ``inner.usdc`` of ``pkg.usdz[inner.usdc]``."""
    return path.rstrip("]").rsplit("[", 1)[-1] if path.endswith("]") else path


def _outer(path: str) -> str:
    """A package-relative path ``pkg.usdz[inner.usdc]`` lives in ``pkg.usdz``."""
    return path.split("[", 1)[0]


def _arcs(layer: Sdf.Layer) -> list[tuple[str, str]]:
    """(kind, authored asset path) of every arc layer authors, sorted."""
    if layer.anonymous or not layer.realPath:
        return sorted(("arc", p) for p in layer.GetCompositionAssetDependencies())
    try:
        groups = UsdUtils.ExtractExternalReferences(layer.identifier)
    except Tf.ErrorException:
        return sorted(("arc", p) for p in layer.GetCompositionAssetDependencies())
    return sorted((kind, p) for kind, paths in zip(_KIND, groups, strict=True) for p in paths)


def _open(path: str, referrer: str | None, kind: str) -> Sdf.Layer | None:
    """The layer at path, None when it is not a layer file psdbake can follow. A layer that
    an input reaches but USD cannot read is named with the layer that reaches it (the file
    given on the command line is opened by ``read.open_layer``, which names it)."""
    outer = _outer(path)
    if not _is_layer_file(_innermost(path)) or not os.path.isfile(outer):
        return None
    try:
        require_readable_crates([outer])
        require_shallow(outer)
    except InputError as exc:
        if referrer is None:
            raise
        raise InputError(f"{referrer}: {kind} {exc}") from None
    try:
        layer = fresh(Sdf.Layer.FindOrOpen(path))
    except Tf.ErrorException as exc:
        if referrer is None:
            return None
        raise InputError(f"{referrer}: {kind} {path} is not a readable USD file ({first_line(exc)})") from None
    if _KEPT and layer is not None:
        _KEPT[-1].append(layer)
    return layer


Walk = tuple[str, str, list[tuple[str, str]]]  # (identifier, name in messages, [(arc kind, absolute path)])
#: Walks of unchanged files, by (absolute path, file identity and times): parsing a text
#: layer is the walk's whole cost (0.25 s for a 53 MB CORRECTIVES .usda), and a command walks
#: its inputs more than once (checking the outputs first, again when it writes them).
_WALKS: dict[tuple, Walk] = {}
#: A file changed this recently may change again within the same timestamp tick, its size
#: too, and look unchanged: its walk is not remembered.
SETTLED_SECONDS = 2.0


def _walk(layer: Sdf.Layer, referrer: str | None) -> Walk:
    name = layer.identifier if not layer.anonymous else (referrer or "an in-memory layer")
    return layer.identifier, name, [(arc, layer.ComputeAbsolutePath(asset) if asset else "") for arc, asset in _arcs(layer)]


def _file_walk(path: str, referrer: str | None, kind: str) -> Walk | None:
    """The walk of the layer file at path (None when it is not a layer psdbake follows),
    remembered while the file is unchanged (same identity, size, mtime and ctime)."""
    try:
        st = os.stat(_outer(path))
    except OSError:
        st = None
    key = None
    if st is not None and time.time() - st.st_ctime >= SETTLED_SECONDS:
        key = (os.path.abspath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        if key in _WALKS:
            return _WALKS[key]
    layer = _open(path, referrer, kind)
    if layer is None:
        return None
    walk = _walk(layer, referrer)
    if key is not None:
        _WALKS[key] = walk
    return walk


def layer_files(items: Iterable[str | Sdf.Layer]) -> list[str]:
    """The real paths of every file the given layers read, themselves included, sorted.

    Raises InputError when a reached layer file is not a regular file or cannot be read."""
    found: set[str] = set()
    pending: list[tuple[Sdf.Layer | str, str | None, str]] = []  # (layer or path, referrer, arc kind)
    items = list(items)
    for item in items:
        if not isinstance(item, Sdf.Layer):
            require_regular(_outer(item))
        pending.append((item, None, "layer"))
    # one probe process for every binary file given (the reached ones are probed as found)
    require_readable_crates([_outer(i) for i in items if not isinstance(i, Sdf.Layer) and os.path.isfile(_outer(i))])
    seen: set[str] = set()
    while pending:
        item, referrer, kind = pending.pop()
        if isinstance(item, Sdf.Layer):
            walk: Walk | None = _walk(item, referrer)
        else:
            if os.path.exists(_outer(item)):
                found.add(os.path.realpath(_outer(item)))
            walk = _file_walk(item, referrer, kind)
        if walk is None or walk[0] in seen:
            continue  # not a layer, or reached before (cycles included)
        identifier, name, arcs = walk
        seen.add(identifier)
        for arc, resolved in arcs:
            if not resolved or not os.path.exists(_outer(resolved)):
                continue  # missing: composition names it
            if _is_layer_file(_innermost(resolved)):
                require_regular(_outer(resolved), name, arc)
            pending.append((resolved, name, arc))
    return sorted(found)
