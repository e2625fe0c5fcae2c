"""The pipeline in plain sight.

fit:   read USD -> pose space -> black-box skinning -> inverse (Powell) -> RBF -> CORRECTIVES
eval:  CORRECTIVES + ANIM -> pose space -> RBF weights -> WEIGHTS (+ points cache)
pose:  ASSET + POSES -> plain UsdSkel skinning per time code -> EXAMPLES to sculpt on

Every function returns data (frozen dataclasses or in-memory layers); nothing here
prints. ``write_*`` export layers atomically.

The machinery of fit, mirror and the OBJ round trip (SciPy's interpolation and spatial
modules among it) is imported by the functions that run it, so ``eval`` loads only what it
uses (issue 16: every farm chunk pays its start-up).
"""

from __future__ import annotations

import os
import time as _time
import warnings
from collections.abc import Sequence

from . import __version__, atomic
from .deformers import deformer_files, load_deformers
from .errors import InputError, PsdWarning, where
from .evaluation import animation_weights, correctives_by_animation, posed_points
from .frames import frames_of
from .groups import correctives_layer, read_correctives, updated_layer
from .results import FitResult, GltfResult, MirrorResult, PoseResult, Progress, SculptsResult, WeightsResult
from .settings import FitSettings, MirrorSettings, SettingError
from .usd import write as usdwrite
from .usd.author import Layer
from .usd.bindspace import read_bind_space
from .usd.compose import compose
from .usd.describe import describe as describe_file
from .usd.gltf_source import read_gltf_source
from .usd.read import Scene, animation_components, hidden_from_usdskel, open_layers, why_hidden
from .usd.validate import require_finite_time_samples, require_psd_prims_skinned, validate_animation, validate_skinning
from .usd.valuetypes import Checked

__all__ = [  # noqa: RUF022 - in pipeline order; the public surface is psdbake/__init__.py
    "fit", "write_correctives", "evaluate", "weights_layer", "write_weights", "points_cache_layer",
    "write_points_cache", "pose", "write_pose", "write_stack", "describe", "open_asset", "files_read",
    "correctives_layer", "export_gltf",
    "mirror", "mirror_reads", "write_mirror",
]










# --- fit: read USD -> pose space -> black-box inverse (Powell) -> RBF -> CORRECTIVES -----------

def open_asset(asset: str, notes: list[str] | None = None) -> Scene:
    """The asset on its own, with every skinned mesh's influences and skeleton validated."""
    scene = Scene([asset])
    scene.require_skinned()
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


def fit(
    asset: str,
    example_files: Sequence[str],
    settings: FitSettings = FitSettings(),  # noqa: B008 - frozen, so one shared default is safe
    *,
    jobs: int | None = None,
    progress: Progress | None = None,
) -> FitResult:
    """Fit rest-space correctives and their RBF drivers from sculpted examples.

    jobs: worker processes for the per-example inverses (None: 1, see ``solve.auto_jobs``).
    The output does not depend on it.
    """
    from .correctives import fit_regions, plan_mesh, plan_systems
    from .examples import gather_examples
    from .solve import clear_caches, share_scene, solve_all

    started = _time.perf_counter()
    if not example_files:
        raise InputError("fit needs at least one EXAMPLES file")
    notes: list[str] = []
    load_deformers(settings.deformers)  # fail fast on a bad spec; each solve loads its own chain
    asset_scene = open_asset(asset, notes)
    infos = asset_scene.skinned_meshes()
    meshes = _meshes_to_fit(asset, [m.path for m in infos], settings.meshes)
    skipped: list[str] = []
    layout: list[str] = []  # why a mesh's correctives are one global group, when they are
    try:
        share_scene(asset_scene)  # the solves' rest points and shading come from this stage, not a second one
        per_mesh, tasks = gather_examples(asset, asset_scene, infos, meshes, example_files, settings)  # checked
        plans, systems = {}, {}
        for info in [i for i in infos if i.path in per_mesh]:
            regions, unused, why = plan_mesh(asset, info, per_mesh[info.path], settings)  # who drives what
            plans[info.path] = regions
            systems[info.path] = plan_systems(asset, info, per_mesh[info.path], regions, settings, notes)
            skipped += [f"{per_mesh[info.path][i].label} <{info.path}>" for i in unused]
            if why:
                layout.append(f"{where(asset, info.path)}: one global correctives group 'main': {why} (local, "
                              "additive correctives need every joint an example moves sculpted on its own too)")
        used = {(p, per_mesh[p][i].source, per_mesh[p][i].time) for p, regions in plans.items() for r in regions
                for i in r.examples}
        wanted = [t for t in tasks if (t.mesh, t.source, t.time) in used]
        solved = dict(zip([(t.mesh, t.source, t.time) for t in wanted], solve_all(wanted, jobs, progress), strict=True))
        fits = []
        for info in [i for i in infos if i.path in plans]:  # the RBFs, each mesh's regions in turn
            examples = per_mesh[info.path]
            mine = {i: solved[(info.path, e.source, e.time)] for i, e in enumerate(examples)
                    if (info.path, e.source, e.time) in solved}
            fits += fit_regions(asset, asset_scene, info, examples, mine, plans[info.path], settings, notes,
                                systems[info.path])
            _note_normals(asset, info.path, notes)
        # for write_correctives: the asset's layers and the EXAMPLES files still open, so no input is parsed twice
        held = {layer.identifier: layer for layer in [*asset_scene.file_layers(), *open_layers(example_files)]}
    finally:
        clear_caches()  # the example stages die with the fit
    return FitResult(asset=asset, example_files=tuple(example_files), settings=settings, meshes=tuple(fits),
                     warnings=tuple(notes), seconds=_time.perf_counter() - started, skipped=tuple(skipped),
                     layout=tuple(layout), input_layers=tuple(held[k] for k in sorted(held)))


def _meshes_to_fit(asset: str, skinned: list[str], wanted: Sequence[str]) -> list[str]:
    for mesh in wanted:
        if mesh not in skinned:
            raise SettingError("meshes", mesh, "is not a skinned mesh of the asset", location=asset)
    return [m for m in skinned if not wanted or m in wanted]


def _note_normals(asset: str, mesh: str, notes: list[str]) -> None:
    """Warn when a mesh authors shading normals psdbake cannot give normalOffsets to."""
    from .solve import cached_shading

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


def write_correctives(result: FitResult, path: str, *, update: bool = False,
                      side_files: Sequence[tuple[str, str]] = ()) -> str:
    """Export CORRECTIVES atomically; inputs are never overwritten.

    update: when path exists, keep its other groups (``fit --group``); the read, merge and
    rename happen under a lock, so concurrent group fits into one layer all land.
    side_files: (path, text) written in the same commit (``fit --report``): both land or neither.
    """
    inputs = files_read([result.asset, *result.example_files], result.settings.deformers)
    if not update:
        usdwrite.export_all([(path, correctives_layer(result)), *side_files], inputs)
        return path
    atomic.check_output(path, inputs, tuple(usdwrite.FORMATS))
    with atomic.updating(path):
        base = path if os.path.exists(path) else None
        usdwrite.export_all([(path, correctives_layer(result, update=base)), *side_files], inputs)
        return path


# --- eval: CORRECTIVES + ANIM -> pose space -> RBF weights -> WEIGHTS (+ points cache) ---------

def evaluate(
    asset: str,
    correctives: str,
    anim: str,
    *,
    frames: tuple[float, float] | None = None,
    progress: Progress | None = None,
) -> WeightsResult:
    """RBF weights of every corrective at every frame of ANIM."""
    started = _time.perf_counter()
    open_asset(asset)
    scene = Scene([anim, correctives, asset], label=correctives, checked=Checked.NO_SHAPE_VALUES)  # weights read no offsets
    scene.require_skinned()
    require_psd_prims_skinned(scene, correctives, asset)
    per_anim = correctives_by_animation(scene, Scene([anim, asset], label=anim), correctives, anim)
    if not per_anim:
        raise InputError(f"{correctives}: no psd: driver data on any skinned mesh of {asset}")
    planned = {a: frames_of(scene, per_anim[a][0][0].path, frames, label=anim) for a in sorted(per_anim)}
    total, done = sum(len(planned[a]) * len(per_anim[a]) for a in planned), 0

    def tick(mesh: str) -> None:
        nonlocal done
        done += 1
        if progress:
            progress(done, total, mesh)

    results = tuple(animation_weights(scene, a, per_anim[a], planned[a], correctives, anim, tick) for a in sorted(per_anim))
    fps = scene.stage.GetTimeCodesPerSecond()
    return WeightsResult(asset, correctives, anim, results, fps, _time.perf_counter() - started)


def weights_layer(result: WeightsResult) -> Layer:
    """WEIGHTS as an in-memory layer."""
    return usdwrite.weights_layer(
        f"psdbake {__version__} eval: corrective blend-shape weights",
        [(a.animation, a.channels, a.times, a.weights) for a in result.animations],
        result.fps,
        usdwrite.asset_metadata(result.asset),
    )


def write_weights(result: WeightsResult, path: str, *, points_cache: tuple[str, Layer] | None = None,
                  deformers: Sequence[str] = ()) -> str:
    """Export WEIGHTS (and, given as (path, layer), the points cache in the same commit:
    both land or neither)."""
    outputs = [(path, weights_layer(result)), *([points_cache] if points_cache else [])]
    usdwrite.export_all(outputs, files_read([result.asset, result.correctives, result.anim], deformers))
    return path


def points_cache_layer(result: WeightsResult, deformers: Sequence[str] = (), *, progress: Progress | None = None
                       ) -> Layer:
    """Final posed points per frame (correctives, existing shapes, skinning, deformers),
    as a layer that needs no UsdSkel: the SkelRoots become Xforms, like BakeSkinning.
    The asset's authored shading normals are blocked (they are rest normals), so renderers
    derive normals from the cached points.

    The points come from UsdSkel evaluating the stack ASSET + CORRECTIVES + ANIM + WEIGHTS
    (the correctives are ordinary blend shapes there), then the deformer chain.
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
    return usdwrite.points_layer(
        f"psdbake {__version__} eval: points cache (no UsdSkel needed)",
        scene.skel_roots, posed_points(scene, scene, meshes, times, chain, progress), times, result.fps,
        usdwrite.asset_metadata(result.asset),
        blocked=[(m.path, name) for m in meshes for name in ("normals", "primvars:normals")
                 if scene.prim(m.path).GetAttribute(name).HasAuthoredValue()],
    )


def write_points_cache(result: WeightsResult, path: str, deformers: Sequence[str] = (), *,
                       progress: Progress | None = None) -> str:
    return usdwrite.export_atomic(
        points_cache_layer(result, deformers, progress=progress), path,
        files_read([result.asset, result.correctives, result.anim], deformers),
    )


# --- export-gltf: ASSET + CORRECTIVES + ANIM + eval's weights -> one .glb for game engines ---

def export_gltf(asset: str, correctives: str, anim: str, output: str, *, frames: tuple[float, float] | None = None,
                progress: Progress | None = None) -> GltfResult:
    """Write the shot as a skinned glTF 2.0 binary: meshes, skins, joint animation (one
    key per time code), every BlendShape channel of the composed stack as a morph target
    and eval's weights animating them. Skinned in glTF (linear blend), it gives
    ``UsdSkel.BakeSkinning``'s world-space points of ASSET + CORRECTIVES + ANIM + WEIGHTS,
    in glTF's Y-up meters."""
    from . import gltf  # pygltflib loads only for this command

    inputs = files_read([asset, correctives, anim])
    atomic.check_output(output, inputs, (".glb",))  # before the work, so a bad output fails at once
    weights = evaluate(asset, correctives, anim, frames=frames, progress=progress)
    scene = Scene([anim, correctives, asset], label=correctives)
    source = read_gltf_source(scene, asset, {a.animation: (a.channels, a.times, a.weights) for a in weights.animations})
    for msg in gltf.differences(source, asset):
        warnings.warn(msg, PsdWarning, stacklevel=2)
    name = os.path.splitext(os.path.basename(anim))[0] or "animation"
    glb = gltf.build_glb(source, name, f"psdbake {__version__} export-gltf")
    gltf.write_glb(glb.data, output, inputs)
    return GltfResult(output, weights, tuple(m.path for m in source.meshes), glb.morph_targets, glb.sparse_targets,
                      max((len(s.times) for s in source.skeletons), default=0), len(glb.data))


# --- pose: ASSET + POSES -> plain UsdSkel skinning per time code -> EXAMPLES to sculpt on -------

def pose(asset: str, poses: str, deformers: Sequence[str] = (), *, progress: Progress | None = None) -> PoseResult:
    """EXAMPLES to sculpt on: skinned points per time code of POSES, with the pose itself."""
    chain = load_deformers(deformers)
    asset_scene = open_asset(asset)
    scene = Scene([poses, asset], label=poses)
    meshes = scene.skinned_meshes()
    for info in meshes:
        validate_animation(scene, info.path)
        if (anim_path := scene.animation_prim(info.path)) is not None:
            require_finite_time_samples(scene, anim_path, poses)
    anims = sorted({a for m in meshes if (a := scene.animation_prim(m.path))})
    if not anims:
        raise InputError(f"{poses}: no SkelAnimation is bound to the skeleton (skel:animationSource)")
    times = sorted({t for m in meshes for t in scene.animation_times(m.path)})
    if not times:
        raise InputError(f"{where(poses, anims[0])}: the animation has no time samples: nothing to pose")
    animations, seen = [], set()
    for info in meshes:
        if scene.animation_prim(info.path) is None or info.skeleton in seen:
            continue
        seen.add(info.skeleton)
        path, joints, channels, anim_samples = animation_components(scene, info.path, times)
        animations.append((info.skeleton, path, joints, channels, anim_samples))
    layer = usdwrite.examples_layer(
        f"psdbake {__version__} pose: skinned examples to sculpt on", animations,
        posed_points(asset_scene, scene, meshes, times, chain, progress), times, scene.stage.GetTimeCodesPerSecond(),
        usdwrite.asset_metadata(asset),
    )
    return PoseResult(asset, poses, tuple(times), tuple(m.path for m in meshes), layer, tuple(deformers))


def write_pose(result: PoseResult, path: str, obj_dir: str | None = None) -> str:
    """Export EXAMPLES atomically; with obj_dir, also one OBJ per skinned mesh and time code
    plus ``manifest.json`` there, all in the same commit (``objloop``)."""
    from . import objloop

    inputs = files_read([result.asset, result.poses], result.deformers)
    if obj_dir is None:
        return usdwrite.export_atomic(result.layer, path, inputs)
    objloop.write_pose_objs(result, path, obj_dir, inputs)
    return path


# --- sculpts: the OBJs of pose --obj-dir, sculpted -> EXAMPLES for fit --------------------------

def check_obj_dir(obj_dir: str, inputs: Sequence[str] = ()) -> None:
    """Refuse an OBJ folder pose cannot fill (before the work; exit 6)."""
    from .obj.folder import check_obj_dir as check_obj_folder

    check_obj_folder(obj_dir, inputs)


def obj_files(result: PoseResult) -> list[str]:
    """The OBJ file names ``write_pose(..., obj_dir)`` writes for result."""
    from . import objloop

    return objloop.obj_files(result)


def sculpts(asset: str, examples: str, obj_dir: str, *, scale: float | None = None,
            up_axis: str | None = None) -> SculptsResult:
    """Read back the sculpted OBJs of obj_dir (listed in its manifest) over EXAMPLES, the layer
    ``pose`` wrote with them: each file checked (vertex count, faces, finite, near its posed
    mesh), ``scale`` and ``up_axis`` applied first."""
    from . import objloop

    return objloop.read_sculpts(asset, examples, obj_dir, scale=scale, up_axis=up_axis)


def write_sculpts(result: SculptsResult, path: str) -> str:
    """Export SCULPTED_EXAMPLES (EXAMPLES with the sculpted points) atomically; no input, OBJ
    or manifest may be the output."""
    from . import objloop

    usdwrite.export_all([(path, objloop.sculpts_layer(result))], [result.asset, result.examples],
                        other_inputs=result.read)
    return path


# --- mirror: one side's correctives groups -> the other side's, in CORRECTIVES ------------------

def mirror(asset: str, correctives: str, settings: MirrorSettings) -> MirrorResult:
    """The other side's correctives groups, made from CORRECTIVES's groups (``settings.group``,
    or every group whose drivers all have partners) by reflecting the rig's bind space
    (``psdbake/mirroring.py``); refuses a rig or mesh that is not mirror-symmetric."""
    from .mirroring import mirror_groups

    started = _time.perf_counter()
    scene = open_asset(asset)
    groups = read_correctives(asset, correctives)
    meshes = {m.path: m for m in scene.skinned_meshes() if m.path in groups}
    binds = {path: read_bind_space(scene, info) for path, info in meshes.items()}
    made, skipped = mirror_groups(asset, correctives, groups, binds, meshes, settings)
    return MirrorResult(asset, correctives, settings, tuple(made), tuple(skipped), _time.perf_counter() - started)


def mirror_reads(asset: str, correctives: str, output: str) -> list[str]:
    """Every file ``mirror`` reads that its output may not be: CORRECTIVES itself may be the
    output (it is then updated in place, as ``fit --group`` updates its output)."""
    reads = files_read([asset, correctives])
    if os.path.realpath(output) != os.path.realpath(correctives):
        return reads
    return [f for f in reads if os.path.realpath(f) != os.path.realpath(correctives)]


def write_mirror(result: MirrorResult, path: str) -> str:
    """Export CORRECTIVES's groups with the mirrored ones written in (each replacing its
    namesake) atomically to path. When path is CORRECTIVES itself, it is re-read and
    replaced under the update lock, so concurrent group updates all land."""
    inputs = mirror_reads(result.asset, result.correctives, path)
    new: dict = {}
    for g in result.groups:
        new.setdefault(g.mesh, {})[g.group] = (g.driver_data, list(g.shapes))
    doc = f"psdbake {__version__} mirror: rest-space correctives (inverse PSD), groups mirrored"
    if os.path.realpath(path) != os.path.realpath(result.correctives):
        usdwrite.export_all([(path, updated_layer(result.asset, result.correctives, new, doc))], inputs)
        return path
    atomic.check_output(path, inputs, tuple(usdwrite.FORMATS))
    with atomic.updating(path):
        usdwrite.export_all([(path, updated_layer(result.asset, path, new, doc))], inputs)
    return path


# --- views and descriptions --------------------------------------------------------------

def write_stack(path: str, layers: Sequence[str]) -> str:
    """A viewable stack: sublayers ``layers`` (weakest first: ASSET, CORRECTIVES, ANIM, WEIGHTS)."""
    compose(list(reversed(layers)))  # refuse what no viewer could compose (cycles, unreadable sublayers)
    return usdwrite.export_atomic(usdwrite.stack_layer(path, layers), path, files_read(layers))


def describe(path: str) -> dict:
    """What a USD file holds (``psdbake inspect``): JSON-ready, sorted."""
    return describe_file(path)
