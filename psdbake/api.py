"""The pipeline in plain sight.

fit:   read USD -> pose space -> black-box skinning -> inverse (Powell) -> RBF -> CORRECTIVES
eval:  CORRECTIVES + ANIM -> pose space -> RBF weights -> WEIGHTS (+ points cache)
pose:  ASSET + POSES -> plain UsdSkel skinning per time code -> EXAMPLES to sculpt on

Every function returns data (frozen dataclasses or in-memory layers); nothing here
prints. ``write_*`` export layers atomically.

The machinery of fit, mirror and the OBJ round trip (SciPy's interpolation and spatial
modules among it) is imported by the functions that run it, so ``eval`` loads only what it
uses (every farm chunk pays its start-up).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time as _time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from . import __version__, atomic, outputs
from .arrays import Progress
from .deformers import deformer_files, load_deformers
from .errors import FitError, InputError, OutputError, PsdWarning, StrictError, where
from .fitting.groups import (
    GroupChanges,
    Groups,
    changes_between,
    check_name_case,
    check_not_doubled,
    cross_talk,
    fitted_groups,
    groups_layer,
    is_sculpted,
    merged_groups,
    names_of,
    origin_text,
    read_correctives,
    renamed_group,
    without_groups,
)
from .lookup import did_you_mean, matches
from .model.posespace import active_joints
from .results import FitResult, GltfResult, MirrorResult, PoseResult, SculptsResult, WeightsResult
from .settings import FitSettings, MirrorSettings, SettingError
from .shot.evaluation import animation_weights, correctives_by_animation, posed_points
from .shot.frames import check_authored, frames_of
from .tolerances import ROUNDTRIP_RTOL
from .usd import provenance
from .usd import write as usdwrite
from .usd.author import Layer
from .usd.bindspace import read_bind_space
from .usd.clips import remove_unstitched, stitched_files
from .usd.compose import compose, open_layer, reread
from .usd.describe import describe as describe_file
from .usd.gltf_source import read_gltf_source
from .usd.read import Scene, animation_components, hidden_from_usdskel, holds_skel_root, open_layers, why_hidden
from .usd.schema import psd_prims
from .usd.validate import require_finite_time_samples, require_psd_prims_skinned, validate_animation, validate_skinning
from .usd.valuetypes import Checked

if TYPE_CHECKING:
    from .export.blender.export import BlenderRigResult

__all__ = [  # noqa: RUF022 - in pipeline order; psdbake/__init__.py re-exports exactly these (tests/test_layering.py)
    "pose", "write_pose", "sculpts", "write_sculpts", "fit", "write_correctives", "correctives_layer", "evaluate",
    "weights_layer", "write_weights", "points_cache_layer", "write_points_cache", "mirror", "mirror_reads",
    "write_mirror", "list_groups", "edit_groups", "write_stack", "export_gltf", "export_blender", "describe",
    "files_read",
]


# --- provenance: what every output records, and the check it allows ---------------------------

@contextlib.contextmanager
def _forced(force: bool) -> Iterator[None]:
    """``--force``: within the block, outputs may replace files that are not their own kind's."""
    with atomic.forcing() if force else contextlib.nullcontext():
        yield


def stamped(layer: Any, kind: str, output: str, inputs: Mapping[str, str | Sequence[str]], *,
            rig: Mapping | None = None, deformers: Sequence[str] = (), settings: Mapping | None = None,
            command: bool = True, **more: Any) -> Any:
    """layer stamped with its kind and provenance (``usd.provenance``), paths relative to output."""
    record: dict[str, Any] = {"command": outputs.command_line(output) if command else None,
                              "inputs": provenance.inputs_record(inputs, output)}
    if rig:
        record["rig"] = dict(rig)
    if deformers:
        record["deformers"] = list(deformers)
    if settings is not None:
        record["settings"] = dict(settings)
    record.update(more)
    return provenance.stamp(layer, kind, record)


def check_fitted_on(asset: str, asset_scene: Scene, correctives: str, *, strict: bool = False) -> list[str]:
    """Warn (or, strict, refuse: exit 3) when the asset's rig is not the one CORRECTIVES were
    fitted on: another skinning method, other weights, rest points, geomBindTransform or
    skeleton (``provenance.rig_differences``). A layer from before provenance is not checked."""
    stamp = provenance.read_stamp(correctives)
    recorded = provenance.plain(stamp.get("rig", {}))
    if not recorded:
        return []
    differences = provenance.rig_differences(recorded, provenance.rig_record(asset_scene))
    if not differences:
        return []
    fitted_on = provenance.plain(stamp.get("inputs", {})).get("asset", {}).get("path")
    shown = os.path.normpath(os.path.join(os.path.dirname(correctives), fitted_on)) if fitted_on else "another asset"
    msg = f"{correctives}: fitted on {shown}, not on {asset} as it is: {'; '.join(differences)}"
    if strict:
        raise InputError(f"{msg} (--strict)")
    warnings.warn(f"{msg}: re-fit the correctives for this asset (--strict refuses)", PsdWarning, stacklevel=3)
    return [msg]


# --- fit: read USD -> pose space -> black-box inverse (Powell) -> RBF -> CORRECTIVES -----------

def open_asset(asset: str, notes: list[str] | None = None, others: Sequence[str] = ()) -> Scene:
    """The asset on its own, with every skinned mesh's influences and skeleton validated.
    ``others``: the command's other input files; where the asset has no SkelRoot and one of
    them does, the refusal says the two were given in the other order (a first-day mistake)."""
    scene = Scene([asset])
    try:
        scene.require_skinned()
    except InputError as error:
        if scene.has_skel_root():
            raise
        holder = next((other for other in others if other != asset and holds_skel_root(other)), None)
        if holder is None:
            raise
        raise InputError(f"{error}; {holder} has one: the two look given in the other order (ASSET comes "
                         "first)") from None
    hidden = [f"{where(asset, mesh)}: left out: {why_hidden(scene.stage, blocker)}"
              for mesh, blocker in hidden_from_usdskel(scene.stage)]
    for info in scene.skinned_meshes():
        for msg in validate_skinning(scene, info.path):
            if notes is not None:
                notes.append(msg)
            warnings.warn(msg, PsdWarning, stacklevel=3)
    for msg in hidden:
        if notes is not None:
            notes.append(msg)
        warnings.warn(msg, PsdWarning, stacklevel=3)
    return scene


#: A file path as the library takes it: a str or an ``os.PathLike`` (a ``pathlib.Path``).
PathArg = str | os.PathLike[str]


def as_path(value: object, name: str) -> str:
    """``value`` as the str path the library works with, or a ``SettingError`` naming the
    parameter (not a C++ signature from USD, or an AttributeError from deep inside)."""
    if isinstance(value, str | os.PathLike):
        path = os.fspath(value)
        if isinstance(path, str):
            return path
    raise SettingError(name, type(value).__name__, "must be a file path (str or pathlib.Path)")


def as_paths(value: object, name: str) -> list[str]:
    """A sequence of paths (one path alone counts as a list of one, not as its characters)."""
    if isinstance(value, str | os.PathLike):
        return [as_path(value, name)]
    if not isinstance(value, Sequence | set | frozenset):
        raise SettingError(name, type(value).__name__, "must be a list of file paths")
    return [as_path(v, name) for v in value]


def fit(
    asset: PathArg,
    example_files: Sequence[PathArg] | PathArg,
    settings: FitSettings = FitSettings(),  # noqa: B008 - frozen, so one shared default is safe
    *,
    jobs: int | None = None,
    progress: Progress | None = None,
) -> FitResult:
    """Fit rest-space correctives and their RBF drivers from sculpted examples.

    Paths are str or ``pathlib.Path``. jobs: worker processes for the per-example inverses
    (None: 1, see ``solve.auto_jobs``). The output does not depend on it. With jobs > 1 the
    workers are spawned: a script that calls this must guard its top level with
    ``if __name__ == "__main__":``, as ``multiprocessing`` requires.
    """
    from .fitting.correctives import fit_planned, plan_mesh, plan_systems
    from .fitting.examples import gather_examples
    from .fitting.fitcheck import check_product
    from .solver.solve import clear_caches, share_scene, solve_all

    started = _time.perf_counter()
    asset, example_files = as_path(asset, "asset"), as_paths(example_files, "example_files")
    if not isinstance(settings, FitSettings):
        raise SettingError("settings", type(settings).__name__, "must be a psdbake.FitSettings")
    if jobs is not None and (not isinstance(jobs, int) or jobs < 1):
        raise SettingError("jobs", jobs, "must be a whole number of worker processes, at least 1 (or None)")
    if not example_files:
        raise InputError("fit needs at least one EXAMPLES file")
    notes: list[str] = []
    load_deformers(settings.deformers)  # fail fast on a bad spec; each solve loads its own chain
    asset_scene = open_asset(asset, notes, others=example_files)
    infos = asset_scene.skinned_meshes()
    meshes = _meshes_to_fit(asset, infos, settings, notes)
    skipped: list[str] = []
    layout: list[str] = []  # why a mesh's correctives are one global group, when they are
    left_out: list[str] = []  # groups with no edited example
    try:
        share_scene(asset_scene)  # the solves' rest points and shading come from this stage, not a second one
        per_mesh, tasks = gather_examples(asset, asset_scene, infos, meshes, example_files, settings)  # checked
        plans, systems = {}, {}
        for info in [i for i in infos if i.path in per_mesh]:
            if not settings.drivers and not any(active_joints(np.array([e.pose for e in per_mesh[info.path]]))):
                left_out.append(f"<{info.path}>: its skeleton <{info.skeleton}> never leaves its bind pose")
                _skip(notes, f"{where(asset, info.path)}: every example is at the bind pose of its skeleton "
                             f"<{info.skeleton}>, so no joint can drive a corrective for it: skipped (an edit at the bind "
                             "pose belongs in the asset itself)")
                continue
            plan = plan_mesh(asset, info, per_mesh[info.path], settings)  # who drives what
            plans[info.path] = plan
            systems[info.path] = plan_systems(asset, info, per_mesh[info.path], plan, settings, notes)
            skipped += [f"{per_mesh[info.path][i].label} <{info.path}>" for i in plan.unused]
            if plan.why:
                layout.append(f"{where(asset, info.path)}: one global correctives group 'main': {plan.why}")
        used = {(p, per_mesh[p][i].source, per_mesh[p][i].time) for p, plan in plans.items()
                for i in plan.examples(len(per_mesh[p]))}
        wanted = [t for t in tasks if (t.mesh, t.source, t.time) in used]
        solved = dict(zip([(t.mesh, t.source, t.time) for t in wanted], solve_all(wanted, jobs, progress), strict=True))
        fits, splits = [], []
        for info in [i for i in infos if i.path in plans]:  # the groups, mesh by mesh
            examples = per_mesh[info.path]
            mine = {i: solved[(info.path, e.source, e.time)] for i, e in enumerate(examples)
                    if (info.path, e.source, e.time) in solved}
            mesh_fits, mesh_splits = fit_planned(asset, asset_scene, info, examples, mine, plans[info.path], settings,
                                                 notes, systems[info.path], left_out)
            fits += mesh_fits
            splits += mesh_splits
            _note_normals(asset, info.path, notes)
        if not fits:
            raise FitError(f"{', '.join(example_files)}: nothing to correct: {'; '.join(left_out)}")
        # for write_correctives: the asset's layers and the EXAMPLES files still open, so no input is parsed twice
        held = {layer.identifier: layer for layer in [*asset_scene.file_layers(), *open_layers(example_files)]}
    finally:
        clear_caches()  # the example stages die with the fit
    result = FitResult(asset=asset, example_files=tuple(example_files), settings=settings, meshes=tuple(fits),
                       warnings=tuple(notes), skipped=tuple(skipped), layout=tuple(layout), splits=tuple(splits),
                       input_layers=tuple(held[k] for k in sorted(held)), rig=provenance.rig_record(asset_scene))
    for note in cross_talk(result, fitted_groups(result)):  # why an example may not be reproduced, said before the check
        notes.append(note)
        warnings.warn(note, PsdWarning, stacklevel=2)
    checks = check_product(result, correctives_layer(result), load_deformers(settings.deformers))
    return dataclasses.replace(result, checks=checks, warnings=tuple(notes), seconds=_time.perf_counter() - started)


def _skip(notes: list[str], msg: str) -> None:
    notes.append(msg)
    warnings.warn(msg, PsdWarning, stacklevel=3)


def resolve_meshes(asset: str, skinned: Sequence[str], wanted: Sequence[str]) -> list[str]:
    """The skinned meshes ``--mesh`` names (full paths or unambiguous leaf names), in the asset's order."""
    chosen = set()
    for mesh in wanted:
        hits = matches(mesh, skinned)
        if len(hits) != 1:
            problem = (f"is not a skinned mesh of the asset (skinned: {', '.join(skinned)}){did_you_mean(mesh, skinned)}"
                       if not hits else f"is ambiguous ({', '.join(hits)}): give its full path")
            raise SettingError("meshes", mesh, problem, location=asset)
        chosen.add(hits[0])
    return [m for m in skinned if not wanted or m in chosen]


def _meshes_to_fit(asset: str, infos: Sequence[Any], settings: FitSettings, notes: list[str]) -> list[str]:
    """The meshes to fit: ``--mesh`` (resolved), and with ``--driver`` only those whose skeleton
    has the drivers: a file with several skeletons (a head's, each hand's) skins each mesh by one,
    and a driver of one cannot drive another's meshes. A driver no skeleton has, or one the
    chosen meshes' skeletons lack, is refused naming the skeletons that have it (--mesh)."""
    meshes = resolve_meshes(asset, [m.path for m in infos], settings.meshes)
    if not settings.drivers:
        return meshes
    by_path = {m.path: m for m in infos}
    lacking = {m: [d for d in settings.drivers if not matches(d, by_path[m].joints)] for m in meshes}
    usable = [m for m in meshes if not lacking[m]]
    if usable and not settings.meshes:
        for m in sorted(set(meshes) - set(usable)):
            _skip(notes, f"{where(asset, m)}: skipped: its skeleton <{by_path[m].skeleton}> has no joint "
                         f"{lacking[m][0]!r} (--driver)")
        return usable
    bad = next(m for m in meshes if lacking[m])
    name = lacking[bad][0]
    owners = sorted({i.skeleton for i in infos if matches(name, i.joints)})
    hint = (f"; it is a joint of <{owners[0]}>, which skins "
            f"{', '.join(i.path.rsplit('/', 1)[-1] for i in infos if i.skeleton == owners[0])}: choose those with --mesh"
            if owners else did_you_mean(name, [j for i in infos for j in i.joints]))
    raise SettingError("drivers", name, f"is not a joint of skeleton <{by_path[bad].skeleton}>, which skins "
                       f"<{bad}>{hint}", location=asset)


def _note_normals(asset: str, mesh: str, notes: list[str]) -> None:
    """Warn when a mesh authors shading normals psdbake cannot give normalOffsets to."""
    from .solver.solve import cached_shading

    why_not = cached_shading(asset, mesh).why_not  # read once for the solves and this note
    if why_not and not why_not.startswith(("no authored normals", "not a Mesh")):
        msg = f"{where(asset, mesh)}: no normalOffsets written: {why_not}"
        notes.append(msg)
        warnings.warn(msg, PsdWarning, stacklevel=3)


def files_read(paths: Sequence[str], deformers: Sequence[str] = ()) -> list[str]:
    """Every file a command reads: the given layers, every layer they reach (sublayers,
    references, payloads, clips) and the ``--deformer`` source files. No output may be
    one of them (``atomic.check_output``); layer files that are not regular files
    (a FIFO would block USD) are refused here, before anything is composed."""
    return sorted(set(usdwrite.files_read(paths)) | set(deformer_files(deformers)))


@contextlib.contextmanager
def updating(path: str, *also: str) -> Iterator[None]:
    """A read-modify-write of the layer at path: the update lock on the folders of path and of
    also (the other files written in the same commit), then path re-read from disk
    (``compose.reread``), so the read inside the block is the last writer's result, never a
    copy this process loaded before it waited."""
    with atomic.updating(path, *also):
        reread(path)
        yield


@contextlib.contextmanager
def mirror_lock(correctives: str, output: str) -> Iterator[None]:
    """``mirror`` in place (output is CORRECTIVES itself) reads, mirrors and writes under the
    update lock, CORRECTIVES re-read inside it: one step between any two other writers of the
    layer, as if run alone. Otherwise nothing: CORRECTIVES is then an input like any other."""
    if os.path.realpath(output) != os.path.realpath(correctives):
        yield
        return
    with updating(output):
        yield


def existing_groups(asset: str, path: str) -> tuple[Groups, dict[str, dict]]:
    """The groups of the CORRECTIVES layer at path and their provenance records ({} when path
    holds no CORRECTIVES layer: nothing there is carried over). Another asset's layer (none of
    its meshes skinned by ASSET) is refused as an output (exit 6), or, forced
    (``atomic.forcing``), treated as empty: it is replaced whole. A damaged one is bad input."""
    if not os.path.isfile(path) or provenance.existing_kind(path) != "correctives":
        return {}, {}
    records = provenance.plain(provenance.read_stamp(path).get("groups", {}))
    owners = sorted(psd_prims(open_layer(path)))
    if owners and not {m.path for m in Scene([asset]).skinned_meshes()}.intersection(owners):
        if atomic.forced():  # another asset's layer: replaced whole
            return {}, {}
        raise OutputError(f"{path}: holds CORRECTIVES for {', '.join(f'<{m}>' for m in owners)}, which {asset} does "
                          "not skin: another asset's CORRECTIVES layer; write to another file, or give --force to "
                          "replace it")
    return read_correctives(asset, path), records if isinstance(records, dict) else {}


def _check_not_dropping(path: str, asset: str, groups: Groups, command: str) -> None:
    """``mirror`` or ``groups`` writing a CORRECTIVES layer other than the one they read
    replaces it whole: refused (unless forced) where that drops groups it holds, as a plain
    fit is (``write_correctives``), or where it is another asset's layer."""
    if atomic.forced():
        return
    before, records = existing_groups(asset, path)
    _refuse_dropping(path, sorted(names_of(before) - names_of(groups)), records, command,
                     "It replaces the whole layer: write to another file, update that layer in place, or give --force "
                     "to replace it")


def _refuse_dropping(path: str, lost: Sequence[str], records: Mapping[str, Any], command: str, remedy: str) -> None:
    """Refuse (exit 6, unless forced) a write of the CORRECTIVES layer at path that would drop
    the groups ``lost``, each named with where it came from."""
    if lost and not atomic.forced():
        raise OutputError(f"{path}: holds groups this {command} would drop: "
                          f"{', '.join(f'{g} ({origin_text(records.get(g))})' for g in lost)}. {remedy}")


def _settings_record(settings: FitSettings) -> dict[str, Any]:
    return {k: v for k, v in dataclasses.asdict(settings).items() if k not in ("deformers", "group")}


def fit_failure(result: FitResult, output: str, *, strict: bool, allow_degraded: bool) -> str | None:
    """Why this fit must not be written (``StrictError``, exit 7), or None: a degraded product
    (unless allowed) or, strict, any vertex that missed the fit tolerance. ``write_correctives``
    refuses the first itself, so a pipeline calling the library cannot write one unknowingly."""
    if strict and result.missed:
        return f"{output}: not written: {result.missed} vertices missed the tolerance (--strict)"
    if result.degraded and not allow_degraded:
        worst = max(result.degraded, key=lambda c: c.error)
        return (f"{output}: not written: the product does not reproduce {len(result.degraded)} of {len(result.checks)} "
                f"example(s) within {ROUNDTRIP_RTOL:g} of the diagonal (worst {worst.label} <{worst.mesh}>: "
                f"{worst.error:.2g}, vertex {worst.worst_vertex}); see the warnings above, or give --allow-degraded to "
                "write it anyway")
    return None


def write_correctives(result: FitResult, path: PathArg, *, update: bool = False,
                      side_files: Sequence[tuple[str, str]] = (), force: bool = False,
                      allow_degraded: bool = False) -> GroupChanges:
    """Export CORRECTIVES atomically; inputs are never overwritten. Returns what happened to
    the groups already at path.

    update (``fit --group``): keep path's other groups, this fit's groups replacing their
    namesakes. Without it path is replaced, but only when every group it holds that this fit
    does not write came from an earlier plain fit: groups from ``--group`` fits or ``mirror``
    are not dropped without ``force``. Either way the read, the checks and the rename happen
    under a lock, so concurrent writers of one layer serialise. A group that would double
    another's correction (the same driver, neither a combination) is refused (exit 4).
    side_files: (path, text) written in the same commit (``fit --report``): both land or neither.
    A degraded fit (``FitResult.degraded``: the product misses an example through UsdSkel) is
    refused (``StrictError``, nothing written) unless ``allow_degraded``, as ``fit`` refuses it.
    """
    if not isinstance(result, FitResult):
        raise SettingError("result", type(result).__name__, "must be the FitResult psdbake.fit returned "
                           "(write_correctives(result, path))")
    path = as_path(path, "path")
    failure = fit_failure(result, path, strict=False, allow_degraded=allow_degraded)
    if failure:
        raise StrictError(failure.replace("give --allow-degraded", "give --allow-degraded (allow_degraded=True)"))
    inputs = files_read([result.asset, *result.example_files], result.settings.deformers)
    written = fitted_groups(result)
    with _forced(force):
        atomic.check_output(path, inputs, kind=outputs.CORRECTIVES)
        with updating(path, *(side for side, _ in side_files)):
            before, records = existing_groups(result.asset, path)
            if update:
                check_name_case(before, written, path)
                groups = merged_groups(before, written, result.settings.meshes)
            else:
                groups = written
                lost = sorted(g for g in names_of(before) - names_of(written)
                              if (records.get(g) or {}).get("origin") != "fit")
                _refuse_dropping(path, lost, records, "fit",
                                 "A fit without --group replaces the whole layer: fit into it with --group, remove them "
                                 f"first (psdbake groups {path} --remove NAME), or give --force to replace the layer")
            check_not_doubled(groups, written, path)
            for note in cross_talk(result, groups):  # with the groups carried over (its own: said by fit)
                if note not in result.warnings:
                    warnings.warn(note, PsdWarning, stacklevel=2)
            entry = {"origin": "fit --group" if update else "fit", "command": outputs.command_line(path),
                     **provenance.inputs_record({"examples": list(result.example_files)}, path),
                     "settings": _settings_record(result.settings), "deformers": list(result.settings.deformers)}
            kept = {g: r for g, r in records.items() if g in names_of(groups)}
            layer = groups_layer(result.asset, groups, f"psdbake {__version__} fit: rest-space correctives (inverse PSD)")
            stamped(layer, "correctives", path, {"asset": result.asset}, rig=result.rig, command=False,
                    groups={**kept, **{g: entry for g in names_of(written)}})
            usdwrite.export_all([(path, layer), *side_files], inputs)
    return changes_between(before, groups, written, records, routine="fit --group of" if update else "fit of")


def write_fit_report(result: FitResult, path: str, text: str, *, force: bool = False) -> str:
    """The ``--report`` of a fit that wrote no CORRECTIVES (degraded, or refused by ``--strict``):
    the diagnosis on its own, so the fit need not be run again to read it."""
    with _forced(force):
        usdwrite.export_all([(path, text)], files_read([result.asset, *result.example_files], result.settings.deformers))
    return path


def correctives_layer(result: FitResult) -> Any:
    """CORRECTIVES of one fit as an in-memory layer (BlendShapes, bindings, psd: driver data),
    stamped with its kind only: ``write_correctives`` adds the provenance of the path it writes."""
    layer = groups_layer(result.asset, fitted_groups(result), f"psdbake {__version__} fit: rest-space correctives "
                         "(inverse PSD)")
    return provenance.stamp(layer, "correctives")


# --- eval: CORRECTIVES + ANIM -> pose space -> RBF weights -> WEIGHTS (+ points cache) ---------

def evaluate(
    asset: PathArg,
    correctives: PathArg,
    anim: PathArg,
    *,
    frames: tuple[float, float] | None = None,
    progress: Progress | None = None,
    strict: bool = False,
    hold: bool = False,
    shot: tuple[float, float] | None = None,
    meshes: Sequence[str] = (),
) -> WeightsResult:
    """RBF weights of every corrective at every frame of ANIM. Warns when ASSET's rig is not
    the one CORRECTIVES were fitted on (strict: refuses, exit 3).

    frames: whole frames A..B, within ANIM's authored samples unless ``hold``; ``shot``: the
    range to check instead (a farm chunk checks the whole shot's, so every chunk agrees);
    meshes: only these meshes' correctives (full paths or leaf names). Paths are str or
    ``pathlib.Path``."""
    started = _time.perf_counter()
    asset, correctives, anim = as_path(asset, "asset"), as_path(correctives, "correctives"), as_path(anim, "anim")
    if frames is not None and not (isinstance(frames, tuple | list) and len(frames) == 2):
        raise SettingError("frames", frames, "must be (first, last), e.g. psdbake.parse_frames('1:10')")
    asset_scene = open_asset(asset, others=(correctives, anim))
    check_fitted_on(asset, asset_scene, correctives, strict=strict)
    scene = Scene([anim, correctives, asset], label=correctives, checked=Checked.NO_SHAPE_VALUES)  # weights read no offsets
    scene.require_skinned()
    require_psd_prims_skinned(scene, correctives, asset)
    per_anim = correctives_by_animation(scene, Scene([anim, asset], label=anim), correctives, anim)
    if meshes:
        chosen = set(resolve_meshes(asset, sorted({i.path for e in per_anim.values() for i, _ in e}), meshes))
        per_anim = {a: kept for a, e in per_anim.items() if (kept := [x for x in e if x[0].path in chosen])}
    if not per_anim:
        raise InputError(f"{correctives}: no psd: driver data on any skinned mesh of {asset}")
    if frames is not None and shot is not None:
        for a in sorted(per_anim):
            check_authored(scene, per_anim[a][0][0].path, shot, anim, hold=hold)
        hold = True  # checked on the shot's range: a chunk's own frames lie inside it
    planned = {a: frames_of(scene, per_anim[a][0][0].path, frames, label=anim, hold=hold) for a in sorted(per_anim)}
    total, done = sum(len(planned[a]) * len(per_anim[a]) for a in planned), 0

    def tick(mesh: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, mesh)

    results = tuple(animation_weights(scene, a, per_anim[a], planned[a], correctives, anim, tick) for a in sorted(per_anim))
    fps = scene.stage.GetTimeCodesPerSecond()
    return WeightsResult(asset, correctives, anim, results, fps, _time.perf_counter() - started,
                         rig=provenance.rig_record(asset_scene))


def weights_layer(result: WeightsResult) -> Layer:
    """WEIGHTS as an in-memory layer, stamped with its kind only (``stamp_weights`` adds the
    provenance of the path it is written to)."""
    return provenance.stamp(usdwrite.weights_layer(
        f"psdbake {__version__} eval: corrective blend-shape weights",
        [(a.animation, a.channels, a.times, a.weights) for a in result.animations],
        result.fps,
        usdwrite.asset_metadata(result.asset),
    ), "weights")


def stamp_weights(layer: Layer, kind: str, result: WeightsResult, path: str, deformers: Sequence[str] = (), *,
                  command: bool = True) -> Layer:
    """A WEIGHTS layer or points cache of ``eval`` stamped for path (``provenance``)."""
    contained = bool(provenance.stamp_of(layer).get("selfContained"))
    return stamped(layer, kind, path, {"asset": result.asset, "correctives": result.correctives, "anim": result.anim},
                   rig=result.rig, deformers=deformers if kind == "points_cache" else (), command=command,
                   selfContained=contained or None)


def write_weights(result: WeightsResult, path: PathArg, *, points_cache: tuple[str, Layer] | None = None,
                  deformers: Sequence[str] = (), force: bool = False) -> str:
    """Export WEIGHTS (and, given as (path, layer), the points cache in the same commit:
    both land or neither)."""
    if not isinstance(result, WeightsResult):
        raise SettingError("result", type(result).__name__, "must be the WeightsResult psdbake.evaluate returned "
                           "(write_weights(result, path))")
    path = as_path(path, "path")
    written = [(path, stamp_weights(weights_layer(result), "weights", result, path))]
    if points_cache:
        written.append((points_cache[0], stamp_weights(points_cache[1], "points_cache", result, points_cache[0],
                                                       deformers)))
    paths = [p for p, _ in written]
    with _forced(force), updating(*paths):  # one step for another eval writing here (a farm chunk)
        earlier = [f for p in paths for f in stitched_files(p)]  # a chunked eval's, now replaced by one layer
        inputs = files_read([result.asset, result.correctives, result.anim], deformers)
        usdwrite.export_all(written, inputs)
        remove_unstitched(earlier, [*paths, *inputs])  # an old chunk read as an input (--anim) stays
    return path


def points_cache_layer(result: WeightsResult, deformers: Sequence[str] = (), *, progress: Progress | None = None,
                       self_contained: bool = False) -> Layer:
    """Final posed points per frame (correctives, existing shapes, skinning, deformers),
    as a layer that needs no UsdSkel: the SkelRoots become Xforms, like BakeSkinning.
    The asset's authored shading normals are blocked (they are rest normals), so renderers
    derive normals from the cached points.

    The points come from UsdSkel evaluating the stack ASSET + CORRECTIVES + ANIM + WEIGHTS
    (the correctives are ordinary blend shapes there), then the deformer chain.

    The layer holds overrides only (points, extents, the retyping), to be stacked over the asset;
    ``self_contained``: the cache over the asset flattened into one layer (topology, transforms,
    materials and all), which opens on its own.
    """
    chain = load_deformers(deformers)
    # WEIGHTS only drives UsdSkel here: without the asset's metadata, which would open the
    # asset once more before the stage does (a second parse of a large .usda)
    drive = usdwrite.weights_layer("psdbake eval: weights driving the points cache",
                                   [(a.animation, a.channels, a.times, a.weights) for a in result.animations], result.fps)
    # evaluate checked these files' value types but the offsets, which UsdSkel applies here
    scene = Scene([drive, result.anim, result.correctives, result.asset], label=result.correctives,
                  checked=Checked.SHAPE_VALUES)
    times = sorted({float(t) for a in result.animations for t in a.times})
    meshes = scene.skinned_meshes()
    layer = usdwrite.points_layer(
        f"psdbake {__version__} eval: points cache ("
        + ("self-contained, no UsdSkel needed)" if self_contained else "no UsdSkel needed; overrides to stack over ASSET)"),
        scene.skel_roots, posed_points(scene, scene, meshes, times, chain, progress), times, result.fps,
        usdwrite.asset_metadata(result.asset),
        blocked=[(m.path, name) for m in meshes for name in ("normals", "primvars:normals")
                 if scene.prim(m.path).GetAttribute(name).HasAuthoredValue()],
    )
    if self_contained:
        layer = usdwrite.flattened(layer, result.asset)
    return provenance.stamp(layer, "points_cache", {"selfContained": True} if self_contained else {})


def write_points_cache(result: WeightsResult, path: str, deformers: Sequence[str] = (), *,
                       progress: Progress | None = None, force: bool = False) -> str:
    layer = stamp_weights(points_cache_layer(result, deformers, progress=progress), "points_cache", result, path,
                          deformers)
    with _forced(force):
        return usdwrite.export_atomic(layer, path, files_read([result.asset, result.correctives, result.anim], deformers))


# --- export-gltf: ASSET + CORRECTIVES + ANIM + eval's weights -> one .glb for game engines ---

def export_gltf(asset: str, correctives: str, anim: str, output: str, *, frames: tuple[float, float] | None = None,
                progress: Progress | None = None, strict: bool = False, force: bool = False, hold: bool = False
                ) -> GltfResult:
    """Write the shot as a skinned glTF 2.0 binary: meshes, skins, joint animation (one
    key per time code), every BlendShape channel of the composed stack as a morph target
    and eval's weights animating them. Skinned in glTF (linear blend), it gives
    ``UsdSkel.BakeSkinning``'s world-space points of ASSET + CORRECTIVES + ANIM + WEIGHTS,
    in glTF's Y-up meters."""
    from .export import gltf  # pygltflib loads only for this command

    inputs = files_read([asset, correctives, anim])
    with _forced(force):
        atomic.check_output(output, inputs, kind=outputs.GLTF)  # before the work, so a bad output fails at once
    weights = evaluate(asset, correctives, anim, frames=frames, progress=progress, strict=strict, hold=hold)
    scene = Scene([anim, correctives, asset], label=correctives)
    source = read_gltf_source(scene, asset, {a.animation: (a.channels, a.times, a.weights) for a in weights.animations})
    for msg in gltf.differences(source, asset):
        warnings.warn(msg, PsdWarning, stacklevel=2)
    name = os.path.splitext(os.path.basename(anim))[0] or "animation"
    glb = gltf.build_glb(source, name, f"psdbake {__version__} export-gltf")
    with _forced(force):
        gltf.write_glb(glb.data, output, inputs)
    return GltfResult(output, weights, tuple(m.path for m in source.meshes), glb.morph_targets, glb.sparse_targets,
                      max((len(s.times) for s in source.skeletons), default=0), len(glb.data))


def export_blender(asset: str, correctives: str, output: str, *, anim: str | None = None, blender: str | None = None,
                   strict: bool = False, force: bool = False) -> BlenderRigResult:
    """Write a .blend with the correctives driven live by the armature's pose: Blender's USD
    import of ASSET + CORRECTIVES (+ ANIM), one shape key per channel, drivers computing the
    ``psd:`` formula in simple expressions (``psdbake.blender``). ``blender``: a Blender
    executable or a Python with the bpy module (default: $PSDBAKE_BLENDER, else ``blender``)."""
    from .export.blender.export import export_blender as build  # the compiler loads only for this command

    inputs = files_read([asset, correctives, *([anim] if anim else [])])
    check_fitted_on(asset, open_asset(asset, others=(correctives, *([anim] if anim else []))), correctives, strict=strict)
    if anim is not None:  # what eval refuses, Blender would import as a rig that never moves, or a mesh cache
        if provenance.authors_point_samples(anim):
            raise InputError(f"{anim}: authors time-sampled points (an EXAMPLES layer or a points cache): Blender would "
                             "import them as a mesh cache over the rig; give an ANIM layer (psdbake inspect says what "
                             "a file is)")
        correctives_by_animation(Scene([anim, correctives, asset], label=correctives), Scene([anim, asset], label=anim),
                                 correctives, anim)
    with _forced(force):
        return build(asset, correctives, output, anim=anim, blender=blender, inputs=inputs)


# --- pose: ASSET + POSES -> plain UsdSkel skinning per time code -> EXAMPLES to sculpt on -------

def pose(asset: str, poses: str, deformers: Sequence[str] = (), *, progress: Progress | None = None,
         frames: tuple[float, float] | None = None, hold: bool = False, meshes: Sequence[str] = ()) -> PoseResult:
    """EXAMPLES to sculpt on: skinned points per time code of POSES, with the pose itself.

    frames: whole frames A..B of POSES instead of its time codes (the frames of a shot to fix),
    within its authored samples unless ``hold``; meshes: only these (full paths or leaf names)."""
    chain = load_deformers(deformers)
    asset_scene = open_asset(asset, others=(poses,))
    scene = Scene([poses, asset], label=poses)
    wanted = set(resolve_meshes(asset, [m.path for m in scene.skinned_meshes()], meshes))
    posed = [m for m in scene.skinned_meshes() if m.path in wanted]
    for info in posed:
        validate_animation(scene, info.path)
        if (anim_path := scene.animation_prim(info.path)) is not None:
            require_finite_time_samples(scene, anim_path, poses)
    anims = sorted({a for m in posed if (a := scene.animation_prim(m.path))})
    if not anims:
        raise InputError(f"{poses}: no SkelAnimation is bound to the skeleton (skel:animationSource)")
    times = sorted({t for m in posed for t in scene.animation_times(m.path)})
    if frames is not None:
        animated = [m for m in posed if scene.animation_prim(m.path) is not None]
        times = sorted({float(t) for m in animated for t in frames_of(scene, m.path, frames, poses, hold=hold)})
    if not times:
        raise InputError(f"{where(poses, anims[0])}: the animation has no time samples: nothing to pose (give --frames "
                         "to pose its static pose)")
    animations, seen = [], set()
    for info in posed:
        if scene.animation_prim(info.path) is None or info.skeleton in seen:
            continue
        seen.add(info.skeleton)
        path, joints, channels, anim_samples = animation_components(scene, info.path, times)
        animations.append((info.skeleton, path, joints, channels, anim_samples))
    layer = provenance.stamp(usdwrite.examples_layer(
        f"psdbake {__version__} pose: skinned examples to sculpt on", animations,
        posed_points(asset_scene, scene, posed, times, chain, progress), times, scene.stage.GetTimeCodesPerSecond(),
        usdwrite.asset_metadata(asset),
    ), "examples")
    return PoseResult(asset, poses, tuple(times), tuple(m.path for m in posed), layer, tuple(deformers),
                      rig=provenance.rig_record(asset_scene))


def write_pose(result: PoseResult, path: str, obj_dir: str | None = None, *, force: bool = False) -> str:
    """Export EXAMPLES atomically; with obj_dir, also one OBJ per skinned mesh and time code
    plus ``manifest.json`` there, all in the same commit (``objloop``)."""
    from .sculpting import loop as objloop

    inputs = files_read([result.asset, result.poses], result.deformers)
    stamped(result.layer, "examples", path, {"asset": result.asset, "poses": result.poses}, rig=result.rig,
            deformers=result.deformers)
    with _forced(force):
        if obj_dir is None:
            return usdwrite.export_atomic(result.layer, path, inputs)
        objloop.write_pose_objs(result, path, obj_dir, inputs)
    return path


# --- sculpts: the OBJs of pose --obj-dir, sculpted -> EXAMPLES for fit --------------------------

def check_obj_dir(obj_dir: str, inputs: Sequence[str] = ()) -> None:
    """Refuse an OBJ folder pose cannot fill (before the work; exit 6)."""
    from .sculpting.obj.folder import check_obj_dir as check_obj_folder

    check_obj_folder(obj_dir, inputs)


def obj_files(result: PoseResult) -> list[str]:
    """The OBJ file names ``write_pose(..., obj_dir)`` writes for result."""
    from .sculpting import loop as objloop

    return objloop.obj_files(result)


def sculpts(asset: str, examples: str, obj_dir: str, *, scale: float | None = None,
            up_axis: str | None = None, fixes: Mapping[str, Mapping[str, Any]] | None = None) -> SculptsResult:
    """Read back the sculpted OBJs of obj_dir (listed in its manifest) over EXAMPLES, the layer
    ``pose`` wrote with them: each file checked (vertex count, faces, finite, near its posed
    mesh), ``scale`` and ``up_axis`` applied first, or per file (``fixes``: OBJ file name ->
    {"scale": S, "up_axis": "Z"}). Every bad file is named in one refusal."""
    from .sculpting import loop as objloop

    return objloop.read_sculpts(asset, examples, obj_dir, scale=scale, up_axis=up_axis, fixes=fixes)


def write_sculpts(result: SculptsResult, path: str, *, force: bool = False) -> str:
    """Export SCULPTED_EXAMPLES (EXAMPLES with the sculpted points) atomically; no input, OBJ
    or manifest may be the output."""
    from .sculpting import loop as objloop

    layer = stamped(objloop.sculpts_layer(result), "sculpted_examples", path,
                    {"asset": result.asset, "examples": result.examples, "sculpts": sorted(result.read)},
                    settings={"scale": result.scale, "up_axis": result.up_axis})
    with _forced(force):
        usdwrite.export_all([(path, layer)], [result.asset, result.examples], other_inputs=result.read)
    return path


# --- mirror: one side's correctives groups -> the other side's, in CORRECTIVES ------------------

def mirror(asset: str, correctives: str, settings: MirrorSettings, *, strict: bool = False,
           meshes: Sequence[str] = ()) -> MirrorResult:
    """The other side's correctives groups, made from CORRECTIVES's groups (``settings.group``,
    or every group whose drivers all have partners) by reflecting the rig's bind space
    (``psdbake/mirroring/groups.py``); refuses a rig or mesh that is not mirror-symmetric. Warns (or,
    strict, refuses) when ASSET's rig is not the one CORRECTIVES were fitted on."""
    from .mirroring.groups import mirror_groups

    started = _time.perf_counter()
    scene = open_asset(asset, others=(correctives,))
    check_fitted_on(asset, scene, correctives, strict=strict)
    groups = read_correctives(asset, correctives)
    if meshes:
        chosen = set(resolve_meshes(asset, sorted(groups), meshes))
        groups = {m: g for m, g in groups.items() if m in chosen}
    infos = {m.path: m for m in scene.skinned_meshes() if m.path in groups}
    binds = {path: read_bind_space(scene, info) for path, info in infos.items()}
    made, skipped = mirror_groups(asset, correctives, groups, binds, infos, settings)
    return MirrorResult(asset, correctives, settings, tuple(made), tuple(skipped), _time.perf_counter() - started,
                        rig=provenance.rig_record(scene))


def mirror_reads(asset: str, correctives: str, output: str) -> list[str]:
    """Every file ``mirror`` reads that its output may not be: CORRECTIVES itself may be the
    output (it is then updated in place, as ``fit --group`` updates its output)."""
    reads = files_read([asset, correctives])
    if os.path.realpath(output) != os.path.realpath(correctives):
        return reads
    return [f for f in reads if os.path.realpath(f) != os.path.realpath(correctives)]


def write_mirror(result: MirrorResult, path: str, *, force: bool = False, replace_sculpted: bool = False
                 ) -> GroupChanges:
    """Export CORRECTIVES's groups with the mirrored ones written in (each replacing its
    namesake) atomically to path; returns what happened to the groups. When path is
    CORRECTIVES itself, it is re-read and replaced under the update lock, so concurrent group
    updates all land.

    A group fitted from sculpts is not replaced by a mirrored one unless ``replace_sculpted``:
    one named group (``--group``) is refused (exit 6); in whole-layer mode it is left alone and
    reported (``GroupChanges.protected``)."""
    inputs = mirror_reads(result.asset, result.correctives, path)
    in_place = os.path.realpath(path) == os.path.realpath(result.correctives)
    doc = f"psdbake {__version__} mirror: rest-space correctives (inverse PSD), groups mirrored"
    with _forced(force):
        atomic.check_output(path, inputs, kind=outputs.CORRECTIVES)
        with updating(path) if in_place else contextlib.nullcontext():
            base = path if in_place else result.correctives
            before = read_correctives(result.asset, base)
            records = provenance.plain(provenance.read_stamp(base).get("groups", {}))
            sources = {g.group: g.source for g in result.groups}
            protected = sorted(g for g in sources if g in names_of(before) and is_sculpted(records.get(g))
                               and not replace_sculpted)
            if protected and result.settings.group:
                raise OutputError(
                    f"{path}: group {protected[0]!r} there was fitted from sculpts ({origin_text(records.get(protected[0]))}): "
                    "mirror does not replace it unless asked (--replace-sculpted), or name the mirror otherwise (--as)")
            written: Groups = {}
            for g in result.groups:
                if g.group not in protected:
                    written.setdefault(g.mesh, {})[g.group] = (g.driver_data, list(g.shapes))
            groups = merged_groups(before, written)
            if not in_place:
                _check_not_dropping(path, result.asset, groups, "mirror")
            entries = {name: {"origin": "mirror", "source": sources[name], "command": outputs.command_line(path),
                              "plane": result.settings.plane, "joints": list(result.settings.joints)}
                       for name in names_of(written)}
            layer = groups_layer(result.asset, groups, doc)
            stamped(layer, "correctives", path, {"asset": result.asset}, rig=result.rig, command=False,
                    groups={**{g: r for g, r in records.items() if g in names_of(groups)}, **entries})
            usdwrite.export_all([(path, layer)], inputs)
    return dataclasses.replace(changes_between(before, groups, written, records, routine="mirrored from"),
                               protected=tuple(protected))


# --- groups: list, remove, rename the groups of a CORRECTIVES layer -------------------------------

def recorded_asset(correctives: str) -> str | None:
    """The asset a CORRECTIVES layer records it was fitted on (its provenance), as a path from
    here, or None."""
    recorded = provenance.plain(provenance.read_stamp(correctives).get("inputs", {}))
    asset = recorded.get("asset") if isinstance(recorded, dict) else None
    if isinstance(asset, list):  # a stack records each role's layers as a list, the strongest last
        asset = asset[-1] if asset else None
    rel = asset.get("path") if isinstance(asset, dict) else None
    return os.path.normpath(os.path.join(os.path.dirname(correctives), rel)) if isinstance(rel, str) else None


def list_groups(correctives: str) -> list[dict[str, Any]]:
    """Every group of a CORRECTIVES layer, per mesh (``psdbake groups``): drivers, RBF settings,
    channels, examples, gates, and where it came from (its provenance record)."""
    from .usd.describe import describe as describe_file

    open_layer(correctives)
    if provenance.existing_kind(correctives) != "correctives" and not describe_file(correctives)["correctives"]:
        raise InputError(f"{correctives}: not a CORRECTIVES layer (it holds no psd: correctives groups)")
    records = provenance.plain(provenance.read_stamp(correctives).get("groups", {}))
    out = []
    for c in describe_file(correctives)["correctives"]:
        record = records.get(c["group"]) if isinstance(records, dict) else None
        out.append({**c, "origin": origin_text(record), "record": record or {}})
    return sorted(out, key=lambda c: (c["group"], c["mesh"]))


def edit_groups(correctives: str, *, remove: Sequence[str] = (), rename: Mapping[str, str] | None = None,
                output: str | None = None, asset: str | None = None, force: bool = False) -> GroupChanges:
    """CORRECTIVES without the groups in ``remove`` and with those in ``rename`` (old -> new)
    renamed, written to output (default: in place, re-read and replaced under the update lock).
    ASSET defaults to the one the layer records it was fitted on. Renaming changes the groups'
    channel names, so WEIGHTS evaluated before must be evaluated again."""
    if asset is None:
        asset = recorded_asset(correctives)
        if asset is None:
            raise InputError(f"{correctives}: records no asset it was fitted on (older psdbake): give --asset")
        if not os.path.isfile(asset):
            raise InputError(f"{correctives}: records it was fitted on {asset}, which is not there (the layer was moved "
                             "without it?): give --asset")
    output = output or correctives
    in_place = os.path.realpath(output) == os.path.realpath(correctives)
    inputs = [f for f in files_read([asset, correctives]) if not in_place or os.path.realpath(f) != os.path.realpath(correctives)]
    with _forced(force):
        atomic.check_output(output, inputs, kind=outputs.CORRECTIVES)
        with updating(output) if in_place else contextlib.nullcontext():
            before = read_correctives(asset, correctives)
            records = provenance.plain(provenance.read_stamp(correctives).get("groups", {}))
            groups = without_groups(before, list(remove), correctives)
            for old, new in (rename or {}).items():
                groups = renamed_group(groups, old, new, correctives)
                if old in records:
                    records[new] = {**records.pop(old), "renamed_from": old}
            if not in_place:
                _check_not_dropping(output, asset, groups, "groups edit")
            layer = groups_layer(asset, groups, f"psdbake {__version__} groups: rest-space correctives (inverse PSD)")
            stamped(layer, "correctives", output, {"asset": asset}, rig=provenance.plain(
                provenance.read_stamp(correctives).get("rig", {})), command=False,
                groups={g: r for g, r in records.items() if g in names_of(groups)})
            usdwrite.export_all([(output, layer)], inputs)
    rename = dict(rename or {})
    return GroupChanges(removed=tuple(sorted(remove)), renamed=tuple(f"{a} -> {b}" for a, b in sorted(rename.items())),
                        kept=tuple(sorted(names_of(groups) - set(rename.values()))),
                        origins={g: origin_text(r) for g, r in records.items()})


# --- views and descriptions --------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class StackResult:
    """What ``write_stack`` wrote: the layers in the order composed, weakest first, with roles."""

    output: str
    layers: tuple[tuple[str, str], ...]  # (path, role), weakest first
    reordered: bool  # the layers were given in another order than composed
    warnings: tuple[str, ...] = ()


def plan_stack(layers: Sequence[str], *, strict: bool = False) -> StackResult:
    """The layers in the order a viewer must compose them, weakest first: ASSET < CORRECTIVES <
    ANIM < WEIGHTS < points cache, by each layer's role (its psdbake kind; the asset is the
    layer that defines a SkelRoot; any other layer of the user's is an ANIM), whatever the order
    given. Layers of one role keep the order given, strongest first, as in a USD subLayers list.
    Refuses contradictions: two CORRECTIVES layers on one mesh, two WEIGHTS layers on one
    animation. Warns (strict: refuses, exit 3) when CORRECTIVES were fitted on another rig than
    the asset's, or WEIGHTS were evaluated from other CORRECTIVES than the ones stacked."""
    notes: list[str] = []
    unique = list(dict.fromkeys(layers))
    roles = {path: provenance.layer_role(path) for path in unique}
    rank = {r: i for i, r in enumerate(provenance.STACK_ROLES)}
    position = {path: i for i, path in enumerate(unique)}
    ordered = sorted(unique, key=lambda p: (rank[roles[p]], -position[p]))
    by_role: dict[str, list[str]] = {}
    for path in ordered:
        by_role.setdefault(roles[path], []).append(path)
    stamps = {p: provenance.read_stamp(p) for p in unique if roles[p] != "asset" and roles[p] != "anim"}
    claimed: dict[str, str] = {}
    for path in by_role.get("correctives", []):
        for mesh in psd_prims(open_layer(path)):
            if mesh in claimed:
                raise InputError(f"{path}: CORRECTIVES for <{mesh}>, as {claimed[mesh]} is: the stronger layer's "
                                 "blend shapes would hide the other's; merge them into one layer (fit --group)")
            claimed[mesh] = path
    weights_of: dict[str, str] = {}
    for path in by_role.get("weights", []):
        anim = provenance.plain(stamps[path].get("inputs", {})).get("anim", {}).get("sha256", path)
        if anim in weights_of:
            raise InputError(f"{path}: WEIGHTS for the same animation as {weights_of[anim]}: the stronger layer's "
                             "weights would hide the other's; stack one of them")
        weights_of[anim] = path
    for role in ("correctives", "anim", "asset"):  # WEIGHTS made from other layers show the wrong weights
        notes += _weights_made_from(stamps, by_role, role, strict=strict)
    assets = by_role.get("asset", [])
    if assets:
        scene = open_asset(assets[-1])
        skinned = {m.path for m in scene.skinned_meshes()}
        for path in by_role.get("correctives", []):
            meshes = sorted(psd_prims(open_layer(path)))
            if meshes and not skinned.intersection(meshes):
                raise InputError(f"{path}: CORRECTIVES for {', '.join(f'<{m}>' for m in meshes)}, which {assets[-1]} "
                                 "does not skin: the stack would show no correction (fitted on another asset?)")
            notes += check_fitted_on(assets[-1], scene, path, strict=strict)
    return StackResult("", tuple((p, roles[p]) for p in ordered), ordered != list(reversed(unique)) and
                       ordered != unique, tuple(notes))


def _weights_made_from(stamps: Mapping[str, dict], by_role: Mapping[str, list[str]], role: str, *,
                       strict: bool) -> list[str]:
    """Warn (strict: refuse, exit 3) when a WEIGHTS layer records it was evaluated from another
    ``role`` layer (CORRECTIVES, ANIM or ASSET) than any stacked: its weights belong to other
    channels, frames or another rig, and the stack would show them without a word."""
    stacked = {provenance.file_sha256(p) for p in by_role.get(role, [])}
    notes = []
    for path in by_role.get("weights", []) if stacked else ():
        used = provenance.plain(stamps[path].get("inputs", {})).get(role, {})
        if not (isinstance(used, dict) and used.get("sha256") and used["sha256"] not in stacked):
            continue
        if role == "correctives":
            msg = (f"{path}: evaluated from {used.get('path', 'other correctives')} (other bytes than "
                   f"{', '.join(by_role[role])}): re-run psdbake eval with the stacked CORRECTIVES")
        else:
            msg = (f"{path}: evaluated over {used.get('path', 'another ' + role)} (other bytes than the stacked "
                   f"{role.upper()} {', '.join(by_role[role])}): re-run psdbake eval with the stacked layers")
        if strict:
            raise InputError(f"{msg} (--strict)")
        notes.append(msg)
        warnings.warn(msg, PsdWarning, stacklevel=3)
    return notes


def write_stack(path: str, layers: Sequence[str], *, strict: bool = False, force: bool = False) -> StackResult:
    """A viewable stack of layers, given in any order (``plan_stack``): one layer sublayering
    them, paths relative to it, written atomically."""
    plan = dataclasses.replace(plan_stack(layers, strict=strict), output=path)
    ordered = [p for p, _ in plan.layers]
    compose(list(reversed(ordered)))  # refuse what no viewer could compose (cycles, unreadable sublayers)
    layer = stamped(usdwrite.stack_layer(path, ordered), "stack", path,
                    {role: [p for p, r in plan.layers if r == role] for role in provenance.STACK_ROLES
                     if any(r == role for _, r in plan.layers)})
    with _forced(force):
        usdwrite.export_atomic(layer, path, files_read(ordered))
    return plan


def describe(path: PathArg, asset: PathArg | None = None) -> dict:
    """What a USD file holds (``psdbake inspect``): JSON-ready, sorted. With the asset (given, or
    the one the file records it was made from), the example poses are spelled out: per time code,
    the joints turned from bind and by how many degrees."""
    from .usd.describe import spelled_poses

    path = as_path(path, "path")
    asset = as_path(asset, "asset") if asset is not None else None

    info = describe_file(path)
    stamp = provenance.read_stamp(path)
    info["kind"] = provenance.existing_kind(path)
    info["command"] = stamp.get("command") if isinstance(stamp.get("command"), str) else None
    if info["kind"] == "stack":  # each sublayer's role, as stack recorded it
        recorded = provenance.plain(stamp.get("inputs", {}))
        roles = {os.path.normpath(entry.get("path", "")): role for role, entries in
                 (recorded.items() if isinstance(recorded, dict) else ())
                 for entry in (entries if isinstance(entries, list) else [entries]) if isinstance(entry, dict)}
        info["layers"] = [{"path": p, "role": roles.get(os.path.normpath(p))} for p in info["sublayers"]]
    asset = asset or recorded_asset(path)
    times = sorted({t for e in info["examples"] for t in e["time_codes"]})
    if asset and os.path.isfile(asset) and times and os.path.realpath(asset) != os.path.realpath(path):
        info["asset"] = asset
        info["poses"] = spelled_poses(Scene([path, asset], label=path), times)
        if not info["poses"]:
            meshes = ", ".join(sorted(f"<{e['mesh']}>" for e in info["examples"]))
            info["warnings"] = [*info.get("warnings", []), f"{path}: {asset} skins none of the meshes these examples "
                                f"pose ({meshes}): no pose spelled out (another asset?)"]
    return info
