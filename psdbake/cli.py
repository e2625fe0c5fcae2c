"""The ``psdbake`` command: a thin shell over ``psdbake.api``.

It parses options, calls one library function per command, renders a summary and
maps errors to exit codes in one place (``main``). No numerics and no USD here.

Start-up: this module imports click and psdbake's light modules only (``names``,
``tolerances``, ``errors``, ``console``); each command imports the library it calls inside
its body, and USD's diagnostics are trapped when a command runs (``_Command.invoke``). So
``psdbake --help``, option parsing and usage errors load no numpy, SciPy or USD
(tests/test_startup.py; ``python -m benchmarks.startup`` measures it).

Exit codes: 0 success, 1 unexpected failure, 2 usage error, 3 bad input,
4 ill-posed fit, 5 deformer failure, 6 output not writable, 7 ``--strict`` and some
vertices missed tolerance, 130 interrupted. ``batch`` exits with its first failed
job's code (1 if that job died otherwise).
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import signal
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import click

from . import __version__, console, outputs
from . import tolerances as tol
from .console import Ui
from .errors import PsdError, SettingError, StrictError, UsdDataError
from .names import DEFAULT_GROUP, KERNEL_NAMES, POSE_SPACE_NAMES

if TYPE_CHECKING:
    from .settings import FitSettings

EXIT_INTERNAL, EXIT_USAGE, EXIT_INTERRUPTED = 1, 2, 130


_COMMON = [
    click.option("-q", "--quiet", is_flag=True,
                 help="Print no summary on stdout (--json still prints its JSON); warnings and errors still go to stderr."),
    click.option("-v", "--verbose", count=True, help="More detail in the summary."),
    click.option("--json", "as_json", is_flag=True, help="Print a machine-readable summary on stdout."),
]


deformer_option = click.option(
    "--deformer", "deformers", multiple=True, metavar="MODULE:FACTORY",
    help="A studio deformer applied after skinning (repeatable, chained in order): "
         "package.module:factory or file.py:factory. This runs your code.",
)

force_option = click.option(
    "--force", is_flag=True,
    help="Replace an existing output even when it is not this command's own earlier output (an asset, a sculpted "
         "EXAMPLES layer, another kind of layer) or is read-only. Inputs, and the OBJs in an --obj-dir, are never "
         "replaced.",
)

strict_provenance_option = click.option(
    "--strict", is_flag=True,
    help="Refuse (exit 3) when the asset's rig is not the one the correctives were fitted on (another skinning "
         "method, weights, rest points or skeleton), instead of warning.",
)

_FRAMES = [
    click.option("--frames", metavar="START:END",
                 help="Whole frames START..END (inclusive), within the animation's authored samples. "
                      "Default: the animation's authored samples."),
    click.option("--hold", is_flag=True,
                 help="Accept --frames outside the authored samples, where the animation holds its first or last "
                      "pose (warned); without it such a range is refused."),
]


_RBF_OPTIONS = [
    click.option("--driver", "drivers", multiple=True, metavar="JOINT",
                 help="Driver joint (path or unique name; repeatable). Default: every joint rotated in any example."),
    click.option("--kernel", type=click.Choice(sorted(KERNEL_NAMES)), default="gaussian", show_default=True),
    click.option("--sigma", type=float, default=None,
                 help="Kernel width in radians. Default: mean distance between example poses."),
    click.option("--degree", type=int, default=None,
                 help="Polynomial degree (-1: none). Default: the kernel's minimum (none for gaussian)."),
    click.option("--smoothing", type=float, default=0.0, show_default=True, help="RBF smoothing (0 interpolates exactly)."),
    click.option("--no-rest-example", is_flag=True, help="Do not add the bind pose as an implicit zero example."),
    click.option("--pose-space", type=click.Choice(list(POSE_SPACE_NAMES)),
                 default="rotationVector", show_default=True,
                 help="Pose coordinates of each driver joint (docs: explanation/pose-space-and-rbf.md)."),
    click.option("--twist-axis", type=(float, float, float), default=None, metavar="X Y Z",
                 help="swingTwist: the twist axis in each driver's bind frame, e.g. 1 0 0 for a bone along x."),
    click.option("--clamp-weights", is_flag=True, help="Clamp weights to [0, 1] at eval time (stored in psd:)."),
    click.option("--normalize-weights", is_flag=True, help="Scale weights so they sum to at most 1 (stored in psd:)."),
]


def _stacked(options: Sequence[Callable]) -> Callable[[Callable], Callable]:
    """One decorator applying several click options, in the order listed."""

    def apply(fn: Callable) -> Callable:
        for option in reversed(options):
            fn = option(fn)
        return fn

    return apply


_RBF_NAMES = ("drivers", "kernel", "sigma", "degree", "smoothing", "no_rest_example", "pose_space", "twist_axis",
              "clamp_weights", "normalize_weights")


def rbf_options(fn: Callable) -> Callable:
    """The pose-space and RBF options, shared by ``fit`` and ``compare`` (which fits too), given
    to the command as one ``rbf`` dict of ``FitSettings`` fields (``_settings``)."""

    @functools.wraps(fn)
    def command(*args, **kwargs):
        rbf = {name: kwargs.pop(name) for name in _RBF_NAMES}
        return fn(*args, rbf=rbf, **kwargs)

    return _stacked(_RBF_OPTIONS)(command)


#: --frames and --hold, shared by every command that evaluates a shot.
frame_options = _stacked(_FRAMES)
_common = _stacked(_COMMON)


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="psdbake")
def cli() -> None:
    """Inverse Pose Space Deformation correctives for UsdSkel assets.

    pose -> (artists sculpt) -> fit -> eval. File conventions: docs/guide/file-conventions.md.
    """


#: Library parameter -> the flag that sets it, for messages (``SettingError``).
FLAGS = {"rtol": "--tolerance", "meshes": "--mesh", "drivers": "--driver", "as_name": "--as"}

_INPUT_PARAMS = ("asset", "examples", "correctives", "anim", "poses", "file", "layers", "jobs_file")
#: Parameters naming files or folders a command writes (with the inputs: recorded relative to the output).
_OUTPUT_PARAMS = ("output", "report", "points_cache", "obj_dir", "report_dir")


def _paths(ctx: click.Context, names: Sequence[str]) -> list[str]:
    """The values of a command's path parameters among names, flattened."""
    found: list[str] = []
    for name in names:
        value = ctx.params.get(name)
        found += [str(v) for v in value] if isinstance(value, (list, tuple)) else [str(value)] if value else []
    return found


@dataclass
class _Run:
    """What ``main`` hands its command (as click's ``ctx.obj``): the list that collects USD's
    diagnostics while the command runs, for ``main`` to show once it has succeeded."""

    usd_messages: list[str] = field(default_factory=list)
    argv: tuple[str, ...] = ()  # the command line, recorded in every output's provenance


class _Command(click.Command):
    """A psdbake command: when USD refuses the inputs' data past psdbake's own checks
    (``UsdDataError``), the message names this command's input files. Run from ``main``, USD's
    own diagnostics are trapped from here on (not before: options are parsed and ``--help``
    printed without loading USD)."""

    def invoke(self, ctx: click.Context):
        from .paths import check_paths

        files = _paths(ctx, _INPUT_PARAMS)
        check_paths(files, _paths(ctx, _OUTPUT_PARAMS))  # before USD sees a path it cannot take

        from .usd.dependencies import layers_kept_open
        from .usd.diagnostics import usd_diagnostics, usd_errors

        run = ctx.find_object(_Run)  # None under click's CliRunner: USD's diagnostics go to stderr, as ever
        trap: contextlib.AbstractContextManager[list[str]] = usd_diagnostics() if run else contextlib.nullcontext([])
        paths = files + _paths(ctx, _OUTPUT_PARAMS)
        invoked = outputs.invoked_as(run.argv, paths) if run else contextlib.nullcontext()
        with trap as found, layers_kept_open(), invoked:
            try:
                with usd_errors():
                    result = super().invoke(ctx)
            except UnicodeDecodeError:  # a name or string in the data is not UTF-8 (a damaged file)
                raise UsdDataError(f"{', '.join(files) or 'the inputs'}: a name or string in the data is not UTF-8 "
                                   "text") from None
            except UsdDataError as exc:
                raise UsdDataError(f"{', '.join(files) or 'the inputs'}: {exc}") from None
        if run is not None:
            run.usd_messages += found
        return result


cli.command_class = _Command


def _settings(rbf: dict, deformers, **more) -> FitSettings:
    """FitSettings from the shared RBF options (``rbf_options``) and a command's own."""
    from .settings import FitSettings

    drivers, kernel, sigma, degree, smoothing, no_rest_example, pose_space, twist_axis, clamp_weights, \
        normalize_weights = (rbf[name] for name in _RBF_NAMES)
    return FitSettings(
        drivers=tuple(drivers), kernel=kernel, sigma=sigma, degree=degree, smoothing=smoothing,
        rest_example=not no_rest_example, pose_space=pose_space, twist_axis=twist_axis,
        clamp_weights=clamp_weights, normalize_weights=normalize_weights, deformers=tuple(deformers), **more,
    )


@cli.command("pose")
@click.argument("asset", type=str)
@click.option("--poses", "poses", type=str,
              help="POSES layer (required): one pose per time code (any animation: a shot whose frames need fixing will "
                   "do).")
@click.option("--anim", "poses", hidden=True, type=str, help="Older name of --poses.")
@click.option("-o", "--output", required=True, type=str, help="EXAMPLES layer to write.")
@frame_options
@click.option("--mesh", "meshes", multiple=True, metavar="PATH",
              help="Only pose this mesh (path or unique name; repeatable). Default: every skinned mesh.")
@click.option("--obj-dir", metavar="DIR", default=None,
              help="Also write one OBJ per skinned mesh and time code into DIR, plus DIR/manifest.json, for sculpting "
                   "applications (read back with psdbake sculpts). Created if missing; a non-empty DIR must hold an "
                   "earlier manifest (its unedited files are replaced).")
@deformer_option
@force_option
@_common
def pose_cmd(asset, poses, output, frames, hold, meshes, obj_dir, deformers, force, quiet, verbose, as_json) -> None:
    """Write the skinned character at every time code of POSES (or every frame of --frames), for
    artists to sculpt."""
    from . import api, atomic
    from .shot.frames import parse_frames

    if poses is None:
        raise click.UsageError("Missing option '--poses' (the POSES layer: one pose per time code).")
    ui = Ui(quiet, verbose, as_json)
    reads = api.files_read([asset, poses], deformers)
    with atomic.forcing(force):
        atomic.check_outputs([(output, outputs.EXAMPLES)], reads)
    if obj_dir is not None:
        api.check_obj_dir(obj_dir, reads)
    with ui.warnings(), ui.progress("posing") as progress:
        result = api.pose(asset, poses, deformers, progress=progress, frames=parse_frames(frames), hold=hold,
                          meshes=meshes)
        api.write_pose(result, output, obj_dir=obj_dir, force=force)
    summary = {"output": output, "times": list(result.times), "meshes": list(result.meshes)}
    if obj_dir is not None:
        summary.update(obj_dir=obj_dir, obj_files=api.obj_files(result))
    if as_json:
        click.echo(json.dumps(summary, sort_keys=True))
    ui.say(f"psdbake pose: {len(result.meshes)} mesh(es) at {len(result.times)} time code(s)")
    if obj_dir is not None:
        ui.say(f"wrote {output} and {len(api.obj_files(result))} OBJ file(s) in {obj_dir}: sculpt them keeping the vertex "
               f"order, then run psdbake sculpts {asset} {output} --obj-dir {obj_dir} -o SCULPTED_EXAMPLES")
        return
    ui.say(f"wrote {output}: sculpt the points at each time code, then run psdbake fit")


@cli.command("sculpts")
@click.argument("asset", type=str)
@click.argument("examples", type=str)
@click.option("--obj-dir", required=True, metavar="DIR",
              help="The folder psdbake pose --obj-dir wrote, its OBJs sculpted (DIR/manifest.json lists them).")
@click.option("-o", "--output", required=True, type=str, help="SCULPTED_EXAMPLES layer to write (what fit reads).")
@click.option("--scale", "scales", multiple=True, metavar="[FILE=]S",
              help="Multiply the OBJs' coordinates by S first (e.g. 0.01: exported in centimetres, the asset is in "
                   "metres); FILE=S for one OBJ file only (repeatable).")
@click.option("--up-axis", "up_axes", multiple=True, metavar="[FILE=]Y|Z",
              help="The OBJs' up axis, when the sculpting application exported them with another one than the asset's; "
                   "they are turned to the asset's first. FILE=Z for one OBJ file only (repeatable).")
@force_option
@_common
def sculpts_cmd(asset, examples, obj_dir, output, scales, up_axes, force, quiet, verbose, as_json) -> None:
    """Read the sculpted OBJs of DIR back into EXAMPLES (the layer psdbake pose wrote with them):
    each OBJ checked against the asset's mesh and its posed points, written as SCULPTED_EXAMPLES for fit.
    Every file is checked before anything is refused: the refusal names each bad file."""
    from . import api, atomic

    ui = Ui(quiet, verbose, as_json)
    scale, per_scale = _per_file("--scale", scales, _positive_number)
    up_axis, per_up = _per_file("--up-axis", up_axes, lambda flag, v: v.upper())
    fixes: dict[str, dict] = {}
    for name, value in per_scale.items():
        fixes.setdefault(name, {})["scale"] = value
    for name, value in per_up.items():
        fixes.setdefault(name, {})["up_axis"] = value
    with atomic.forcing(force):
        atomic.check_outputs([(output, outputs.SCULPTED_EXAMPLES)], api.files_read([asset, examples]))
    with ui.warnings():
        result = api.sculpts(asset, examples, obj_dir, scale=scale, up_axis=up_axis, fixes=fixes)
        api.write_sculpts(result, output, force=force)
    ui.payload(console.sculpts_payload(result, output))
    console.say_sculpts(ui, result, output)


def _positive_number(flag: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise click.BadParameter(f"{text!r} is not a number", param_hint=f"'{flag}'") from None


def _per_file(flag: str, values: Sequence[str], convert: Callable[[str, str], Any]) -> tuple[Any, dict[str, Any]]:
    """(the value for every file, {file name: its own value}) from VALUE and FILE=VALUE items."""
    every, per = None, {}
    for item in values:
        name, eq, value = item.rpartition("=")
        if eq:
            per[name] = convert(flag, value)
        elif every is None:
            every = convert(flag, value)
        else:
            raise click.BadParameter(f"given twice for every file ({every!r} and {item!r})", param_hint=f"'{flag}'")
    return every, per


@cli.command("fit")
@click.argument("asset", type=str)
@click.argument("examples", nargs=-1, required=True, type=str)
@click.option("-o", "--output", required=True, type=str, help="CORRECTIVES layer to write.")
@rbf_options
@click.option("--tolerance", type=float, default=tol.INVERSE_RTOL, show_default=True,
              help="Inverse residual tolerance, fraction of the mesh's bounding-box diagonal.")
@click.option("--mesh", "meshes", multiple=True, metavar="PATH", help="Only fit this mesh (repeatable).")
@click.option("--group", default=None, metavar="NAME",
              help="Fit one correctives group (its own examples, drivers, kernel and sigma) and write or update it "
                   "inside OUTPUT, keeping OUTPUT's other groups. Without it, OUTPUT is replaced by local, additive "
                   "groups: one per joint the examples move, plus combinations (docs: explanation/pose-space-and-rbf.md).")
@click.option("--report", type=str, help="Write a JSON report here.")
@click.option("--strict", is_flag=True,
              help="Fail (exit 7, no CORRECTIVES written; --report still describes the run) if any vertex misses "
                   "--tolerance.")
@click.option("--allow-degraded", is_flag=True,
              help="Write the correctives even when the product does not reproduce some example within the round-trip "
                   "tolerance (1e-5 of the diagonal): by default such a fit fails with exit 7 and writes only --report.")
@click.option("--jobs", "-j", type=click.IntRange(min=1), default=None,
              help="Worker processes for the examples (default 1: UsdSkel already skins on every core). "
                   "The output is byte-identical whatever N is.")
@deformer_option
@force_option
@_common
def fit_cmd(asset, examples, output, rbf, tolerance, meshes, group, report, strict, allow_degraded, jobs, deformers,
            force, quiet, verbose, as_json) -> None:
    """Fit rest-space corrective BlendShapes and their RBF drivers from sculpted EXAMPLES."""
    from . import api, atomic
    from .usd.provenance import existing_kind

    ui = Ui(quiet, verbose, as_json)
    settings = _settings(rbf, deformers, rtol=tolerance, meshes=tuple(meshes), group=group)
    reads = api.files_read([asset, *examples], deformers)
    with atomic.forcing(force):
        atomic.check_outputs([(output, outputs.CORRECTIVES), *([(report, outputs.FIT_REPORT)] if report else [])],
                             reads)
    if group and os.path.exists(output) and existing_kind(output) == "correctives":
        with atomic.forcing(force):
            api.existing_groups(asset, output)  # refuse a layer it cannot update before the long fit
    with ui.warnings():
        with ui.progress("fitting examples") as progress:
            result = api.fit(asset, examples, settings, jobs=jobs, progress=progress)
        payload = console.fit_report(result, output)
        failure = api.fit_failure(result, output, strict=strict, allow_degraded=allow_degraded)
        if failure:
            payload["written"] = False
            if report:  # the diagnosis, so the long fit need not be run again to read it
                api.write_fit_report(result, report, console.json_text(payload), force=force)
            console.say_fit(ui, result, output, written=False)
            raise StrictError(failure)
        side = [(report, console.json_text(payload))] if report else []
        changes = api.write_correctives(result, output, update=bool(group), side_files=side, force=force,
                                        allow_degraded=allow_degraded)
    payload["groups"] = console.changes_payload(changes)
    ui.payload(payload)
    console.say_fit(ui, result, output, changes)


@cli.command("eval")
@click.argument("asset", type=str)
@click.argument("correctives", type=str)
@click.option("--anim", required=True, type=str, help="ANIM layer to drive the correctives over.")
@click.option("-o", "--output", required=True, type=str, help="WEIGHTS layer to write.")
@frame_options
@click.option("--points-cache", type=str,
              help="Also write final posed points per frame (no UsdSkel needed), as overrides to stack over ASSET.")
@click.option("--self-contained", is_flag=True,
              help="With --points-cache: write the asset's geometry into the cache too (flattened), so it opens on its "
                   "own in any USD application.")
@click.option("--chunk-size", type=int, default=None, metavar="N",
              help="Farm: one layer per N frames beside -o (and --points-cache), and -o a manifest stitching "
                   "them with USD value clips.")
@click.option("--chunk", type=int, default=None, metavar="K",
              help="Farm: with --chunk-size, write only chunk K (1-based) and the manifest.")
@click.option("--mesh", "meshes", multiple=True, metavar="PATH",
              help="Only this mesh's correctives (path or unique name; repeatable). Default: every corrected mesh.")
@strict_provenance_option
@deformer_option
@force_option
@_common
def eval_cmd(asset, correctives, anim, output, frames, hold, points_cache, self_contained, chunk_size, chunk, meshes,
             strict, deformers, force, quiet, verbose, as_json) -> None:
    """Compute the correctives' weights over ANIM and write them as a WEIGHTS layer."""
    from . import api, atomic
    from .deformers import load_deformers
    from .shot.frames import parse_frames

    ui = Ui(quiet, verbose, as_json)
    if self_contained and not points_cache:
        raise click.UsageError("--self-contained applies to --points-cache: give --points-cache CACHE")
    if self_contained and (chunk_size is not None or chunk is not None):
        raise click.UsageError("--self-contained is for one points cache: a chunked cache is stitched over ASSET "
                               "(stack ASSET CACHE -o VIEW)")
    if chunk_size is not None or chunk is not None:
        with atomic.forcing(force):
            _eval_chunked(ui, asset, correctives, anim, output, frames, points_cache, chunk_size, chunk, deformers,
                          strict, hold, meshes)
        return
    with ui.warnings():
        reads = api.files_read([asset, correctives, anim], deformers)
        with atomic.forcing(force):
            atomic.check_outputs([(output, outputs.WEIGHTS),
                                  *([(points_cache, outputs.POINTS_CACHE)] if points_cache else [])], reads)
        span = parse_frames(frames)
        load_deformers(deformers)
        with ui.progress("weights") as progress:
            result = api.evaluate(asset, correctives, anim, frames=span, progress=progress, strict=strict, hold=hold,
                                  meshes=meshes)
        cache = None
        if points_cache:
            with ui.progress("points cache") as progress:
                cache = (points_cache, api.points_cache_layer(result, deformers, progress=progress,
                                                              self_contained=self_contained))
        api.write_weights(result, output, points_cache=cache, deformers=deformers, force=force)
    console.say_eval(ui, result, output, points_cache)


@cli.command("mirror")
@click.argument("asset", type=str)
@click.argument("correctives", type=str)
@click.option("-o", "--output", required=True, type=str,
              help="CORRECTIVES layer to write: CORRECTIVES's groups with the mirrored ones written in (may be "
                   "CORRECTIVES itself, updated in place).")
@click.option("--joints", "joint_rules", multiple=True, required=True, metavar="REGEX=REPLACEMENT",
              help="Joint map (repeatable): a joint path takes the first rule whose REGEX it contains, rewritten with "
                   "re.sub, e.g. 'L_=R_' or '(^|/)l_=\\1r_'. Group names are mapped the same way.")
@click.option("--group", default=None, metavar="NAME",
              help="Mirror this group only. Default: every group whose drivers all map to other joints.")
@click.option("--as", "as_name", default=None, metavar="NAME",
              help="With --group: the mirrored group's name (default: the joint map applied to NAME).")
@click.option("--plane", type=click.Choice(["x", "y", "z"]), default="x", show_default=True,
              help="Mirror plane: the skeleton-space plane through the origin normal to this axis.")
@click.option("--mesh", "meshes", multiple=True, metavar="PATH",
              help="Only mirror groups on this mesh (path or unique name; repeatable). Default: every mesh.")
@click.option("--replace-sculpted", is_flag=True,
              help="Replace groups on the other side that were fitted from sculpts (by default they are kept, and "
                   "only groups made by an earlier mirror are replaced).")
@strict_provenance_option
@force_option
@_common
def mirror_cmd(asset, correctives, output, joint_rules, group, as_name, plane, meshes, replace_sculpted, strict, force,
               quiet, verbose, as_json) -> None:
    """Make the other side's correctives groups from one side's (a symmetric rig and mesh) and write them
    into CORRECTIVES's groups."""
    from . import api, atomic
    from .settings import MirrorSettings

    ui = Ui(quiet, verbose, as_json)
    settings = MirrorSettings(joints=tuple(joint_rules), plane=plane, group=group, as_name=as_name)
    with atomic.forcing(force):
        atomic.check_outputs([(output, outputs.CORRECTIVES)], api.mirror_reads(asset, correctives, output))
    with ui.warnings(), api.mirror_lock(correctives, output):
        result = api.mirror(asset, correctives, settings, strict=strict, meshes=meshes)
        changes = api.write_mirror(result, output, force=force, replace_sculpted=replace_sculpted)
    ui.payload({**console.mirror_report(result, output), "changes": console.changes_payload(changes)})
    console.say_mirror(ui, result, output, changes)


@cli.command("export-gltf")
@click.argument("asset", type=str)
@click.argument("correctives", type=str)
@click.option("--anim", required=True, type=str, help="ANIM layer: the shot to animate.")
@click.option("-o", "--output", required=True, type=str, help="SHOT.glb to write (glTF 2.0 binary).")
@frame_options
@strict_provenance_option
@force_option
@_common
def export_gltf_cmd(asset, correctives, anim, output, frames, hold, strict, force, quiet, verbose, as_json) -> None:
    """Write a skinned glTF 2.0 binary for game engines: meshes, skin, joint animation, the correctives
    as morph targets and eval's weights animating them."""
    from . import api
    from .shot.frames import parse_frames

    ui = Ui(quiet, verbose, as_json)
    with ui.warnings(), ui.progress("weights") as progress:  # the output is checked before any work
        result = api.export_gltf(asset, correctives, anim, output, frames=parse_frames(frames), progress=progress,
                                 strict=strict, force=force, hold=hold)
    ui.payload({"output": output, "meshes": list(result.meshes), "morph_targets": result.morph_targets,
                "sparse_targets": result.sparse_targets, "frames": result.frames, "bytes": result.size})
    ui.say(f"psdbake export-gltf: {len(result.meshes)} mesh(es), {result.morph_targets} morph target(s) "
           f"({result.sparse_targets} sparse), {result.frames} frame(s)")
    ui.say(f"wrote {output} ({result.size} bytes)")


@cli.command("export-blender")
@click.argument("asset", type=str)
@click.argument("correctives", type=str)
@click.option("-o", "--output", required=True, type=str, help="RIG.blend to write.")
@click.option("--anim", default=None, type=str,
              help="ANIM layer: the shot as the armature's action, to play with live correctives (optional).")
@click.option("--blender", default=None, metavar="PATH",
              help="A Blender executable, or a Python with the bpy module. Default: $PSDBAKE_BLENDER, else blender.")
@strict_provenance_option
@force_option
@_common
def export_blender_cmd(asset, correctives, output, anim, blender, strict, force, quiet, verbose, as_json) -> None:
    """Write a .blend whose correctives follow the armature live: Blender's USD import of the character,
    one shape key per channel, and drivers computing the psd: weights from the pose in simple expressions
    (they run with Python auto-run off)."""
    from . import api

    ui = Ui(quiet, verbose, as_json)
    with ui.warnings():
        result = api.export_blender(asset, correctives, output, anim=anim, blender=blender, strict=strict, force=force)
    ui.payload({"output": output, "blender": result.blender, "anim": anim, "drivers": result.drivers,
                "meshes": [{"mesh": m.path, "object": m.object, "armature": m.armature, "groups": list(m.groups),
                            "channels": m.channels, "nodes": m.nodes, "joints": list(m.graph.joints)}
                           for m in result.meshes]})
    ui.say(f"psdbake export-blender: {len(result.meshes)} mesh(es), "
           f"{sum(m.channels for m in result.meshes)} channel(s) driven live by {result.drivers} simple-expression "
           f"driver(s) (Blender {result.blender}, {result.seconds:.1f} s)")
    for m in result.meshes:
        ui.say(f"  <{m.path}> -> object {m.object!r}, armature {m.armature!r}: {m.channels} channel(s), "
               f"{m.nodes} driven propert{'y' if m.nodes == 1 else 'ies'} on its shape keys, "
               f"{len(m.graph.joints)} driver joint(s)")
    ui.say(f"wrote {output}")


def _eval_chunked(ui: Ui, asset, correctives, anim, output, frames, points_cache, chunk_size, chunk,
                  deformers, strict, hold, meshes) -> None:
    """eval --chunk-size N [--chunk K]: chunk layers plus the value-clip manifest(s) (psdbake.farm.chunked)."""
    from . import api, atomic
    from .deformers import load_deformers
    from .errors import ChunkUsageError
    from .farm import chunked
    from .shot.frames import parse_frames

    if chunk_size is None:
        raise ChunkUsageError("--chunk needs --chunk-size (every farm task must cut the shot the same way)")
    if chunk_size < 1:
        raise ChunkUsageError(f"--chunk-size {chunk_size}: must be at least 1 frame")
    reads = api.files_read([asset, correctives, anim], deformers)
    atomic.check_outputs([(output, outputs.WEIGHTS), *([(points_cache, outputs.POINTS_CACHE)] if points_cache else [])],
                         reads)
    with ui.warnings():
        load_deformers(deformers)
        with ui.progress("weights") as progress:
            ev = chunked.evaluate_chunks(asset, correctives, anim, chunk_size, frames=parse_frames(frames),
                                         chunk=chunk, progress=progress, strict=strict, hold=hold, meshes=meshes)
        with ui.progress("points cache") as progress:
            written = chunked.write_chunks(ev, output, points_cache=points_cache, deformers=deformers, progress=progress)
    console.say_chunks(ui, ev, written)


@cli.command("compare")
@click.argument("asset", type=str)
@click.argument("examples", nargs=-1, required=True, type=str)
@click.option("--anim", required=True, type=str, help="ANIM layer to compare over (may be ASSET).")
@click.option("-o", "--output", "report_dir", required=True, type=str,
              help="REPORT_DIR: created if missing; a non-empty folder must hold an earlier psdbake compare report "
                   "(its files are replaced).")
@click.option("--vertex", type=click.IntRange(min=0), default=None,
              help="Vertex for the correction-angle figure. Default: the most corrected one (and the one where "
                   "forward and inverse disagree most).")
@click.option("--mesh", default=None, metavar="PATH", help="Only fit and report this mesh.")
@frame_options
@click.option("--views", metavar="F1,F2,...", help="Frames to draw the mesh at. Default: three chosen frames.")
@rbf_options
@deformer_option
@_common
def compare_cmd(asset, examples, anim, report_dir, vertex, mesh, frames, hold, views, rbf, deformers, quiet, verbose,
                as_json) -> None:
    """Fit EXAMPLES, then compare plain skinning, forward PSD and inverse PSD (same RBF weights)
    at every frame of ANIM; write an HTML report with figures and per-frame statistics."""
    from . import api, report
    from .report import compare as compare_meshes
    from .shot.frames import parse_frames

    ui = Ui(quiet, verbose, as_json)
    # the paper's comparison: one RBF, the same weights for forward and inverse PSD
    settings = _settings(rbf, deformers, meshes=(mesh,) if mesh else (), group=DEFAULT_GROUP)
    span, view_frames = parse_frames(frames), report.parse_views(views)
    report.check_report_dir(report_dir, api.files_read([asset, *examples, anim], deformers))  # before the fit
    with ui.warnings(), ui.progress("fitting examples") as progress:
        result = compare_meshes(asset, examples, anim, settings, frames=span, hold=hold, progress=progress)
        prepared = report.prepare(result, asset_label=asset, mesh=mesh, vertex=vertex, views=view_frames)
        report.write_prepared(prepared, report_dir)
    if as_json:
        click.echo(json.dumps(report.summary(prepared, report_dir), sort_keys=True))
    for line in report.summary_lines(prepared, report_dir):
        ui.say(line)


@cli.command("inspect")
@click.argument("file", type=str)
@click.option("--asset", default=None, metavar="ASSET",
              help="The asset FILE is layered over (EXAMPLES, POSES): spell out each example's pose, the joints turned "
                   "from bind and by how much. Default: the asset FILE records, if any.")
@_common
def inspect_cmd(file, asset, quiet, verbose, as_json) -> None:
    """What FILE holds: skeletons (joint hierarchy), skinned meshes, animations, example poses and psd:
    correctives."""
    from . import api

    info = api.describe(file, asset=asset)
    if as_json:
        click.echo(json.dumps(info, indent=2, sort_keys=True))
    elif not quiet:
        console.say_inspect(file, info, verbose)
    else:
        for warning in info.get("warnings", []):
            click.echo(f"psdbake: warning: {warning}", err=True)


@cli.command("stack")
@click.argument("layers", nargs=-1, required=True, type=str)
@click.option("-o", "--output", required=True, type=str, help="The stack layer to write (open it in any UsdSkel viewer).")
@strict_provenance_option
@force_option
@_common
def stack_cmd(layers, output, strict, force, quiet, verbose, as_json) -> None:
    """Write OUTPUT sublayering LAYERS, so any UsdSkel viewer shows the corrected character.

    LAYERS in any order: each layer's role (ASSET, CORRECTIVES, ANIM, WEIGHTS, points cache) is
    read from the layer itself, and they are stacked in the order a viewer needs.
    """
    from . import api, atomic

    ui = Ui(quiet, verbose, as_json)
    with atomic.forcing(force):
        atomic.check_outputs([(output, outputs.STACK)], api.files_read(layers))
    with ui.warnings():
        result = api.write_stack(output, layers, strict=strict, force=force)
    ui.payload({"output": output, "layers": [{"layer": p, "role": r} for p, r in reversed(result.layers)],
                "reordered": result.reordered})
    shown = " > ".join(f"{p} ({r.upper().replace('_', ' ')})" for p, r in reversed(result.layers))
    ui.say(f"psdbake stack: {len(result.layers)} layer(s), strongest first: {shown}"
           + ("  (reordered by role)" if result.reordered else ""))
    ui.say(f"wrote {output}")


@cli.command("groups")
@click.argument("file", type=str)
@click.option("--remove", multiple=True, metavar="NAME", help="Remove this group from every mesh (repeatable).")
@click.option("--rename", multiple=True, metavar="OLD=NEW",
              help="Rename a group, its BlendShapes and channels (repeatable): evaluate WEIGHTS again afterwards.")
@click.option("--asset", default=None, metavar="ASSET",
              help="The asset FILE's correctives belong to. Default: the one FILE records it was fitted on.")
@click.option("-o", "--output", default=None, type=str,
              help="Write the edited CORRECTIVES here. Default: FILE itself, updated in place.")
@force_option
@_common
def groups_cmd(file, remove, rename, asset, output, force, quiet, verbose, as_json) -> None:
    """List the correctives groups of FILE (a CORRECTIVES layer), or remove or rename some."""
    from . import api

    ui = Ui(quiet, verbose, as_json)
    if not remove and not rename:
        if output:
            raise click.UsageError("-o needs --remove or --rename (listing writes nothing)")
        groups = api.list_groups(file)
        ui.payload({"file": file, "groups": groups})
        console.say_groups(ui, file, groups)
        return
    pairs = {}
    for rule in rename:
        old, eq, new = rule.partition("=")
        if not eq or not old or not new:
            raise click.BadParameter(f"{rule!r}: expected OLD=NEW", param_hint="'--rename'")
        pairs[old] = new
    with ui.warnings():
        changes = api.edit_groups(file, remove=remove, rename=pairs, output=output, asset=asset, force=force)
    ui.payload({"file": file, "output": output or file, "changes": console.changes_payload(changes)})
    console.say_changes(ui, changes, output or file)
    if changes.renamed:
        ui.warn(f"{output or file}: renamed groups have new channel names: evaluate WEIGHTS again (psdbake eval)")
    ui.say(f"wrote {output or file}")


@cli.command("batch")
@click.argument("jobs_file", metavar="JOBS.toml", type=str)
@click.option("--jobs", "-j", "workers", type=click.IntRange(min=1), default=None,
              help="Jobs at once on the local pool (default: one per core; a job's start-up is single-threaded).")
@click.option("--workers", "-w", "workers_alias", type=click.IntRange(min=1), default=None, hidden=True)
@click.option("--scheduler", metavar="tcp://HOST:PORT",
              help="Run on this Dask cluster instead (pip install 'psdbake[dask]'); workers need the same paths.")
@click.option("--retries", type=click.IntRange(min=0), default=2, show_default=True,
              help="Reruns of a job whose process is killed by a signal (a psdbake exit code is final).")
@click.option("--dry-run", is_flag=True, help="Check the jobs file and print the commands in order; run nothing.")
@click.option("--allow-deformers-from-jobs", "allow_deformers", is_flag=True,
              help="Run the deformers the jobs file names (their code runs in every job). Without it, a jobs file "
                   "naming a deformer is refused.")
@_common
def batch_cmd(jobs_file, workers, workers_alias, scheduler, retries, dry_run, allow_deformers, quiet, verbose,
              as_json) -> None:
    """Run the jobs of JOBS.toml (any command that writes files), in parallel where their files allow.

    A job reading a file other jobs write runs after them; jobs writing one file run in file
    order. One line per finished job on stderr; the exit code is the first failed job's.
    """
    from . import farm

    if workers is not None and workers_alias is not None and workers != workers_alias:
        raise click.UsageError(f"--jobs {workers} and --workers {workers_alias} name one setting: give one")
    workers = workers if workers is not None else workers_alias  # --workers/-w: the name before --jobs
    ui = Ui(quiet, verbose, as_json)
    jobs = farm.load_jobs(jobs_file, {name: cli.commands[name] for name in farm.COMMANDS},  # the CLI is the job schema
                          allow_deformers=allow_deformers)
    farm.check_reads(jobs)  # a missing input fails now, not hours into the run
    if dry_run:
        ui.say(f"# {len(jobs.tasks)} task(s), run in {jobs.folder} (the jobs file's folder), in this order:")
        if as_json:
            click.echo(json.dumps([{"job": t.label, "command": t.command_line, "needs": list(t.needs),
                                    "after": list(t.after), "key": t.key} for t in jobs.tasks], sort_keys=True))
        labels = {t.key: t.label for t in jobs.tasks}
        for t in jobs.tasks:
            waits = ", ".join(labels[k] for k in (*t.needs, *t.after))
            ui.say(f"{t.label:<24} {t.command_line}" + (f"   (after {waits})" if waits else ""))
        return

    result = farm.run_batch(jobs, scheduler=scheduler, workers=workers, signal_retries=retries,
                            on_done=console.batch_lines(jobs_file, quiet, verbose))
    ui.payload(result.summary())
    where = f"on {scheduler} ({result.workers} workers)" if scheduler else f"on {result.workers} local worker(s)"
    ui.say(f"psdbake batch: {len(result.results)} job(s) {where}: {result.count('ok')} ok, {result.count('failed')} failed, "
           f"{result.count('skipped')} skipped" + (f", {result.count('lost')} lost" if result.count("lost") else "")
           + f" in {result.seconds:.2f} s")
    if result.exit_code:
        bad = [r.label for r in result.results if r.status in ("failed", "lost")]
        skipped = result.count("skipped")
        raise farm.BatchError(f"{jobs_file}: {len(bad)} job(s) failed: {', '.join(bad)}"
                               + (f"; {skipped} skipped" if skipped else ""), result.exit_code)


def _terminate(signum, frame) -> None:
    """SIGTERM unwinds like Ctrl-C, so temporary files are removed on the way out."""
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point: run the CLI, turn every failure into one line and an exit code."""
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        signal.signal(signal.SIGTERM, _terminate)
    run = _Run()
    try:
        # make_context + invoke rather than cli.main: click's main echoes a blank line on
        # Ctrl-C (for the terminal's ^C), and a refusal must be exactly one line
        args = list(argv) if argv is not None else sys.argv[1:]
        run.argv = tuple(args)
        with cli.make_context("psdbake", args, obj=run) as ctx:
            cli.invoke(ctx)
        for message in dict.fromkeys(run.usd_messages):  # USD repeats itself; once is enough
            click.echo(f"psdbake: warning: USD: {message}", err=True)
    except click.exceptions.Exit as exc:  # --help, --version
        sys.exit(exc.exit_code)
    except click.exceptions.Abort:
        click.echo("psdbake: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except SettingError as exc:  # the library names its parameter; users know the flag
        click.echo(f"psdbake: error: {exc.render(FLAGS.get(exc.param, '--' + exc.param.replace('_', '-')))}", err=True)
        sys.exit(exc.exit_code)
    except PsdError as exc:
        one_line = re.sub(r"\s*\n\s*", " ", str(exc).strip())  # a value's repr may span lines (a matrix)
        click.echo(f"psdbake: error: {one_line}", err=True)
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        click.echo("psdbake: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except BrokenPipeError:  # stdout closed early (``psdbake inspect X | head``): outputs are already whole
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's recipe: no second error
        sys.exit(EXIT_INTERNAL)
    except Exception as exc:
        if os.environ.get("PSDBAKE_DEBUG"):
            raise
        first = (str(exc).strip().splitlines() or [""])[0]
        click.echo(f"psdbake: internal error: {type(exc).__name__}: {first} (set PSDBAKE_DEBUG=1 for a traceback)", err=True)
        sys.exit(EXIT_INTERNAL)
    sys.exit(0)
