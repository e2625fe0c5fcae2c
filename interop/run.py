"""``make interop``: does psdbake's output look the same in Blender's default USD import as in
Pixar's ``UsdSkel.BakeSkinning``, at every frame?

Runs in the project venv (``.venv/bin/python -m interop.run``). Per case it builds, in a temporary
folder, with the psdbake CLI and its default fit/eval options:

- the PLAIN stack, ASSET + ANIM (``psdbake stack``), and
- the CORRECTED stack, ASSET + CORRECTIVES + ANIM + WEIGHTS (``psdbake fit``, ``eval``, ``stack``);

bakes each with ``UsdSkel.BakeSkinning`` over the animation's time samples (world space:
``ComputeLocalToWorldTransform``), imports each into Blender 5.0 (``interop/blender_points.py`` in
``.venv-blender``), and compares per mesh, in USD world units, after undoing the conversion the
Blender importer documents (``convert_to_z_up``: +90 degrees about X when the stage is Y-up;
``apply_unit_conversion_scale``: scale by metersPerUnit times the ``scale`` option):

    error = max over frames and vertices of |blender - BakeSkinning| / bounding-box diagonal of
            the mesh at bind pose (rest points through geomBindTransform and the skeleton's world
            transform: what a UsdSkel viewer shows with no animation)

Criterion per mesh: corrected error <= plain error + 1e-6. Also reported: whether every channel
(``skel:blendShapes``) arrived as a shape key under its own name, and the shape-key values Blender
applies (clamped to [slider_min, slider_max]) against the weights UsdSkel applies.

Exit 0 when every case meets the criterion, 1 when one does not, 2 when the harness could not
build, bake, import or map a case. The report goes to stdout and to OUT/interop/ (report.md,
weights.md with the per-frame weights, results.json).

glTF: ``check_gltf`` compares a .glb imported by Blender's glTF importer with a BakeSkinning
reference; the glTF cases run when ``psdbake export-gltf --help`` works (criterion 1e-5).

Live rig: ``live_case`` builds ``psdbake export-blender ASSET CORRECTIVES --anim ANIM`` (the
drivers compute the weights from the armature's pose), opens the .blend as a user does, Python
auto-run off, plays every frame and asserts: each channel's shape-key value close to
``psdbake eval``'s weight (what UsdSkel reads from WEIGHTS): what the difference moves a point by,
|Δw| times the channel's largest offset, within 1e-7 of the diagonal (``LIVE_POINT_ATOL``); the
evaluated mesh within plain + 1e-6 of the corrected stack's BakeSkinning (the criterion above),
every driver a valid simple
expression and no Python blocked; and (``interop/blender_constraints.py``) that a driver bone
turned by a constraint drives the correctives as the same turn keyed on the bone, within 1e-6.
``interop/blender_speed.py`` then times a frame of the plain stack, the baked corrected stack and
the live rig side by side in one Blender process.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIXTURES = os.path.join(ROOT, "fixtures")
HERE = os.path.dirname(os.path.abspath(__file__))
BLENDER_SCRIPT = os.path.join(HERE, "blender_points.py")
SPEED_SCRIPT = os.path.join(HERE, "blender_speed.py")
CONSTRAINTS_SCRIPT = os.path.join(HERE, "blender_constraints.py")
DEFAULT_BLENDER_PYTHON = os.path.join(ROOT, ".venv-blender", "bin", "python")

CRITERION = 1e-6  # corrected error may exceed plain error by at most this (fraction of the diagonal)
GLTF_CRITERION = 1e-5  # glTF: error against the corrected BakeSkinning reference
PLAIN_MISMATCH = 1e-5  # a plain-stack error above this is a placement mismatch of Blender's import
LIVE_WEIGHT_ATOL = 1e-6  # live rig: a constraint's turn against the same turn keyed (Blender against itself)
#: Live rig: each channel's shape-key value against eval's weight, as what the difference moves a
#: point by (|Δw| x the channel's largest offset, fraction of the diagonal): a tenth of CRITERION.
#: Not |Δw| alone: both read the same float32 joint rotations, but Blender's pass through its pose
#: matrices and back moves them by ~1e-7, and a narrow kernel (the combinations of shot frames a few
#: degrees apart) turns that into |Δw| of a few 1e-6, on offsets a few thousandths of the diagonal
#: long (docs/decisions/blender-live-drivers.md).
LIVE_POINT_ATOL = 1e-7
SPEED_ROUNDS = 5  # blender_speed.py: interleaved rounds per case (each plays the shot 3 times per variant)
BLENDER_NAME_BYTES = 63  # Blender's MAX_NAME - 1
BLENDER_FACTORY_FPS = 24.0  # the scene's frame rate after read_factory_settings (the glTF importer keeps it)


def fixture(*parts: str) -> str:
    return os.path.join(FIXTURES, *parts)


# --- cases --------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One rig: ASSET, the fits that make CORRECTIVES ((group or None, EXAMPLES...) per ``psdbake
    fit`` run, None: fit's default layout), and ANIM (None: the asset carries its animation)."""

    name: str
    asset: str
    fits: tuple[tuple[str | None, tuple[str, ...]], ...]
    anim: str | None
    note: str = ""
    mirror: tuple[str, ...] = ()  # psdbake mirror --joints rules applied to CORRECTIVES after the fits


def character_fits() -> tuple[tuple[str | None, tuple[str, ...]], ...]:
    """The character as tests/test_character.py fits it: one ``fit --group`` per group, all groups."""
    sys.path.insert(0, FIXTURES)
    import character  # fixtures/character.py

    return tuple((group, tuple(fixture("character", character.EXAMPLE_SETS[name]["file"]) for name in names))
                 for group, names in character.FIT_GROUPS.items())


def make_cases(tmp: str, only: list[str] | None) -> list[Case]:
    cases: list[Case] = []

    def want(name: str) -> bool:
        return not only or name in only

    if want("humanoid"):
        cases.append(Case("humanoid", fixture("humanoid", "humanoid.usda"),
                          ((None, (fixture("humanoid", "humanoid_examples.usda"),)),),
                          fixture("humanoid", "humanoid_anim.usda"), "make demo's set-up: default fit, combinations"))
    if want("humanoid_mirrored"):
        cases.append(Case("humanoid_mirrored", fixture("humanoid", "humanoid.usda"),
                          ((None, (fixture("humanoid", "humanoid_examples.usda"),)),),
                          fixture("humanoid", "humanoid_anim.usda"),
                          "make demo's fit, then psdbake mirror --joints L_=R_: the R groups from the L ones",
                          mirror=("L_=R_",)))
    if want("humanoid_shots"):
        sys.path.insert(0, FIXTURES)
        import humanoid  # fixtures/humanoid.py

        shot = humanoid.write_shot_files(os.path.join(tmp, "humanoid_shots_fixture"), fixture("humanoid", "humanoid.usda"))
        cases.append(Case("humanoid_shots", fixture("humanoid", "humanoid.usda"), ((None, (shot["additive"],)),),
                          shot["second"], "10 sculpts on frames of a shot where every region moves, played over "
                          "another shot: per-joint terms and gated combinations (psd: v5)"))
    if want("arm"):
        cases.append(Case("arm", fixture("arm_lbs.usda"), ((None, (fixture("arm_lbs_examples.usda"),)),),
                          fixture("arm_anim.usda"), "a layout Blender misplaces (psdbake inspect warns)"))
    if want("character"):
        cases.append(Case("character", fixture("character", "character.usda"), character_fits(),
                          fixture("character", "character_anim.usda"), "three fit --group runs, as tests/test_character.py"))
    if want("cesiumman"):
        cases.append(Case("cesiumman", fixture("cesiumman", "CesiumMan.usdz"),
                          ((None, (fixture("cesiumman", "cesiumman_examples.usda"),)),), None,
                          "its own 48-frame walk (the usdz) is ANIM"))
    if want("long_path"):
        from interop import long_path

        asset, examples, anim = long_path.write(os.path.join(tmp, "long_path_fixture"))
        cases.append(Case("long_path", asset, ((None, (examples,)),), anim,
                          f"arm with its mesh at {long_path.MESH} (generated)"))
    return cases


# --- running tools ------------------------------------------------------------------------------

class HarnessError(RuntimeError):
    pass


def psdbake_exe() -> str:
    """The psdbake CLI: $PSDBAKE if set (e.g. another checkout's), else the one beside this Python."""
    if os.environ.get("PSDBAKE"):
        return os.environ["PSDBAKE"]
    beside = os.path.join(os.path.dirname(sys.executable), "psdbake")
    return beside if os.path.exists(beside) else (shutil.which("psdbake") or "psdbake")


def run(cmd: list[str], log: list[str]) -> subprocess.CompletedProcess:
    log.append("$ " + " ".join(os.path.relpath(c, ROOT) if os.path.isabs(c) and c.startswith(ROOT) else c for c in cmd))
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise HarnessError(f"exit {proc.returncode}: {' '.join(cmd)}\n{proc.stderr.strip()[-2000:]}")
    return proc


def psdbake(log: list[str], *args: str) -> None:
    run([psdbake_exe(), *args, "-q"], log)


def inspect_warnings(asset: str) -> set[str]:
    """The mesh paths ``psdbake inspect ASSET`` warns Blender's import will misplace."""
    proc = subprocess.run([psdbake_exe(), "inspect", asset, "--json"], capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise HarnessError(f"psdbake inspect {asset} failed: {proc.stderr.strip()}")
    return {w.split(" <", 1)[1].split(">", 1)[0] for w in json.loads(proc.stdout).get("warnings", [])}


def has_export_gltf() -> bool:
    proc = subprocess.run([psdbake_exe(), "export-gltf", "--help"], capture_output=True, text=True, cwd=ROOT)
    return proc.returncode == 0


@dataclass
class Stacks:
    plain: str
    corrected: str
    correctives: str
    anim: str
    commands: list[str] = field(default_factory=list)


def build(case: Case, folder: str) -> Stacks:
    """The psdbake CLI with default fit/eval options: CORRECTIVES, WEIGHTS and both stacks."""
    os.makedirs(folder, exist_ok=True)
    log: list[str] = []
    corr, weights = os.path.join(folder, "correctives.usda"), os.path.join(folder, "weights.usda")
    for group, examples in case.fits:
        psdbake(log, "fit", case.asset, *examples, *(["--group", group] if group else []), "-o", corr)
    if case.mirror:
        psdbake(log, "mirror", case.asset, corr, *(a for rule in case.mirror for a in ("--joints", rule)), "-o", corr,
                "--replace-sculpted")  # the case is the R groups made from the L ones, over the ones fitted on R sculpts
    anim = case.anim or case.asset
    psdbake(log, "eval", case.asset, corr, "--anim", anim, "-o", weights)
    anim_layers = [case.anim] if case.anim else []
    plain, corrected = os.path.join(folder, "plain.usda"), os.path.join(folder, "corrected.usda")
    psdbake(log, "stack", case.asset, *anim_layers, "-o", plain)
    psdbake(log, "stack", case.asset, corr, *anim_layers, weights, "-o", corrected)
    return Stacks(plain, corrected, corr, anim, log)


# --- the reference: Pixar's UsdSkel ---------------------------------------------------------------

def gf_to_np(m) -> np.ndarray:
    """A Gf.Matrix4d (row vectors, p' = p M) as a numpy matrix acting on column vectors."""
    return np.array(m, dtype=np.float64).T


def apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Column-vector 4x4 m applied to points (..., 3)."""
    return pts @ m[:3, :3].T + m[:3, 3]


@dataclass
class MeshRef:
    path: str
    points: np.ndarray  # authored rest points (n, 3), mesh space
    diag: float  # bind-pose bounding-box diagonal, world units
    skeleton: str | None
    channels: list[str]  # the mesh's skel:blendShapes
    weights: np.ndarray  # (F, K) UsdSkel's weight per channel and frame (0 where the animation lacks it)
    reach: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (K,) each channel's largest offset / diag
    world: np.ndarray | None = None  # (F, n, 3) BakeSkinning, world space
    layout: dict = field(default_factory=dict)


@dataclass
class Reference:
    stack: str
    frames: list[float]
    up_axis: str
    meters_per_unit: float
    tcps: float  # timeCodesPerSecond
    meshes: dict[str, MeshRef]
    roots: dict[str, np.ndarray]  # root prim name -> its world matrix at the first frame (column vectors)


def outermost_skel_roots(stage: Usd.Stage) -> list[UsdSkel.Root]:
    roots = []
    it = iter(Usd.PrimRange(stage.GetPseudoRoot()))
    for prim in it:
        if prim.IsA(UsdSkel.Root):
            roots.append(UsdSkel.Root(prim))
            it.PruneChildren()
    return roots


def animation_frames(stack: str) -> list[float]:
    """The time samples of every bound animation (joint transforms and blend-shape weights)."""
    stage = Usd.Stage.Open(stack)
    cache = UsdSkel.Cache()
    times: set[float] = set()
    for root in outermost_skel_roots(stage):
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            anim = cache.GetSkelQuery(binding.GetSkeleton()).GetAnimQuery()
            if anim:
                times.update(anim.GetJointTransformTimeSamples())
                times.update(anim.GetBlendShapeWeightTimeSamples())
    if not times:
        raise HarnessError(f"no animation time samples in {stack}")
    return sorted(times)


def skinned_meshes(stage: Usd.Stage, frames: list[float]) -> dict[str, MeshRef]:
    """Every Mesh: rest points, bind-pose diagonal, channels and UsdSkel's weights per frame, and the
    transforms that decide where Blender's importer puts it (parent, own xform, geomBindTransform, skeleton)."""
    cache = UsdSkel.Cache()
    out: dict[str, MeshRef] = {}
    t0 = Usd.TimeCode(frames[0])
    xf = UsdGeom.XformCache(t0)
    for root in outermost_skel_roots(stage):
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            skel = binding.GetSkeleton()
            skel_query = cache.GetSkelQuery(skel)
            anim = skel_query.GetAnimQuery()
            skel_world = gf_to_np(xf.GetLocalToWorldTransform(skel.GetPrim()))
            for target in binding.GetSkinningTargets():
                prim = target.GetPrim()
                if not prim.IsA(UsdGeom.Mesh):
                    continue
                points = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
                gbind = gf_to_np(target.GetGeomBindTransform(t0))
                bind_world = apply(skel_world @ gbind, points)
                diag = float(np.linalg.norm(bind_world.max(axis=0) - bind_world.min(axis=0)))
                channels = [str(c) for c in (target.GetBlendShapeOrder() or [])]
                weights = np.zeros((len(frames), len(channels)))
                if anim and channels:
                    order = [str(c) for c in anim.GetBlendShapeOrder()]
                    for fi, t in enumerate(frames):
                        values = list(anim.ComputeBlendShapeWeights(Usd.TimeCode(t)) or [])
                        by_name = dict(zip(order, values, strict=False))
                        weights[fi] = [by_name.get(c, 0.0) for c in channels]
                parent_world = gf_to_np(xf.GetParentToWorldTransform(prim))
                local = gf_to_np(xf.GetLocalTransformation(prim)[0])
                # Blender 5.0's USD import: mesh object matrix = geomBindTransform under its parent's
                # object; UsdSkel: skinned points in skeleton space, the mesh's own xform ignored
                predicted = np.linalg.norm(apply(parent_world @ gbind, points) - bind_world, axis=1).max() / diag
                layout = {
                    "parent": str(prim.GetParent().GetPath()), "skeleton": str(skel.GetPath()),
                    "parent_world_equals_skeleton_world": bool(np.allclose(parent_world, skel_world, atol=1e-9)),
                    "mesh_xform_identity": bool(np.allclose(local, np.eye(4), atol=1e-12)),
                    "geom_bind_identity": bool(np.allclose(gbind, np.eye(4), atol=1e-12)),
                    "predicted_bind_offset": float(predicted),
                }
                out[str(prim.GetPath())] = MeshRef(str(prim.GetPath()), points, diag, str(skel.GetPath()), channels,
                                                   weights, layout=layout,
                                                   reach=channel_reach(target, skel_world @ gbind, diag, len(channels)))
    return out


def channel_reach(target: UsdSkel.SkinningQuery, to_world: np.ndarray, diag: float, count: int) -> np.ndarray:
    """Each channel's largest offset in world units over the diagonal (its blend shape's
    offsets through the bind transform's linear part; channel k is skel:blendShapeTargets[k])."""
    reach = np.zeros(count)
    targets = UsdSkel.BindingAPI(target.GetPrim()).GetBlendShapeTargetsRel().GetTargets()
    stage = target.GetPrim().GetStage()
    for k, path in enumerate(targets[:count]):
        offsets = UsdSkel.BlendShape(stage.GetPrimAtPath(path)).GetOffsetsAttr().Get()
        if offsets:
            reach[k] = np.linalg.norm(np.asarray(offsets, dtype=np.float64) @ to_world[:3, :3].T, axis=1).max() / diag
    return reach


_KEEP: list[Sdf.Layer] = []  # anonymous root layers stay alive while their stages are read


def bake(stack: str, frames: list[float]) -> Reference:
    """UsdSkel.BakeSkinning of the stack (an anonymous root layer sublayering it), world points per frame."""
    meta_stage = Usd.Stage.Open(stack)
    up_axis = str(UsdGeom.GetStageUpAxis(meta_stage))
    mpu = float(UsdGeom.GetStageMetersPerUnit(meta_stage))
    tcps = float(meta_stage.GetTimeCodesPerSecond())
    root_layer = Sdf.Layer.CreateAnonymous(".usda")
    root_layer.subLayerPaths.append(stack)
    _KEEP.append(root_layer)
    stage = Usd.Stage.Open(root_layer)
    stage.SetEditTarget(Usd.EditTarget(root_layer))
    meshes = skinned_meshes(stage, frames)
    roots = {}
    xf = UsdGeom.XformCache(Usd.TimeCode(frames[0]))
    for prim in stage.GetPseudoRoot().GetChildren():
        if prim.IsA(UsdGeom.Xformable):
            roots[prim.GetName()] = gf_to_np(xf.GetLocalToWorldTransform(prim))
    if not UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(min(frames), max(frames))):
        raise HarnessError(f"UsdSkel.BakeSkinning failed on {stack}")
    for path, ref in meshes.items():
        prim = stage.GetPrimAtPath(path)
        attr = UsdGeom.PointBased(prim).GetPointsAttr()
        samples = set(attr.GetTimeSamples())
        missing = [t for t in frames if t not in samples]
        if missing:
            raise HarnessError(f"BakeSkinning wrote no points for {path} at {missing[:5]} in {stack}")
        xformable = UsdGeom.Xformable(prim)
        ref.world = np.stack([apply(gf_to_np(xformable.ComputeLocalToWorldTransform(Usd.TimeCode(t))),
                                    np.array(attr.Get(Usd.TimeCode(t)), dtype=np.float64)) for t in frames])
    return Reference(stack, frames, up_axis, mpu, tcps, meshes, roots)


# --- Blender ------------------------------------------------------------------------------------

@dataclass
class BlenderView:
    meta: dict
    arrays: dict[str, np.ndarray]
    seconds: float

    def mesh_objects(self) -> list[tuple[int, dict]]:
        return [(i, o) for i, o in enumerate(self.meta["objects"]) if o["type"] == "MESH"]


def blender_python() -> str:
    """The bpy venv's Python: $BLENDER_PYTHON (relative to the repository) or .venv-blender/bin/python."""
    return os.path.join(ROOT, os.environ.get("BLENDER_PYTHON") or DEFAULT_BLENDER_PYTHON)


def blender_points(path: str, frames: list[float], out: str, importer: str | None = None) -> BlenderView:
    """Run interop/blender_points.py in the bpy venv on path; load what it wrote."""
    frame_arg = ",".join(f"{f:g}" for f in frames)
    cmd = [blender_python(), BLENDER_SCRIPT, path, "--frames", frame_arg, "-o", out]
    if importer:
        cmd += ["--importer", importer]
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    seconds = time.perf_counter() - start
    with open(out + ".log", "w", encoding="utf-8") as fh:
        fh.write(proc.stdout + proc.stderr)
    if proc.returncode != 0 or not os.path.exists(out):
        raise HarnessError(f"blender_points.py failed (exit {proc.returncode}) on {path}:\n{(proc.stdout + proc.stderr)[-2000:]}")
    with np.load(out) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays.pop("meta")))
    return BlenderView(meta, arrays, seconds)


def rot_x(degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m


def usd_import_conversion(up_axis: str, meters_per_unit: float, options: dict) -> tuple[np.ndarray, str]:
    """What Blender's USD importer applies to the stage's root objects (blender/io/usd: convert_to_z_up
    and apply_unit_conversion_scale), as a column-vector matrix: Blender world = C @ USD world."""
    scale = float(options.get("scale", 1.0))
    if options.get("apply_unit_conversion_scale", False):
        scale *= meters_per_unit
    rotate = up_axis != "Z"
    c = (rot_x(90.0) if rotate else np.eye(4)) @ np.diag([scale, scale, scale, 1.0])
    text = (f"{'Rx(+90 deg) (upAxis ' + up_axis + ' -> Z-up)' if rotate else 'no rotation (upAxis Z)'}"
            f" x uniform scale {scale:g} (metersPerUnit {meters_per_unit:g} x scale option {options.get('scale', 1.0):g})")
    return c, text


def gltf_conversion(up_axis: str, meters_per_unit: float) -> tuple[np.ndarray, str]:
    """USD world -> Blender world through a glTF file: glTF is +Y up and in metres (so an exporter maps a
    Z-up stage by Rx(-90) and scales by metersPerUnit), and Blender's glTF importer turns +Y up into +Z up
    by Rx(+90)."""
    to_gltf = (rot_x(-90.0) if up_axis == "Z" else np.eye(4)) @ np.diag([meters_per_unit] * 3 + [1.0])
    return rot_x(90.0) @ to_gltf, f"glTF Y-up metres (x{meters_per_unit:g}) then Blender's Rx(+90 deg)"


def strip_suffix(name: str) -> str:
    head, dot, tail = name.rpartition(".")
    return head if dot and tail.isdigit() and len(tail) == 3 else name


def match_meshes(view: BlenderView, ref: Reference) -> tuple[dict[str, tuple[int, dict]], dict[str, str]]:
    """USD mesh path -> Blender mesh object, by vertex count and identical rest points (which also shows
    the vertex order is USD's), names breaking ties. Second result: path -> why it did not match."""
    objects = view.mesh_objects()
    mapping: dict[str, tuple[int, dict]] = {}
    problems: dict[str, str] = {}
    used: set[int] = set()
    for path, mesh in ref.meshes.items():
        name = path.rsplit("/", 1)[-1]
        short_name = truncated(name)
        named = [(i, o) for i, o in objects if short_name in (strip_suffix(o["data"] or ""), strip_suffix(o["name"]))]
        same = []
        for i, o in objects:
            rest = view.arrays[f"rest_{i}"]
            if i not in used and rest.shape == mesh.points.shape and np.abs(rest - mesh.points).max() <= 1e-6 * mesh.diag:
                same.append((i, o))
        pick = [c for c in same if c in named] or same
        if len(pick) >= 1:
            mapping[path] = pick[0]
            used.add(pick[0][0])
            if len(pick) > 1:
                problems[path] = f"ambiguous: {[o['name'] for _, o in pick]} (took {pick[0][1]['name']})"
        elif named:
            i, o = named[0]
            problems[path] = (f"Blender object {o['name']!r} has {o['vertices']} vertices, USD {len(mesh.points)}; "
                              "vertices split or reordered" if o["vertices"] != len(mesh.points)
                              else f"Blender object {o['name']!r}: same count, different rest points (reordered?)")
        else:
            problems[path] = "no Blender mesh object"
    return mapping, problems


def conversion_evidence(view: BlenderView, ref: Reference, c: np.ndarray) -> dict[str, float]:
    """Root prims imported as parentless objects of the same name: |Blender matrix_world - C @ USD world|."""
    out = {}
    for i, o in enumerate(view.meta["objects"]):
        if len(o["parents"]) == 1 and o["name"] in ref.roots:
            out[o["name"]] = float(np.abs(view.arrays[f"matrix_{i}"][0] - c @ ref.roots[o["name"]]).max())
    return out


# --- comparison ---------------------------------------------------------------------------------

@dataclass
class MeshResult:
    case: str
    path: str
    vertices: int
    diag: float
    order: str = ""
    plain: float = math.nan
    corrected: float = math.nan
    correction: float = math.nan  # max |U_corr - U_plain| / diag: how much the correctives move
    delta: float = math.nan  # max |(B_corr - B_plain) - (U_corr - U_plain)| / diag
    passed: bool = False
    channels: list[str] = field(default_factory=list)
    names: dict = field(default_factory=dict)
    weights: dict = field(default_factory=dict)
    per_frame: list[dict] = field(default_factory=list)
    layout: dict = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    inspect_warned: bool = False  # psdbake inspect ASSET warned that Blender misplaces this mesh


def blender_world_in_usd(view: BlenderView, index: int, c: np.ndarray) -> np.ndarray:
    return apply(np.linalg.inv(c), view.arrays[f"world_{index}"])


def relative_error(a: np.ndarray, b: np.ndarray, diag: float) -> float:
    if a.shape != b.shape:
        return math.inf
    return float(np.linalg.norm(a - b, axis=-1).max() / diag)


def truncated(name: str) -> str:
    raw = name.encode("utf-8")[:BLENDER_NAME_BYTES]
    return raw.decode("utf-8", "ignore")


def pair_keys(channels: list[str], obj: dict) -> dict[str, str | None]:
    """channel -> the Blender shape key made for it. Blender adds one key per channel, in channel order,
    after the reference key; when the counts agree they pair by position (so a truncated or .001-suffixed
    name still finds its key), otherwise by exact name."""
    keys = [k["name"] for k in obj.get("shape_keys", []) if k["name"] != obj.get("reference_key")]
    if len(keys) == len(channels):
        return dict(zip(channels, keys, strict=True))
    return {c: (c if c in keys else None) for c in channels}


def shape_key_check(channels: list[str], obj: dict) -> dict:
    """Each channel as a shape key of its own name? (Blender names keys from the skel:blendShapes tokens.)"""
    keys = [k["name"] for k in obj.get("shape_keys", []) if k["name"] != obj.get("reference_key")]
    pairs = pair_keys(channels, obj)
    renamed = {c: k for c, k in pairs.items() if k != c}
    curves = set(obj.get("curves", []))
    return {
        "channels": len(channels), "keys": len(keys), "exact": sum(1 for c, k in pairs.items() if k == c),
        "renamed": renamed, "extra": [k for k in keys if k not in pairs.values()],
        "longest_bytes": max((len(c.encode("utf-8")) for c in channels), default=0),
        "keys_without_curve": [k for k in keys if f'key_blocks["{k}"].value' not in curves],
        "ok": all(k == c for c, k in pairs.items()) and len(keys) == len(channels),
    }


def weight_check(mesh: MeshRef, view: BlenderView, index: int, obj: dict, frames: list[float],
                 rows: list[int] | None = None) -> tuple[dict, list[dict]]:
    """UsdSkel's weights against the values Blender applies (keys_i) at Blender frame rows (default: all)."""
    keys = [k["name"] for k in obj.get("shape_keys", [])]
    lo = {k["name"]: k["slider_min"] for k in obj.get("shape_keys", [])}
    hi = {k["name"]: k["slider_max"] for k in obj.get("shape_keys", [])}
    applied = view.arrays[f"keys_{index}"]
    if rows is not None:
        applied = applied[rows]
    if not mesh.channels:
        return {}, []
    pairs = pair_keys(mesh.channels, obj)
    usd_cols = [k for k, c in enumerate(mesh.channels) if pairs[c] is not None]
    names = [pairs[mesh.channels[k]] for k in usd_cols]
    cols = [keys.index(n) for n in names]
    usd = mesh.weights
    summary: dict = {"usd_min": float(usd.min()), "usd_max": float(usd.max()),
                     "matched": len(cols), "channels": len(mesh.channels)}
    per_frame = []
    if cols:
        b, u = applied[:, cols], usd[:, usd_cols]
        clamp_lo, clamp_hi = np.array([lo[n] for n in names]), np.array([hi[n] for n in names])
        outside = (u < clamp_lo - 1e-7) | (u > clamp_hi + 1e-7)
        summary.update({
            "blender_min": float(b.min()), "blender_max": float(b.max()), "max_abs_diff": float(np.abs(b - u).max()),
            "max_point_effect": float((np.abs(b - u).max(axis=0) * mesh.reach[usd_cols]).max())
            if len(mesh.reach) == len(mesh.channels) else math.inf,
            "clamped_samples": int(outside.sum()), "samples": int(outside.size),
            "slider_range": [float(clamp_lo.min()), float(clamp_hi.max())],
        })
        for fi, t in enumerate(frames):
            per_frame.append({"frame": t, "usd_min": float(usd[fi].min()), "usd_max": float(usd[fi].max()),
                              "blender_min": float(b[fi].min()), "blender_max": float(b[fi].max()),
                              "max_abs_diff": float(np.abs(b[fi] - u[fi]).max()), "clamped": int(outside[fi].sum())})
    return summary, per_frame


@dataclass
class CaseResult:
    case: Case
    meshes: list[MeshResult] = field(default_factory=list)
    conversion: str = ""
    conversion_evidence: dict = field(default_factory=dict)
    frames: list[float] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    commands: list[str] = field(default_factory=list)
    error: str = ""
    gltf: dict = field(default_factory=dict)
    live: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        return (not self.error and bool(self.meshes) and all(m.passed for m in self.meshes)
                and (not self.gltf or bool(self.gltf.get("passed"))) and bool(self.live.get("passed")))


def compare_case(case: Case, tmp: str, gltf: bool) -> CaseResult:
    result = CaseResult(case)
    folder = os.path.join(tmp, case.name)
    try:
        start = time.perf_counter()
        stacks = build(case, folder)
        result.commands = stacks.commands
        result.seconds["psdbake"] = time.perf_counter() - start
        frames = animation_frames(stacks.corrected)
        result.frames = frames
        warned = inspect_warnings(case.asset)
        start = time.perf_counter()
        ref_plain, ref_corr = bake(stacks.plain, frames), bake(stacks.corrected, frames)
        result.seconds["bake"] = time.perf_counter() - start
        view_plain = blender_points(stacks.plain, frames, os.path.join(folder, "blender_plain.npz"))
        view_corr = blender_points(stacks.corrected, frames, os.path.join(folder, "blender_corrected.npz"))
        result.seconds["blender"] = view_plain.seconds + view_corr.seconds
        c, result.conversion = usd_import_conversion(ref_corr.up_axis, ref_corr.meters_per_unit, view_corr.meta["options"])
        result.conversion_evidence = conversion_evidence(view_corr, ref_corr, c)
        map_plain, problems_plain = match_meshes(view_plain, ref_plain)
        map_corr, problems_corr = match_meshes(view_corr, ref_corr)
        for path, mesh in ref_corr.meshes.items():
            r = MeshResult(case.name, path, len(mesh.points), mesh.diag, channels=mesh.channels, layout=mesh.layout)
            result.meshes.append(r)
            for label, problems in (("plain", problems_plain), ("corrected", problems_corr)):
                if path in problems:
                    r.problems.append(f"{label}: {problems[path]}")
            if path not in map_plain or path not in map_corr or path not in ref_plain.meshes:
                r.order = "unmapped"
                continue
            r.order = "preserved"
            (ip, _), (ic, obj) = map_plain[path], map_corr[path]
            u_plain, u_corr = ref_plain.meshes[path].world, ref_corr.meshes[path].world
            b_plain, b_corr = blender_world_in_usd(view_plain, ip, c), blender_world_in_usd(view_corr, ic, c)
            r.plain = relative_error(b_plain, u_plain, mesh.diag)
            r.corrected = relative_error(b_corr, u_corr, mesh.diag)
            r.correction = relative_error(u_corr, u_plain, mesh.diag)
            if b_plain.shape == b_corr.shape == u_plain.shape:
                r.delta = float(np.linalg.norm((b_corr - b_plain) - (u_corr - u_plain), axis=-1).max() / mesh.diag)
            # psdbake inspect must predict Blender's placement: a warning exactly where the plain stack is off
            r.inspect_warned = path in warned
            r.passed = r.corrected <= r.plain + CRITERION and r.inspect_warned == (r.plain > PLAIN_MISMATCH)
            if r.inspect_warned != (r.plain > PLAIN_MISMATCH):
                r.problems.append(f"psdbake inspect {'warned' if r.inspect_warned else 'did not warn'} but the plain "
                                  f"stack is {'within' if r.plain <= PLAIN_MISMATCH else 'off by'} {fmt(r.plain)}")
            r.names = shape_key_check(mesh.channels, obj)
            r.weights, r.per_frame = weight_check(mesh, view_corr, ic, obj, frames)
        if gltf:
            start = time.perf_counter()
            result.gltf = gltf_case(case, stacks, ref_corr, folder)
            result.seconds["gltf (export + Blender)"] = time.perf_counter() - start
        start = time.perf_counter()
        result.live = live_case(case, stacks, ref_corr, {m.path: m.plain for m in result.meshes}, frames, folder)
        result.seconds["live rig (export + Blender + speed)"] = time.perf_counter() - start
    except HarnessError as exc:
        result.error = str(exc)
    return result


# --- the live rig -------------------------------------------------------------------------------

def live_case(case: Case, stacks: Stacks, ref: Reference, plain: dict[str, float], frames: list[float],
              folder: str) -> dict:
    """``psdbake export-blender`` with the shot, opened with Python auto-run off and played: the
    drivers' weights against eval's, the mesh against the corrected stack's BakeSkinning (the
    criterion of the stacks: corrected <= plain + 1e-6), then the per-frame cost."""
    blend = os.path.join(folder, "live.blend")
    log: list[str] = []
    psdbake(log, "export-blender", case.asset, stacks.correctives, "--anim", stacks.anim, "-o", blend,
            "--blender", blender_python())
    view = blender_points(blend, frames, os.path.join(folder, "blender_live.npz"), importer="blend")
    c, _ = usd_import_conversion(ref.up_axis, ref.meters_per_unit, {"scale": 1.0, "apply_unit_conversion_scale": True})
    facts = view.meta["drivers"]
    mapping, problems = match_meshes(view, ref)
    report: dict = {"commands": log, "drivers": facts, "meshes": {}, "file": blend,
                    "auto_run": view.meta["options"]}
    passed = (facts["drivers"] > 0 and facts["simple"] == facts["valid"] == facts["drivers"]
              and not facts["autoexec_fail"] and not view.meta["options"]["use_scripts_auto_execute"])
    for path, mesh in ref.meshes.items():
        if path not in mapping:
            report["meshes"][path] = {"error": math.inf, "passed": False, "problem": problems.get(path, "unmapped")}
            passed = False
            continue
        i, obj = mapping[path]
        assert mesh.world is not None
        error = relative_error(blender_world_in_usd(view, i, c), mesh.world, mesh.diag)
        weights, _ = weight_check(mesh, view, i, obj, frames)
        dw = weights.get("max_abs_diff", 0.0) if mesh.channels else 0.0
        effect = weights.get("max_point_effect", 0.0) if mesh.channels else 0.0
        ok = (error <= plain.get(path, math.inf) + CRITERION and effect <= LIVE_POINT_ATOL
              and weights.get("matched", 0) == len(mesh.channels))
        report["meshes"][path] = {"error": error, "plain": plain.get(path, math.nan), "max_abs_dw": dw,
                                  "max_point_effect": effect,
                                  "channels": len(mesh.channels), "matched": weights.get("matched", 0),
                                  "clamped_samples": weights.get("clamped_samples", 0), "passed": ok}
        passed = passed and ok
    report["constraints"] = blender_json(CONSTRAINTS_SCRIPT, [blend], os.path.join(folder, "constraints.json"), case)
    passed = (passed and report["constraints"]["max_abs_dw"] <= LIVE_WEIGHT_ATOL
              and report["constraints"]["max_value"] > LIVE_WEIGHT_ATOL)
    report["speed"] = speed(case, stacks, blend, frames, folder)
    report["passed"] = passed
    return report


def blender_json(script: str, args: list[str], out: str, case: Case) -> dict:
    """Run an interop script in the bpy venv; the JSON it wrote to ``out``."""
    proc = subprocess.run([blender_python(), script, *args, "-o", out], capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0 or not os.path.exists(out):
        raise HarnessError(f"{os.path.basename(script)} failed (exit {proc.returncode}) on {case.name}:\n"
                           f"{proc.stderr[-2000:]}")
    with open(out, encoding="utf-8") as fh:
        return json.load(fh)


def speed(case: Case, stacks: Stacks, blend: str, frames: list[float], folder: str) -> dict:
    """blender_speed.py on the plain stack, the baked corrected stack and the live rig."""
    return blender_json(SPEED_SCRIPT, ["--frames", ",".join(f"{f:g}" for f in frames), "--rounds", str(SPEED_ROUNDS),
                                       f"plain={stacks.plain}", f"baked={stacks.corrected}", f"live={blend}"],
                        os.path.join(folder, "speed.json"), case)


# --- glTF ---------------------------------------------------------------------------------------

def gltf_start_seconds(glb: str) -> float:
    """The earliest key time (seconds) of any animation in a .glb (the samplers' input accessors' min)."""
    with open(glb, "rb") as fh:
        data = fh.read()
    if data[:4] != b"glTF":
        raise HarnessError(f"{glb} is not a glTF binary")
    length = int.from_bytes(data[12:16], "little")
    if data[16:20] != b"JSON":
        raise HarnessError(f"{glb}: first chunk is not JSON")
    doc = json.loads(data[20:20 + length])
    starts = [doc["accessors"][s["input"]]["min"][0] for a in doc.get("animations", []) for s in a["samplers"]]
    return min(starts) if starts else 0.0


def check_gltf(glb: str, ref: Reference, out: str, *, criterion: float = GLTF_CRITERION,
               conversion: Callable[[str, float], tuple[np.ndarray, str]] = gltf_conversion) -> dict:
    """Import glb with Blender's default glTF importer and compare each mesh's world points per frame with
    ref (a BakeSkinning Reference: frames -> world points per USD mesh path).

    Time: glTF keys are seconds and Blender's importer puts second t at frame t * fps. USD frame f is
    paired with glTF time t0 + (f - f0) / timeCodesPerSecond (t0: the file's first key, f0: the first
    reference frame), i.e. Blender frame (t0 + (f - f0) / tcps) * fps: the criterion. The error when
    pairing by frame number (Blender frame f against USD frame f) is reported too (``by_frame_number``).
    Meshes are matched by name (the exporter names mesh nodes after the USD prims), then by vertex count.
    Vertex order: when the counts agree the order is taken as USD's (the error shows if it is not);
    when they differ (vertices split) each Blender vertex is paired with the nearest reference vertex
    at the first frame and the result says so (a weaker check)."""
    from scipy.spatial import cKDTree

    t0 = gltf_start_seconds(glb)
    fps = BLENDER_FACTORY_FPS
    by_time = [round((t0 + (f - ref.frames[0]) / ref.tcps) * fps, 6) for f in ref.frames]
    frames = sorted(set(by_time) | set(ref.frames))
    view = blender_points(glb, frames, out, importer="gltf")
    scene_fps = view.meta["scene"]["fps"] / view.meta["scene"]["fps_base"]
    if scene_fps != fps:
        raise HarnessError(f"Blender scene fps {scene_fps:g}, expected {fps:g} (factory settings)")
    rows_time = [frames.index(f) for f in by_time]
    rows_number = [frames.index(f) for f in ref.frames]
    c, text = conversion(ref.up_axis, ref.meters_per_unit)
    objects = view.mesh_objects()
    report: dict = {"file": glb, "conversion": text, "criterion": criterion, "meshes": {}, "seconds": view.seconds,
                    "time_mapping": f"USD frame f -> glTF {t0:g} s + (f - {ref.frames[0]:g}) / {ref.tcps:g} -> "
                                    f"Blender frame t * {fps:g} (USD frame {ref.frames[0]:g} at Blender frame {by_time[0]:g})"}
    passed = bool(ref.meshes)
    for path, mesh in ref.meshes.items():
        name = path.rsplit("/", 1)[-1]
        cands = [(i, o) for i, o in objects if name in (strip_suffix(o["name"]), strip_suffix(o["data"] or ""))]
        cands = cands or [(i, o) for i, o in objects if o["vertices"] == len(mesh.points)]
        if not cands:
            report["meshes"][path] = {"error": math.inf, "passed": False, "order": "no Blender mesh object"}
            passed = False
            continue
        i, obj = cands[0]
        blender = apply(np.linalg.inv(c), view.arrays[f"world_{i}"])
        target = mesh.world
        assert target is not None
        entry: dict = {"object": obj["name"], "vertices": int(blender.shape[1]), "usd_vertices": len(mesh.points)}
        if blender.shape[1] == target.shape[1]:
            entry["order"] = "same vertex count: USD order assumed"
        else:
            _, nearest = cKDTree(target[0]).query(blender[rows_time[0]])
            target = target[:, nearest]
            entry["order"] = (f"{blender.shape[1]} vs {len(mesh.points)} vertices: paired by nearest point at USD frame "
                              f"{ref.frames[0]:g}")
        entry["error"] = relative_error(blender[rows_time], target, mesh.diag)
        entry["by_frame_number"] = relative_error(blender[rows_number], target, mesh.diag)
        entry["names"] = shape_key_check(mesh.channels, obj)
        entry["weights"], _ = weight_check(mesh, view, i, obj, ref.frames, rows_time)
        # what an artist scrubbing frames sees: the glTF keys USD time code f at f / fps seconds,
        # so Blender frame f must match USD frame f (and does by time, too)
        entry["passed"] = max(entry["error"], entry["by_frame_number"]) <= criterion
        passed = passed and entry["passed"]
        report["meshes"][path] = entry
    report["passed"] = passed
    return report


def gltf_case(case: Case, stacks: Stacks, ref_corr: Reference, folder: str) -> dict:
    glb = os.path.join(folder, "shot.glb")
    log: list[str] = []
    psdbake(log, "export-gltf", case.asset, stacks.correctives, "--anim", stacks.anim, "-o", glb)
    report = check_gltf(glb, ref_corr, os.path.join(folder, "blender_gltf.npz"))
    report["commands"] = log
    report["validator"] = validate_gltf(glb)
    issues = report["validator"]
    report["passed"] = report["passed"] and issues["errors"] == 0 and issues["warnings"] == 0
    return report


def validate_gltf(glb: str) -> dict:
    """The Khronos glTF-Validator's counts for glb (tests/gltf, installed by make test's npm ci)."""
    proc = subprocess.run(["node", os.path.join(ROOT, "tests", "gltf", "validate.mjs"), glb], capture_output=True,
                          text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise HarnessError(f"glTF-Validator failed on {glb}: {proc.stderr.strip()[:300]}")
    issues = json.loads(proc.stdout)["issues"]
    return {k: int(issues[f"num{k.capitalize()}"]) for k in ("errors", "warnings", "infos", "hints")}


# --- report -------------------------------------------------------------------------------------

def fmt(x: float) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else ("inf" if math.isinf(x) else f"{x:.2e}")


def short(name: str, keep: int = 14) -> str:
    return name if len(name) <= 2 * keep + 1 else f"{name[:keep]}…{name[-keep:]}"


def names_cell(names: dict) -> str:
    if not names:
        return "n/a"
    if names["channels"] == 0:
        return "no channels"
    text = f"{names['exact']}/{names['channels']} exact"
    if names["renamed"]:
        c, k = next(iter(names["renamed"].items()))
        text += (f"; {len(names['renamed'])} renamed, e.g. `{short(c)}` ({len(c.encode())} B) → "
                 f"`{short(k) if k else 'none'}` ({len(k.encode()) if k else 0} B)")
    if names["extra"]:
        text += f"; extra keys {names['extra'][:3]}"
    if names["keys_without_curve"]:
        text += f"; {len(names['keys_without_curve'])}/{names['keys']} keys unanimated (weight curves name the full channel)"
    text += f"; longest channel {names['longest_bytes']} B"
    return ("✓ " if names["ok"] else "✗ ") + text


def report(results: list[CaseResult], gltf_available: bool, seconds: float) -> str:
    lines = ["# Blender 5.0 default USD import vs UsdSkel.BakeSkinning", ""]
    lines += ["error = max over frames and vertices of |Blender - BakeSkinning| / bind-pose bounding-box diagonal "
              "(USD world units, after undoing the importer's conversion); "
              f"criterion: corrected ≤ plain + {CRITERION:g}, and `psdbake inspect ASSET` warns exactly for the meshes "
              f"whose plain error exceeds {PLAIN_MISMATCH:g}. "
              "Δ-corrective = max |(Blender corrected - Blender plain) - (BakeSkinning corrected - BakeSkinning plain)| / diag; "
              "correctives = max |BakeSkinning corrected - BakeSkinning plain| / diag.", ""]
    lines += ["| case | mesh | verts (order) | frames | plain err | corrected err | correctives | Δ-corrective | "
              "inspect warns | criterion |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for res in results:
        if res.error:
            lines.append(f"| {res.case.name} | — | — | — | — | — | — | — | ERROR |")
            continue
        for m in res.meshes:
            verdict = ("PASS" if m.passed else "FAIL") + ("*" if m.plain > PLAIN_MISMATCH else "")
            lines.append(f"| {res.case.name} | `{m.path}` | {m.vertices} ({m.order}) | {len(res.frames)} | {fmt(m.plain)} | "
                         f"{fmt(m.corrected)} | {fmt(m.correction)} | {fmt(m.delta)} | "
                         f"{'yes' if m.inspect_warned else 'no'} | {verdict} |")
    if any(m.plain > PLAIN_MISMATCH for res in results for m in res.meshes):
        lines += ["", f"\\* plain error > {PLAIN_MISMATCH:g}: Blender misplaces this mesh even without correctives (see "
                  "Plain-stack placement), so the criterion cannot see the correctives; Δ-corrective shows how far Blender's "
                  "corrective motion is from UsdSkel's."]
    lines += ["", "Shape keys (corrected stack) and weights: USD = what UsdSkel applies; Blender = the shape-key value "
              "Blender applies (clamped to [slider_min, slider_max]).", ""]
    lines += ["| case | mesh | shape keys named as the channels | USD weights | Blender values | clamped samples | max abs Δw |",
              "|---|---|---|---|---|---|---|"]
    for res in results:
        for m in res.meshes:
            w = m.weights
            if not m.channels:
                lines.append(f"| {res.case.name} | `{m.path}` | no channels | — | — | — | — |")
                continue
            usd = f"[{w.get('usd_min', math.nan):.3f}, {w.get('usd_max', math.nan):.3f}]" if w else "n/a"
            bl = f"[{w['blender_min']:.3f}, {w['blender_max']:.3f}]" if "blender_min" in w else "no key matched"
            clamped = f"{w['clamped_samples']}/{w['samples']}" if "samples" in w else "n/a"
            lines.append(f"| {res.case.name} | `{m.path}` | {names_cell(m.names)} | {usd} | {bl} | {clamped} | "
                         f"{fmt(w.get('max_abs_diff', math.nan))} |")
    lines += ["", "## Conversion applied by Blender's USD importer", ""]
    for res in results:
        if res.conversion:
            ev = ", ".join(f"root `{k}` |matrix_world - C·USD| = {v:.1e}" for k, v in res.conversion_evidence.items())
            lines.append(f"- {res.case.name}: {res.conversion}; checked: {ev or 'no root object to check'}")
    lines += ["", f"## Plain-stack placement (plain error > {PLAIN_MISMATCH:g} of the diagonal)", ""]
    for res in results:
        for m in res.meshes:
            if m.layout and not math.isnan(m.plain):
                lay = m.layout
                flag = "MISMATCH" if m.plain > PLAIN_MISMATCH else "ok"
                lines.append(f"- {res.case.name} `{m.path}`: {flag} (plain {fmt(m.plain)}); parent `{lay['parent']}` world "
                             f"{'=' if lay['parent_world_equals_skeleton_world'] else '≠'} skeleton `{lay['skeleton']}` world; "
                             f"mesh xform {'identity' if lay['mesh_xform_identity'] else 'non-identity (ignored by UsdSkel)'}; "
                             f"geomBindTransform {'identity' if lay['geom_bind_identity'] else 'non-identity'}; "
                             f"bind-pose offset predicted by 'mesh matrix = geomBindTransform under its parent': "
                             f"{fmt(lay['predicted_bind_offset'])}")
    lines += ["", "## glTF", ""]
    if not gltf_available:
        lines.append("- skipped: `psdbake export-gltf --help` does not work yet; `check_gltf()` is ready "
                     f"(criterion {GLTF_CRITERION:g} against the corrected BakeSkinning reference).")
    for res in results:
        if res.gltf:
            v = res.gltf.get("validator", {})
            lines.append(f"- {res.case.name}: {res.gltf['time_mapping']}; {res.gltf['conversion']}; glTF-Validator: "
                         f"{v.get('errors')} errors, {v.get('warnings')} warnings, {v.get('infos')} infos")
            for path, e in res.gltf["meshes"].items():
                w = e.get("weights", {})
                verdict = "PASS" if e.get("passed") else "FAIL"
                lines.append(f"  - `{path}`: error {fmt(e.get('error', math.nan))} ({verdict} ≤ {GLTF_CRITERION:g}); "
                             f"paired by frame number instead: {fmt(e.get('by_frame_number', math.nan))}; "
                             f"{e.get('order', '')}; names {names_cell(e.get('names', {}))}; weights USD "
                             f"[{w.get('usd_min', math.nan):.3f}, {w.get('usd_max', math.nan):.3f}] Blender "
                             f"[{w.get('blender_min', math.nan):.3f}, {w.get('blender_max', math.nan):.3f}], max abs Δw "
                             f"{fmt(w.get('max_abs_diff', math.nan))}")
    lines += live_report(results)
    problems = [(res.case.name, m.path, p) for res in results for m in res.meshes for p in m.problems]
    errors = [(res.case.name, res.error) for res in results if res.error]
    if problems or errors:
        lines += ["", "## Problems", ""]
        lines += [f"- {case} `{path}`: {p}" for case, path, p in problems]
        lines += [f"- {case}: {err}" for case, err in errors]
    lines += ["", "## Timing (s)", ""]
    for res in results:
        lines.append(f"- {res.case.name}: " + ", ".join(f"{k} {v:.1f}" for k, v in res.seconds.items()))
    lines.append(f"- total {seconds:.1f}")
    return "\n".join(lines) + "\n"


def live_report(results: list[CaseResult]) -> list[str]:
    lines = ["", "## Live rig: psdbake export-blender, opened with Python auto-run off, posed at every frame", "",
             f"Criteria: every shape-key value close to eval's weight: |Δw| times the channel's largest offset within "
             f"{LIVE_POINT_ATOL:g} of the diagonal (max \\|Δw\\| and that effect); the evaluated "
             f"mesh within plain + {CRITERION:g} of the corrected stack's BakeSkinning (live err, as corrected err "
             "above); every driver a valid simple expression, no Python blocked; a driver bone turned by a Copy "
             f"Rotation constraint gives the weights of the same turn keyed on it within {LIVE_WEIGHT_ATOL:g} "
             "(constraint \\|Δw\\|: every driver bone, 3 turns each).", "",
             "| case | mesh | frames | channels | drivers (simple, valid) | max \\|Δw\\| | \\|Δw\\| x offset | plain err | "
             "live err | constraint \\|Δw\\| | criterion |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for res in results:
        live = res.live
        if not live:
            continue
        d = live["drivers"]
        for path, m in live["meshes"].items():
            lines.append(f"| {res.case.name} | `{path}` | {len(res.frames)} | {m.get('channels', '—')} | "
                         f"{d['drivers']} ({d['simple']}, {d['valid']}) | {fmt(m.get('max_abs_dw', math.nan))} | "
                         f"{fmt(m.get('max_point_effect', math.nan))} | "
                         f"{fmt(m.get('plain', math.nan))} | {fmt(m.get('error', math.nan))} | "
                         f"{fmt(live.get('constraints', {}).get('max_abs_dw', math.nan))} | "
                         f"{'PASS' if m.get('passed') and live.get('passed') else 'FAIL'} |")
    lines += ["", "Per-frame cost in Blender (`scene.frame_set`: animation, drivers, armature deform; median over "
              f"{SPEED_ROUNDS} interleaved rounds in one process, each playing the shot 3 times per variant):", "",
              "| case | vertices | plain rig | baked shot (shape keys keyed) | live rig | live / plain | live / baked |",
              "|---|---|---|---|---|---|---|"]
    for res in results:
        sp = res.live.get("speed") if res.live else None
        if not sp:
            continue
        v = sp["variants"]
        p, b, li = (v[k]["median"] for k in ("plain", "baked", "live"))
        lines.append(f"| {res.case.name} | {v['live']['vertices']} | {p * 1e3:.3f} ms | {b * 1e3:.3f} ms | {li * 1e3:.3f} ms | "
                     f"{li / p:.2f}x | {li / b:.2f}x |")
    return lines


def weights_report(results: list[CaseResult]) -> str:
    lines = ["# Shape-key values per frame: UsdSkel weights vs the values Blender applies", ""]
    for res in results:
        for m in res.meshes:
            if not m.per_frame:
                continue
            lines += [f"## {res.case.name} `{m.path}`", "",
                      "| frame | USD min | USD max | Blender min | Blender max | max abs Δ | clamped |",
                      "|---|---|---|---|---|---|---|"]
            lines += [f"| {p['frame']:g} | {p['usd_min']:.4f} | {p['usd_max']:.4f} | {p['blender_min']:.4f} | "
                      f"{p['blender_max']:.4f} | {p['max_abs_diff']:.2e} | {p['clamped']} |" for p in m.per_frame]
            lines.append("")
    return "\n".join(lines)


def to_json(results: list[CaseResult]) -> list[dict]:
    out = []
    for res in results:
        out.append({
            "case": res.case.name, "note": res.case.note, "passed": res.passed, "error": res.error,
            "frames": res.frames, "conversion": res.conversion, "conversion_evidence": res.conversion_evidence,
            "seconds": res.seconds, "commands": res.commands, "gltf": res.gltf, "live": res.live,
            "meshes": [{k: v for k, v in vars(m).items()} for m in res.meshes],
        })
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", help="subset of: humanoid humanoid_mirrored humanoid_shots arm character cesiumman "
                        "long_path")
    parser.add_argument("--out", default=os.path.join(ROOT, os.environ.get("OUT", "out"), "interop"),
                        help="folder for report.md, weights.md, results.json (default: out/interop)")
    parser.add_argument("--keep", help="build in this folder (kept) instead of a temporary one")
    args = parser.parse_args(argv)
    if not os.path.exists(blender_python()):
        print(f"interop: no bpy venv at {blender_python()} (run `make interop`)", file=sys.stderr)
        return 2
    start = time.perf_counter()
    gltf = has_export_gltf()
    with tempfile.TemporaryDirectory(prefix="psdbake-interop-") as tmp:
        work = os.path.abspath(args.keep) if args.keep else tmp
        os.makedirs(work, exist_ok=True)
        try:
            cases = make_cases(work, args.cases)
        except (HarnessError, RuntimeError) as exc:
            print(f"interop: could not make the cases: {exc}", file=sys.stderr)
            return 2
        results = []
        for case in cases:
            res = compare_case(case, work, gltf)
            status = "ERROR" if res.error else ("pass" if res.passed else "FAIL")
            print(f"interop: {case.name}: {status} ({sum(res.seconds.values()):.1f} s)", file=sys.stderr, flush=True)
            results.append(res)
    text = report(results, gltf, time.perf_counter() - start)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "report.md"), "w", encoding="utf-8") as fh:
        fh.write(text)
    with open(os.path.join(args.out, "weights.md"), "w", encoding="utf-8") as fh:
        fh.write(weights_report(results))
    with open(os.path.join(args.out, "results.json"), "w", encoding="utf-8") as fh:
        json.dump(to_json(results), fh, indent=1, default=float)
    print(text)
    print(f"Per-frame weights: {os.path.relpath(os.path.join(args.out, 'weights.md'), ROOT)}; "
          f"all numbers: {os.path.relpath(os.path.join(args.out, 'results.json'), ROOT)}")
    if any(res.error for res in results):
        return 2
    if not all(res.passed for res in results):
        return 1
    gltf_fail = [res.case.name for res in results if res.gltf and not res.gltf.get("passed")]
    return 1 if gltf_fail else 0


if __name__ == "__main__":
    sys.exit(main())
