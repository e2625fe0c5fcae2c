"""What the ``psdbake`` command shows: summaries on stdout, progress, warnings and batch
lines on stderr, and the ``--json``/``--report`` payloads. Only the CLI imports this: the
library returns data and never prints.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any
from warnings import WarningMessage

import click

from . import __version__, outputs, reproducible
from . import tolerances as tol
from .errors import PsdWarning, StrictError

if TYPE_CHECKING:  # the results are only read here: importing them would load numpy and USD with --help
    from .arrays import Progress
    from .farm import JobResult
    from .farm.chunked import ChunkedWeights, WrittenChunks
    from .fitting.groups import GroupChanges
    from .results import FitResult, MirrorResult, SculptsResult, WeightsResult


#: eval -v counts a channel as on in a frame above this weight (a display threshold, not a tolerance).
_SHOWN_ON = 1e-3
#: The summary's group names: longer ones are shortened as the layer's names are (a prefix and
#: 8 hex digits of a hash, ``channels.short_name``), at most _DRIVERS_SHOWN drivers are named a
#: group, and at most _NAMES_SHOWN groups a fit replaced as it routinely does (``-v`` shows
#: every name whole). A real character's combination groups are named after every joint they
#: combine: CesiumMan's longest is 190 characters, and a second fit's "replaced" line ran to
#: 2,900.
_GROUP_WIDTH = 48
_DRIVERS_SHOWN = 4
_NAMES_SHOWN = 8
#: The summary's reason for the vertices of an example solved to its least-squares optimum: not
#: a solver's status (``stalled``, ``max_cycles``), since no nearby offset does better.
AT_OPTIMUM = "out of the chain's reach"


class Ui:
    """Where the CLI talks: summaries to stdout, progress and warnings to stderr."""

    def __init__(self, quiet: bool, verbose: int, as_json: bool) -> None:
        self.quiet, self.verbose, self.as_json = quiet, verbose, as_json
        self.warned: list[str] = []  # every warning shown, for the --json summary

    def say(self, text: str = "") -> None:
        if not self.quiet and not self.as_json:
            click.echo(text)

    def warn(self, text: str) -> None:
        """A warning: on stderr, even with -q or --json (a farm log must see it)."""
        self.warned.append(text)
        click.echo(f"psdbake: warning: {text}", err=True)

    def payload(self, data: Any) -> None:
        """The --json summary, on stdout, with the warnings shown on stderr (unless the summary
        has its own list, as fit's does)."""
        if self.as_json:
            if isinstance(data, dict) and "warnings" not in data:
                data = {**data, "warnings": list(self.warned)}
            click.echo(json.dumps(data, sort_keys=True))

    @contextlib.contextmanager
    def progress(self, label: str) -> Iterator[Progress | None]:
        """A progress bar on a terminal (none when quiet, in --json mode or piped); it is
        closed, and the cursor shown again, when the block ends."""
        if self.quiet or self.as_json or not sys.stderr.isatty():
            yield None
            return
        bar: Any = None

        def update(done: int, total: int, what: str) -> None:
            nonlocal bar
            if bar is None:
                bar = click.progressbar(length=total, label=label, file=sys.stderr, show_pos=True)
                bar.__enter__()
            bar.update(done - bar.pos)

        try:
            yield update
        finally:
            if bar is not None:
                bar.__exit__(None, None, None)

    @contextlib.contextmanager
    def warnings(self) -> Iterator[list[str]]:
        """psdbake's warnings raised meanwhile, each shown as one ``psdbake: warning:`` line. A
        refusal of the inputs stays one line; a result that missed its tolerance (exit 7) keeps
        its warnings, which say why."""
        found: list[str] = []
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PsdWarning)
            try:
                yield found
            except StrictError:
                self._show(caught, found)
                raise
            self._show(caught, found)

    def _show(self, caught: list[WarningMessage], found: list[str]) -> None:
        for w in caught:
            if issubclass(w.category, PsdWarning):
                found.append(str(w.message))
                self.warn(str(w.message))


def json_text(payload: dict) -> str:
    """A JSON side file (``--report``), committed with the command's other outputs."""
    return json.dumps(payload, indent=2, sort_keys=True) + "\n"


# --- fit -----------------------------------------------------------------------------------

def fit_report(result: FitResult, output: str) -> dict:
    """The --report / --json payload: per mesh and example, what was solved and how well, and
    how far the product is from each sculpt through a client's composition."""
    checks = {(c.mesh, c.source, c.time): c for c in result.checks}
    meshes = []
    for m in result.meshes:
        examples = []
        for ex, inv, channel in zip(m.examples, m.inverses, m.channels, strict=True):
            diag = inv.diagonal or 1.0
            check = checks.get((m.mesh, ex.source, ex.time))
            examples.append({
                "product_error_rel": None if check is None else check.error,
                "reproduced": None if check is None else check.reproduced,
                "example": ex.label, "source": ex.source, "time": ex.time, "blend_shape": channel or None,
                "vertices_solved": len(inv.indices), "evaluations": inv.evaluations, "regime": inv.regime,
                "max_residual": inv.max_residual, "rms_residual": inv.rms_residual,
                "max_residual_rel": inv.max_residual / diag, "rms_residual_rel": inv.rms_residual / diag,
                "tolerance": inv.atol, "missed": len(inv.missed),
                "missed_vertices": [int(i) for i in inv.missed[:100]], "missed_statuses": inv.missed_statuses,
                "seconds": round(inv.seconds, 6),
                "at_optimum": inv.at_optimum, "unreachable_fraction": inv.unreachable_fraction,
                "worst_vertices": _worst(inv),
            })
        d = m.driver_data
        meshes.append({
            "gate_groups": list(d.gate_groups), "ramp_gates": list(d.ramp_gates), "channels": list(d.channels),
            "mesh": m.mesh, "group": m.group, "skeleton": m.skeleton, "points": m.point_count, "drivers": list(m.drivers),
            "kernel": d.kernel, "sigma": d.sigma, "degree": d.degree, "examples": examples,
            "condition": None if m.condition != m.condition else m.condition,
            "role": m.role or None, "vertices_moved": m.vertices,
            "columns": len(d.shapes),
        })
    settings = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(result.settings).items()}
    return {
        "psdbake": __version__, "command": "fit", "asset": result.asset, "output": output,
        # as typed, file arguments relative to OUTPUT's folder (None from the library)
        "command_line": outputs.command_line(output),
        "settings": settings,  # as asked: rtol is relative, each example's "tolerance" the absolute one used
        "examples": list(result.example_files), "meshes": meshes, "missed": result.missed,
        "warnings": list(result.warnings), "seconds": round(result.seconds, 6),
        "skipped_examples": list(result.skipped), "layout": list(result.layout),
        "degraded": [f"{c.label} <{c.mesh}>" for c in result.degraded], "written": True,
        "roundtrip_tolerance": tol.ROUNDTRIP_RTOL,
        "numerics": reproducible.describe(),  # the BLAS kernel: fits agree bit for bit where it does
        "explained": [{"mesh": x.mesh, "example": x.label, "source": x.source, "time": x.time, "norm": x.norm,
                       "additive": x.shares[0], "interaction": x.shares[1], "terms_rel": x.terms,
                       "combinations_rel": x.combination} for x in result.splits],
    }


def _worst(inv: Any, count: int = 20) -> list[list[float]]:
    """The example's worst vertices above its tolerance, worst first: [vertex, residual / diagonal]."""
    above = [(float(r), int(i)) for i, r in zip(inv.indices, inv.residual, strict=True) if not r <= inv.atol]
    diag = inv.diagonal or 1.0
    return [[i, r / diag] for r, i in sorted(above, key=lambda p: (-p[0], p[1]))[:count]]


def _unreachable_line(label: str, inv: Any) -> str:
    """Where an example missed: how much of its sculpt is not reproduced, where, and whether the
    solve ended at an optimum or short of one (the solver stopped). An optimum is local: no
    nearby offset reproduces more, which is what a chain that smooths the sculpt away leaves,
    but not a proof that no offset does (on the 1.3k bench rig at a 62 degree elbow, a sculpt
    made through Delta Mush from known offsets that fold its smoothed surface over at the inner
    elbow ends at one 919 times the tolerance; docs/decisions/coupled-inverse-coarse-meshes.md).
    Short of one, a residual whose RMS is ``pieces.REACHABLE_SLACK`` times the tolerance or more
    is said to be mostly out of the chain's reach: sculpts the chain can reproduce end within
    2x of it where they miss at all; the bench rigs' sculpts made on the plain-skinned mesh end
    at 4-800x (the 13k rig's nearly reachable 20 and 40 degree elbows at 4 and 7: "stopped
    short" there)."""
    from .solver.pieces import REACHABLE_SLACK  # here, not at import: --help loads no numpy

    worst = ", ".join(str(v) for v, _ in _worst(inv, 3))
    away = inv.rms_residual / inv.atol if inv.atol > 0 else 0.0
    if inv.at_optimum:
        verdict = "at a least-squares optimum: the deformer chain reproduces no more of it from any nearby offset"
    elif away >= REACHABLE_SLACK:
        verdict = (f"the solver stopped short of an optimum; at {away:,.0f}x the tolerance (RMS) it is mostly what "
                   "the chain cannot reproduce")
    else:
        verdict = "the solver stopped short of an optimum"
    return (f"{label}: {len(inv.missed)} vertices above the tolerance, {inv.unreachable_fraction:.1%} of the sculpt not "
            f"reproduced (worst: {worst}); {verdict}")


def changes_payload(changes: GroupChanges) -> dict:
    """What a write did to the groups already in its CORRECTIVES layer (--json, --report)."""
    return {"added": list(changes.added), "replaced": list(changes.replaced), "kept": list(changes.kept),
            "removed": list(changes.removed), "protected": list(changes.protected), "renamed": list(changes.renamed),
            "origins": {g: changes.origins[g] for g in (*changes.replaced, *changes.removed, *changes.protected)
                        if g in changes.origins}}


def _named(names: Sequence[str], limit: int | None = None, width: int | None = None) -> str:
    """Group names, at most ``limit`` of them (the rest counted), each shortened to ``width``
    bytes as the layer's names are (``channels.short_name``)."""
    from .model.channels import short_name  # here, not at the top: --help must not load numpy

    shown = names if limit is None else names[:limit]
    text = ", ".join(n if width is None else short_name(n, width) for n in shown)
    return text + (f" and {len(names) - len(shown)} more" if len(shown) < len(names) else "")


def say_changes(ui: Ui, changes: GroupChanges, output: str) -> None:
    """One line per kind of change to the groups of output; removals and protections always shown."""
    capped = () if ui.verbose else (_NAMES_SHOWN, _GROUP_WIDTH)
    parts = [f"added {_named(changes.added, *capped)}"] if changes.added else []
    parts += [f"{what} {changes.shown(names, *capped)}" for what, names in (("replaced", changes.replaced),
                                                                  ("removed", changes.removed)) if names]
    parts += [f"renamed {', '.join(changes.renamed)}"] if changes.renamed else []
    if changes.kept:
        parts.append(f"kept {len(changes.kept)}" + (f" ({', '.join(changes.kept)})" if ui.verbose else ""))
    if parts:
        ui.say(f"  groups: {'; '.join(parts)}")
    if changes.protected:
        kept = ", ".join(f"{g} ({changes.origins.get(g, 'origin not recorded')})" for g in changes.protected)
        ui.warn(f"{output}: kept {len(changes.protected)} group(s) fitted from sculpts instead of their mirror: {kept} "
                "(--replace-sculpted replaces them)")


def _say_decomposed(ui: Ui, groups: list, result: FitResult) -> None:
    """One mesh of a default fit: its groups (drivers, the points each moves) and, per example,
    the solve and how much of its corrective the per-joint terms explain (``ExampleSplit``)."""
    first = groups[0]
    ui.say(f"  <{first.mesh}>  {len(groups)} group(s) fitted together from {len(first.examples)} example(s): a term per "
           "joint, combinations on what the terms leave")
    shown_as = {m.group: _named([m.group], width=None if ui.verbose else _GROUP_WIDTH) for m in groups}
    name_width = max(12, *(len(shown_as[m.group]) for m in groups))
    for m in groups:
        d = m.driver_data
        names = [j.split("/")[-1] for j in m.drivers]
        drivers = _named(names, None if ui.verbose or len(names) <= _DRIVERS_SHOWN else _DRIVERS_SHOWN - 1)
        gate = (f"  gated by {', '.join(d.gate_groups)}" if d.gate_groups
                else "  ramp-gated" if len(d.ramp_gates) else "")
        ui.say(f"    {shown_as[m.group]:<{name_width}} {m.role:<11} drivers: {drivers}  points: {m.vertices}  columns: "
               f"{len(d.shapes)}  sigma: {d.sigma:.4g} rad{gate}")
    splits = {(x.source, x.time): x for x in result.splits if x.mesh == first.mesh}
    width = max(28, *(len(ex.label) for ex in first.examples))
    ui.say(f"    {'example':<{width}} {'solved':>7} {'evals':>6} {'max/diag':>10} {'rms/diag':>10} {'missed':>7} "
           f"{'seconds':>8} {'additive':>9} {'interaction':>12}  regime")
    for ex, inv in zip(first.examples, first.inverses, strict=True):
        diag = inv.diagonal or 1.0
        split = splits.get((ex.source, ex.time))
        shares = None if split is None or not split.norm else split.shares
        explained = "-" if shares is None else f"{100 * shares[0]:.0f}%"
        rest = "-" if shares is None else f"{100 * shares[1]:.0f}%"
        ui.say(
            f"    {ex.label:<{width}} {len(inv.indices):>7} {inv.evaluations:>6} {inv.max_residual / diag:>10.2e} "
            f"{inv.rms_residual / diag:>10.2e} {len(inv.missed):>7} {inv.seconds:>8.3f} {explained:>9} {rest:>12}  "
            f"{inv.regime}"
        )


def say_fit(ui: Ui, result: FitResult, output: str, changes: GroupChanges | None = None, *, written: bool = True
            ) -> None:
    solves = result.solves
    solved = sum(len(inv.indices) for inv in solves.values())
    n_meshes = len({m.mesh for m in result.meshes})
    ui.say(f"psdbake fit: {n_meshes} mesh(es), {len(result.meshes)} group(s), {len(solves)} example(s), {solved} "
           f"vertices solved in {result.seconds:.2f} s")
    for mesh in dict.fromkeys(m.mesh for m in result.meshes if m.role):
        _say_decomposed(ui, [m for m in result.meshes if m.mesh == mesh and m.role], result)
    for m in (m for m in result.meshes if not m.role):
        d = m.driver_data
        drivers = ", ".join(j.split("/")[-1] for j in m.drivers)
        cond = f"  cond: {m.condition:.2g}" if m.condition == m.condition else ""
        ui.say(f"  <{m.mesh}>  group: {m.group}  drivers: {drivers}  kernel: {d.kernel}  sigma: {d.sigma:.4g} rad  "
               f"degree: {d.degree}{cond}")
        width = max(28, *(len(ex.label) for ex in m.examples))
        ui.say(f"    {'example':<{width}} {'solved':>7} {'evals':>6} {'max/diag':>10} {'rms/diag':>10} {'missed':>7} "
               f"{'seconds':>8}  regime")
        for ex, inv in zip(m.examples, m.inverses, strict=True):
            diag = inv.diagonal or 1.0
            ui.say(
                f"    {ex.label:<{width}} {len(inv.indices):>7} {inv.evaluations:>6} {inv.max_residual / diag:>10.2e} "
                f"{inv.rms_residual / diag:>10.2e} {len(inv.missed):>7} {inv.seconds:>8.3f}  {inv.regime}"
            )
    if result.skipped:
        ui.say(f"  skipped {len(result.skipped)} example(s) that move other joints than the drivers: "
               + ", ".join(result.skipped))
    if ui.verbose:
        for line in result.layout:
            ui.say(f"  {line}")
    if result.missed:
        why: dict[str, int] = {}
        for inv in result.solves.values():
            # a solve at its least-squares optimum did not stall: what it misses is out of the chain's reach
            statuses = {AT_OPTIMUM: len(inv.missed)} if inv.at_optimum else inv.missed_statuses
            for name, count in statuses.items():
                why[name] = why.get(name, 0) + count
        detail = ", ".join(f"{name} {count}" for name, count in sorted(why.items()))
        ui.warn(f"{output}: {result.missed} vertices missed the fit tolerance ({detail}; see --report; --strict makes "
                "this fatal)")
        for ex, inv in result.solved.values():  # each example once: a default fit's groups all carry it
            if len(inv.missed) and inv.regime != "per-vertex":
                ui.warn(f"{output}: {_unreachable_line(ex.label, inv)}")
    if result.settings.smoothing > 0 and result.checks:
        worst = max(result.checks, key=lambda c: c.error)
        ui.warn(f"{output}: --smoothing {result.settings.smoothing:g}: the product approximates the examples "
                f"(worst {worst.label} <{worst.mesh}>: {worst.error:.2g} of the diagonal)")
    for c in result.degraded:
        ui.warn(f"{output}: DEGRADED: the product misses example {c.label} of <{c.mesh}> by {c.error:.2g} of the "
                f"diagonal (vertex {c.worst_vertex}), more than the round-trip tolerance {tol.ROUNDTRIP_RTOL:g}")
    if changes is not None:
        say_changes(ui, changes, output)
    if written:
        ui.say(f"wrote {output}")


# --- mirror --------------------------------------------------------------------------------

def mirror_report(result: MirrorResult, output: str) -> dict:
    """The --json payload of ``psdbake mirror``: per mirrored group, what was paired and how closely."""
    return {
        "psdbake": __version__, "command": "mirror", "asset": result.asset, "correctives": result.correctives,
        "output": output, "plane": result.settings.plane, "joints": list(result.settings.joints),
        "groups": [{
            "mesh": g.mesh, "source": g.source, "group": g.group, "drivers": [list(p) for p in g.drivers],
            "channels": list(g.driver_data.channels), "gate_groups": list(g.driver_data.gate_groups),
            "vertices": g.vertices, "worst_vertex_rel": g.worst_vertex, "worst_joint_rel": g.worst_joint,
            "kernel": g.driver_data.kernel, "sigma": g.driver_data.sigma,
        } for g in result.groups],
        "skipped": list(result.skipped), "seconds": round(result.seconds, 6),
    }


def say_mirror(ui: Ui, result: MirrorResult, output: str, changes: GroupChanges | None = None) -> None:
    kept = f"; {len(changes.protected)} of them not written (fitted from sculpts there)" if changes and changes.protected else ""
    ui.say(f"psdbake mirror: {len(result.groups)} group(s) mirrored about the {result.settings.plane} plane, "
           f"{sum(g.vertices for g in result.groups)} vertices paired in {result.seconds:.2f} s{kept}")
    for g in result.groups:
        drivers = ", ".join(f"{a.split('/')[-1]} -> {b.split('/')[-1]}" for a, b in g.drivers)
        ui.say(f"  <{g.mesh}>  {g.source} -> {g.group}  drivers: {drivers}  vertices: {g.vertices}  "
               f"worst vertex: {g.worst_vertex:.2e} of the diagonal  worst joint: {g.worst_joint:.2e} of the skeleton")
    if result.skipped:
        ui.say(f"  skipped {len(result.skipped)} group(s):")
        for line in result.skipped:
            ui.say(f"    {line}")
    if changes is not None:
        say_changes(ui, changes, output)
    ui.say(f"wrote {output}")


# --- eval ----------------------------------------------------------------------------------

def say_eval(ui: Ui, result: WeightsResult, output: str, points_cache: str | None) -> None:
    ui.payload({
        "output": output, "points_cache": points_cache, "seconds": round(result.seconds, 6),
        "animations": [
            {"animation": a.animation, "frames": len(a.times), "channels": list(a.channels),
             "psd_channels": a.psd_channels, "first": float(a.times[0]), "last": float(a.times[-1])}
            for a in result.animations
        ],
    })
    frames_n = sum(len(a.times) for a in result.animations)
    ui.say(f"psdbake eval: {frames_n} frame(s) on {len(result.animations)} animation(s) in {result.seconds:.2f} s")
    for a in result.animations:
        ui.say(f"  <{a.animation}>  {a.psd_channels} corrective channel(s), frames {a.times[0]:g}..{a.times[-1]:g}")
        if ui.verbose:  # which correctives fire, how strongly and where
            first = len(a.channels) - a.psd_channels
            for c in range(first, len(a.channels)):
                peak = int(a.weights[:, c].argmax())
                active = int((a.weights[:, c] > _SHOWN_ON).sum())
                ui.say(f"    {a.channels[c]:<48} max {a.weights[peak, c]:.3f} at frame {a.times[peak]:g}, "
                       f"on in {active} of {len(a.times)} frame(s)")
    ui.say(f"wrote {output}" + (f" and {points_cache}" if points_cache else ""))


def say_chunks(ui: Ui, ev: ChunkedWeights, written: WrittenChunks) -> None:
    ui.payload({
        "output": written.manifest, "clip_manifest": written.clip_manifest, "points_cache": written.points_cache,
        "points_cache_clip_manifest": written.points_clip_manifest, "chunk_size": ev.plan.size,
        "chunk_count": written.chunk_count, "first": ev.plan.first, "last": ev.plan.last,
        "stitched": list(written.stitched),
        "chunks": [{"chunk": f.chunk, "first": f.first, "last": f.last, "frames": f.frames, "weights": f.weights,
                    "points_cache": f.points_cache} for f in written.chunks],
        "animations": [{"animation": path, "channels": list(channels)} for path, channels in ev.animations],
    })
    frames_n = sum(f.frames for f in written.chunks)
    ui.say(f"psdbake eval: {len(written.chunks)} of {written.chunk_count} chunk(s) of {ev.plan.size} frame(s), "
           f"{frames_n} frame(s) on {len(ev.animations)} animation(s)")
    for f in written.chunks:
        ui.say(f"  chunk {f.chunk}: frames {f.first:g}..{f.last:g}: wrote {f.weights}"
               + (f" and {f.points_cache}" if f.points_cache else ""))
    ui.say(f"wrote the manifest {written.manifest} (+ {written.clip_manifest})"
           + (f" and {written.points_cache} (+ {written.points_clip_manifest})" if written.points_cache else "")
           + f": it stitches {len(written.stitched)} of the shot's {written.chunk_count} chunk(s) so far")


# --- groups ------------------------------------------------------------------------------

def say_groups(ui: Ui, file: str, groups: list[dict]) -> None:
    meshes = sorted({g["mesh"] for g in groups})
    ui.say(f"{file}: {len({g['group'] for g in groups})} group(s) on {len(meshes)} mesh(es)")
    width = max((len(g["group"]) for g in groups), default=5)
    for g in groups:
        drivers = ", ".join(d.split("/")[-1] for d in g["drivers"])
        gates = (f"  gated by {', '.join(g['gate_groups'])}" if g.get("gate_groups")
                 else "  ramp-gated" if g.get("ramp_gates") else "")
        ui.say(f"  {g['group']:<{width}}  <{g['mesh']}>  drivers {drivers}  {len(g['channels'])} channel(s), "
               f"{g['points']} point(s), {g['examples']} example(s), {g['kernel']} sigma {g['sigma']:.4g}{gates}  "
               f"[{g['origin']}]")


# --- inspect and batch -----------------------------------------------------------------------

def _joint_tree(paths: list[str]) -> list[str]:
    """Joint paths as an indented tree of leaf names, in the skeleton's order."""
    return [f"{'  ' * p.count('/')}{p.split('/')[-1]}" for p in paths]


def say_inspect(file: str, info: dict, verbose: int = 0) -> None:
    for warning in info.get("warnings", []):
        click.echo(f"psdbake: warning: {warning}", err=True)
    kind = outputs.LABELS.get(info.get("kind") or "", "")
    click.echo(f"{file}" + (f": {kind}" if kind else "") + (f", written by `{info['command']}`" if info.get("command") else ""))
    if info.get("layers"):
        click.echo("  layers, strongest first: " + " > ".join(
            f"{layer['path']} ({(layer['role'] or 'unknown').upper().replace('_', ' ')})" for layer in info["layers"]))
    for root in info["skel_roots"]:
        click.echo(f"  SkelRoot <{root}>")
    for skel in info["skeletons"]:
        click.echo(f"  Skeleton <{skel['path']}>: {skel['joints']} joints, animation {skel['animation'] or '-'}")
        for line in _joint_tree(skel.get("joint_paths", [])):
            click.echo(f"      {line}")
    for m in info["meshes"]:
        shapes = f", blend shapes: {', '.join(m['blend_shapes'])}" if m["blend_shapes"] else ""
        click.echo(f"  skinned <{m['path']}>: {m['points']} points, {m['influences']} influences, "
                   f"{m['skinning_method'] or 'classicLinear'}{shapes}")
    for a in info["animations"]:
        span = f"{a['first']:g}..{a['last']:g}" if a["samples"] else "static"
        parts = [f"{a['joints']} joints ({a.get('joint_samples', a['samples'])} samples)"]
        if a["blend_shapes"]:
            parts.append(f"{len(a['blend_shapes'])} blend shapes ({a.get('blend_shape_samples', 0)} weight samples)")
        click.echo(f"  SkelAnimation <{a['path']}>: {', '.join(parts)}, {span}")
    for w in info.get("weights", []):
        click.echo(f"  blend-shape weights over <{w['path']}>: {w['channels']} channels, {w['samples']} samples, "
                   f"{w['first']:g}..{w['last']:g}")
    cache = info.get("kind") in ("points_cache", "clip_manifest")
    for p in info.get("point_samples", []) if cache else ():  # baked points over a shot, not examples to fit
        click.echo(f"  points of <{p['mesh']}>: {p['samples']} samples, {p['first']:g}..{p['last']:g}")
    for e in () if cache else info["examples"]:
        click.echo(f"  examples of <{e['mesh']}> at time codes {', '.join(f'{t:g}' for t in e['time_codes'])}")
    for pose in info.get("poses", []):
        turned = ", ".join(f"{j['joint'].split('/')[-1]} {j['degrees']:g}°" for j in pose["joints"]) or "bind pose"
        click.echo(f"    t={pose['time']:g}: {turned}")
    if info["examples"] and "poses" not in info and not cache:
        click.echo("    (give --asset ASSET to spell out each example's pose)")
    for c in info["correctives"]:
        click.echo(f"  correctives on <{c['mesh']}> group {c['group']} (psd: v{c['version']}): {len(c['shapes'])} shapes from "
                   f"{c['examples']} examples; drivers {', '.join(d.split('/')[-1] for d in c['drivers'])}; "
                   f"{c['pose_space']}, {c['kernel']}, sigma {c['sigma']:.4g}, degree {c['degree']}")
        if verbose:
            for name, count in sorted(c["offsets"].items()):
                click.echo(f"    BlendShape {name}: {count} points")


def batch_lines(jobs_file: str, quiet: bool, verbose: int) -> Callable[[JobResult, int, int], None]:
    """The per-job line on stderr as each job ends (failures always, the rest unless quiet)."""

    def done(r: JobResult, n: int, total: int) -> None:
        if r.status in ("failed", "lost"):
            code = f"exit {r.exit_code}" if r.exit_code is not None else r.status
            click.echo(f"psdbake: error: {jobs_file} {r.label} failed ({code}): {r.error}", err=True)
        elif not quiet:
            extra = f" ({r.error})" if r.status == "skipped" else f" {r.seconds:.2f} s" + (f" on {r.worker}" if verbose else "")
            click.echo(f"psdbake batch: [{n}/{total}] {r.status:<7} {r.label}{extra}", err=True)
        for w in r.warnings:  # even when quiet: a farm log must see them
            click.echo(f"psdbake: warning: {jobs_file} {r.label}: {w}", err=True)

    return done


# --- sculpts -------------------------------------------------------------------------------

def sculpts_payload(result: SculptsResult, output: str) -> dict:
    """The --json summary of ``psdbake sculpts``: per OBJ, what moved and how far."""
    return {
        "psdbake": __version__, "command": "sculpts", "asset": result.asset, "examples": result.examples,
        "obj_dir": result.obj_dir, "output": output, "scale": result.scale, "up_axis": result.up_axis,
        "files": [{"file": f.file, "mesh": f.mesh, "time": f.time, "points": len(f.points), "moved": f.moved,
                   "max_displacement": f.max_displacement, "mean_displacement": f.mean_displacement,
                   "max_displacement_rel": f.max_displacement / (f.diagonal or 1.0), "edited": f.edited}
                  for f in result.files],
        "warnings": list(result.warnings), "seconds": round(result.seconds, 6),
    }


def say_sculpts(ui: Ui, result: SculptsResult, output: str) -> None:
    sculpted = sum(1 for f in result.files if f.moved)
    ui.say(f"psdbake sculpts: {len(result.files)} OBJ file(s), {sculpted} with sculpted vertices, in {result.seconds:.2f} s")
    for f in result.files:
        if f.moved or ui.verbose:
            ui.say(f"  {f.file}  <{f.mesh}> t={f.time:g}: {f.moved} of {len(f.points)} vertices moved, max "
                   f"{f.max_displacement:.4g} ({f.max_displacement / (f.diagonal or 1.0):.2g} of the diagonal), mean "
                   f"{f.mean_displacement:.4g}" + ("" if f.edited else "  (unedited)"))
    untouched = len(result.files) - sculpted
    if untouched and not ui.verbose:
        ui.say(f"  {untouched} file(s) with no vertex moved (-v lists them)")
    ui.say(f"wrote {output}: run psdbake fit {result.asset} {output} -o CORRECTIVES")
