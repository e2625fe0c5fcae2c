"""``JOBS.toml`` -> a ``Batch`` of tasks: read with limits, every job checked, refused whole.

A job is one table of JOBS.toml (``[[fit]]``, ``[[eval]]``, ...): the command's arguments and
long options by name (``schema``), with ``[defaults]`` merged under every job whose command
takes the key. Relative paths are left as written and each job runs in the jobs file's folder,
so a job file is portable and a job's outputs are byte-identical to the same command typed in
that folder. A chunked eval (``chunk_size`` and ``frames``) becomes one task per chunk
(``plan.eval_chunks``); the order of the tasks comes from the files (``order``).
"""

from __future__ import annotations

import os
import stat
import tomllib
from collections.abc import Mapping, Sequence
from typing import Any

import click

from ..errors import InputError, PsdError
from . import schema
from .order import Job, Part, order
from .plan import eval_chunks
from .tasks import Batch

#: The commands a job may run, in the order of the sculptor's loop (and of messages). Every command
#: that writes files; ``inspect`` prints only and ``batch`` is the runner itself.
COMMANDS = ("pose", "sculpts", "fit", "mirror", "groups", "eval", "stack", "export-gltf", "export-blender", "compare")
_READS = frozenset({"asset", "examples", "poses", "anim", "correctives", "layers", "file"})  # click parameter names
_WRITES = frozenset({"output", "report", "points_cache", "obj_dir"})  # obj_dir: a folder, ordered like a file
#: Parameters whose role is the other one for one command: ``sculpts`` reads the OBJ folder
#: ``pose --obj-dir`` wrote.
_READ_BY = {("sculpts", "obj_dir")}
#: Commands that edit a file in place when no ``output`` is given: ``groups FILE``.
_IN_PLACE = {"groups": "file"}

#: Largest jobs file read. A job is a few hundred bytes, so 1 MiB is thousands of jobs (more
#: than a farm queue takes from one file); the cap keeps a wrong path (a huge log, a disk image)
#: from being read into memory whole.
MAX_JOBS_FILE_BYTES = 1 << 20


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    return "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file"


def _read_toml(path: str) -> dict[str, Any]:
    """The jobs file, if it is a regular file of at most MAX_JOBS_FILE_BYTES: a FIFO, a socket
    or a device (``/dev/zero``, ``/dev/urandom``) would block or never end."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))  # a FIFO must not block the open
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise InputError(f"{path}: a jobs file must be a regular file, this is {_kind(info.st_mode)}")
        if info.st_size > MAX_JOBS_FILE_BYTES:
            raise InputError(f"{path}: {info.st_size} bytes, more than a jobs file may hold "
                             f"({MAX_JOBS_FILE_BYTES} bytes): is this the jobs file?")
        os.set_blocking(fd, True)
        with os.fdopen(fd, "rb") as fh:
            fd = -1
            data = fh.read(MAX_JOBS_FILE_BYTES + 1)  # the file may grow after the fstat
        if len(data) > MAX_JOBS_FILE_BYTES:
            raise InputError(f"{path}: more than a jobs file may hold ({MAX_JOBS_FILE_BYTES} bytes)")
        return tomllib.loads(data.decode("utf-8"))
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not valid TOML: {exc}") from None
    finally:
        if fd >= 0:
            os.close(fd)


def _norm(table: Mapping[str, Any]) -> dict[str, Any]:
    return {k.replace("-", "_"): v for k, v in table.items()}


def _defaults(path: str, doc: Mapping[str, Any], schemas: Mapping[str, Mapping[str, click.Parameter]]) -> dict[str, Any]:
    """``[defaults]``, every key of which some command must take."""
    unknown = sorted(set(doc) - {"defaults", *schemas})
    if unknown:
        raise InputError(f"{path}: unknown table [{unknown[0]}] (expected [defaults] or [[{']], [['.join(schemas)}]])")
    defaults = doc.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError(f"{path} [defaults]: must be a table")
    defaults = _norm(defaults)
    for key in sorted(defaults):
        if not any(key in s for s in schemas.values()):
            raise InputError(f"{path} [defaults]: unknown key {key!r}")
    return defaults


def _parts(name: str, n: int, where: str, values: Mapping[str, Any], keys: Mapping[str, click.Parameter],
           args: list[str], writes: tuple[str, ...]) -> list[Part]:
    """The tasks of one job: the job itself, or one per chunk of a chunked eval."""
    label = f"[[{name}]] #{n}"
    if not ("chunk_size" in values and "chunk" in keys and "chunk" not in values):
        return [Part(label, f"{name}-{n}", args, writes)]
    if "frames" not in values:
        raise InputError(f"{where}: chunk_size needs frames = \"START:END\" to cut the job into tasks "
                         "(psdbake batch does not read the animation to count its samples)")
    try:
        chunks = eval_chunks(values["output"], values.get("points_cache"), values["frames"], values["chunk_size"])
    except PsdError as exc:
        raise InputError(f"{where}: {exc}") from None
    return [Part(f"{label} chunk {k}/{len(chunks)}", f"{name}-{n}-chunk{k}", [*args, f"--chunk={k}"], files)
            for k, files in chunks]


def _refuse_deformers(where: str, table: Mapping[str, Any], keys: Mapping[str, click.Parameter]) -> None:
    """A deformer named in a jobs file is code a data folder would make psdbake run: refused unless
    the batch was started with ``--allow-deformers-from-jobs``."""
    for key, value in table.items():
        if key in keys and keys[key].name == "deformers":
            specs = value if isinstance(value, list) else [value]
            raise InputError(f"{where}: deformer {specs[0]!r} would run code named by the jobs file: deformers are "
                             "taken from the command line only, unless batch is given --allow-deformers-from-jobs")


def _job(name: str, n: int, where: str, values: Mapping[str, Any], command: click.Command,
         keys: Mapping[str, click.Parameter], kept: list[tuple[str, str]]) -> Job:
    """One checked job; the ``--deformer`` sources it names are added to ``kept``."""
    args = schema.arguments(command, values, where)
    paths = {key: schema.values(keys[key], values[key], where, key) for key in values
             if keys[key].name in _READS | _WRITES}
    role = {k: "read" if keys[k].name in _READS or (name, keys[k].name) in _READ_BY else "write" for k in paths}
    in_place = _IN_PLACE.get(name)
    if in_place is not None and not any(keys[k].name == "output" for k in paths):
        role.update({k: "write" for k in paths if keys[k].name == in_place})  # read-modify-write, as fit --group
    reads = tuple(p for k, ps in paths.items() if role[k] == "read" for p in ps)
    writes = tuple(p for k, ps in paths.items() if role[k] == "write" for p in ps)
    for k in values:
        if keys[k].name == "deformers":
            specs = schema.values(keys[k], values[k], where, k)
            kept += [(spec.rpartition(":")[0], f"a --deformer file of {where}") for spec in specs
                     if spec.rpartition(":")[0].endswith(".py")]
    return Job(f"[[{name}]] #{n}", name, reads, writes, _parts(name, n, where, values, keys, args, writes))


def load_jobs(path: str, commands: Mapping[str, click.Command], *, allow_deformers: bool = False) -> Batch:
    """Parse, check and expand a jobs file; refuse it whole (InputError) if any job is wrong.

    commands: the click command of each job table (``[[fit]]`` -> ``psdbake fit``), the CLI's
    own, so a job takes exactly what its command takes; their order is the order messages list
    them in. Passed in: the farm never imports the CLI.
    allow_deformers: accept ``deformer`` keys (``batch --allow-deformers-from-jobs``); without
    it a jobs file naming one is refused, since a deformer is code."""
    doc = _read_toml(path)
    folder = os.path.dirname(os.path.abspath(path))
    schemas = {name: schema.schema(cmd) for name, cmd in commands.items()}
    defaults = _defaults(path, doc, schemas)
    if not allow_deformers:
        for keys in schemas.values():
            _refuse_deformers(f"{path} [defaults]", {k: v for k, v in defaults.items() if k in keys}, keys)
    jobs: list[Job] = []
    kept: list[tuple[str, str]] = [(os.path.abspath(path), "the jobs file itself")]  # read, never written by a job
    for name in doc:  # tables in order of first appearance, jobs in file order
        if name == "defaults":
            continue
        entries = doc[name]
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise InputError(f"{path} [{name}]: jobs are an array of tables: write [[{name}]]")
        keys = schemas[name]
        for n, entry in enumerate(entries, start=1):
            where = f"{path} [[{name}]] #{n}"
            job = _norm(entry)
            for key in job:
                if key not in keys:
                    owned = " (psdbake batch sets it)" if key in ("quiet", "verbose", "json") else ""
                    raise InputError(f"{where}: unknown key {key!r} for psdbake {name}{owned}")
            if not allow_deformers:
                _refuse_deformers(where, job, keys)
            values = {k: v for k, v in defaults.items() if k in keys} | job
            jobs.append(_job(name, n, where, values, commands[name], keys, kept))
    _refuse_overwrites(folder, kept, [(p, f"{path} {j.label}") for j in jobs for p in j.writes])
    return Batch(path, folder, order(path, folder, jobs))


def _same_file(a: str, b: str) -> bool:
    """Same path once links are resolved, or the same file under two names (a hard link)."""
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _refuse_overwrites(folder: str, kept: Sequence[tuple[str, str]], written: Sequence[tuple[str, str]]) -> None:
    """No job may write a file the batch reads but never produces: the jobs file itself (a job's
    ``report = "jobs.toml"``) or a ``--deformer`` source file. Refused at load, before any job runs."""
    for out, where in written:
        target = os.path.join(folder, out)
        for src, what in kept:
            if _same_file(target, os.path.join(folder, src)):
                raise InputError(f"{where}: output {out} is {what}: a job may not overwrite it")
