"""``psdbake export-blender``: a .blend whose correctives follow the armature live.

USD in (ASSET + CORRECTIVES [+ ANIM], read and validated as ``eval`` reads them), the
``psd:`` groups of every corrected mesh compiled into a driver graph (``compiler``), and a
plan handed to Blender, which runs the script psdbake ships (``rig_script.py``): Blender's own
USD importer brings the character in, the script adds the drivers and saves. The .blend is
written beside OUTPUT and renamed over it once Blender has saved it whole (``atomic``).

Why a command and not a Blender add-on: the rig is built where the correctives are fitted
(a pipeline step, headless, on the farm alike), from the same validated reading of the
``psd:`` data as ``eval``, and what animators open needs nothing installed: the drivers are
plain Blender data. An add-on would have to ship psdbake's reader and compiler into every
animator's Blender for a step they never run.

Blender: ``blender`` (an executable, run ``--background --factory-startup``) or a Python
interpreter that imports ``bpy`` (PyPI's bpy module, as ``make interop`` uses), told apart by
what ``--version`` prints.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ... import __version__, atomic
from ...errors import InputError, PsdError, SettingError, where
from ...model.posespace import rotations
from ...outputs import BLEND
from ...usd import provenance
from ...usd import write as usdwrite
from ...usd.bindspace import read_bind_space
from ...usd.read import Scene
from ...usd.validate import checked_driver_groups, validate_animation
from .compiler import compile_mesh
from .graph import BoneChannel, DriverGraph

#: The script Blender runs (shipped in the package, beside this module).
RIG_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "rig_script.py")
#: Blender's USD importer options: its defaults plus a rigger's ticks for a skinned character
#: (interop/blender_points.py imports with the same).
IMPORT_OPTIONS = {"import_skeletons": True, "import_blendshapes": True}
#: Where to look for Blender when ``--blender`` is not given.
BLENDER_ENV = "PSDBAKE_BLENDER"


@dataclass(frozen=True)
class Blender:
    """How to run Blender: ``argv`` before the script, and whether it is an executable
    (``blender``) or a Python with the bpy module."""

    path: str
    kind: str  # "blender" or "bpy"
    version: str

    def command(self, plan: str) -> list[str]:
        if self.kind == "blender":
            return [self.path, "--background", "--factory-startup", "--python-exit-code", "1", "--python", RIG_SCRIPT,
                    "--", plan]
        return [self.path, RIG_SCRIPT, plan]


def find_blender(path: str | None = None) -> Blender:
    """``path``, else ``$PSDBAKE_BLENDER``, else ``blender`` on PATH: checked by running it
    with ``--version`` (Blender prints ``Blender 5.0.1``, Python ``Python 3.11.x``)."""
    given = path or os.environ.get(BLENDER_ENV) or shutil.which("blender")
    if not given:
        raise SettingError("blender", None, f"no Blender found: pass --blender PATH (a Blender executable, or a Python "
                                            f"with the bpy module) or set {BLENDER_ENV}")
    try:
        proc = subprocess.run([given, "--version"], capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SettingError("blender", given, f"cannot be run ({exc})") from None
    text = (proc.stdout + proc.stderr).strip()
    first = text.splitlines()[0] if text else ""
    if proc.returncode == 0 and first.startswith("Blender "):
        return Blender(given, "blender", first.split()[1])
    if proc.returncode == 0 and first.startswith("Python "):
        if not _has_bpy(given):
            raise SettingError("blender", given, f"is {first[:40]} without the bpy module (pip install bpy into it, or "
                                                 "pass a Blender executable)")
        return Blender(given, "bpy", first)
    raise SettingError("blender", given, f"is neither Blender nor Python (--version says {first[:60]!r})")


def _has_bpy(python: str) -> bool:
    """Whether that Python can import bpy, asked without importing it (a second, not ten)."""
    try:
        proc = subprocess.run([python, "-c", "import importlib.util, sys; sys.exit(importlib.util.find_spec('bpy') is None)"],
                              capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


@dataclass(frozen=True)
class MeshRig:
    """One corrected mesh in the .blend: its drivers and what Blender made of them."""

    path: str  # USD prim
    groups: tuple[str, ...]
    graph: DriverGraph
    object: str = ""  # Blender object
    armature: str = ""

    @property
    def channels(self) -> int:
        return len(self.graph.channels)

    @property
    def nodes(self) -> int:
        return len(self.graph.nodes)


@dataclass(frozen=True)
class BlenderRigResult:
    """What ``export_blender`` wrote."""

    output: str
    meshes: tuple[MeshRig, ...]
    blender: str  # version as Blender reports it
    anim: str | None
    seconds: float

    @property
    def drivers(self) -> int:
        return sum(len(m.graph.drivers) for m in self.meshes)


def compile_rig(asset: str, correctives: str) -> tuple[list[MeshRig], list[dict]]:
    """Every corrected mesh's driver graph and its entry of Blender's plan (joints, bind
    transforms as column-vector matrices, drivers)."""
    scene = Scene([correctives, asset], label=correctives)
    scene.require_skinned()
    rigs, entries = [], []
    for info in scene.skinned_meshes():
        groups = checked_driver_groups(scene, info)
        if not groups:
            continue
        space = read_bind_space(scene, info)
        rest_rotations = rotations(space.bind_local).as_quat()
        rest = {j: rest_rotations[i] for i, j in enumerate(info.joints)}
        graph = compile_mesh(groups, rest)
        bind = np.swapaxes(space.bind_world, -1, -2)  # column vectors, as Blender's matrices
        heads = bind[:, :3, 3]
        rigs.append(MeshRig(info.path, tuple(g for g, _ in groups), graph))
        entries.append({
            "path": info.path, "points": info.point_count, "skeleton": info.skeleton, "joints": list(info.joints),
            "bind": bind.tolist(), "extent": float(np.linalg.norm(heads.max(axis=0) - heads.min(axis=0))) or 1.0,
            "channels": [d.target for d in graph.channels],
            "drivers": [{"kind": d.kind, "target": d.target, "expression": d.expression,
                         "variables": [[v, *(("bone", s.joint, s.channel) if isinstance(s, BoneChannel) else ("prop", s.name))]
                                       for v, s in d.variables]} for d in graph.drivers],
        })
    if not rigs:
        raise InputError(f"{correctives}: no psd: driver data on any skinned mesh of {asset}")
    return rigs, entries


def export_blender(asset: str, correctives: str, output: str, *, anim: str | None = None, blender: str | None = None,
                   inputs: Sequence[str] = ()) -> BlenderRigResult:
    """Write OUTPUT.blend: the character as Blender's USD importer brings in ASSET +
    CORRECTIVES (+ ANIM, the shot as the armature's action), each corrective channel a shape
    key whose value a driver computes from the armature's pose by the ``psd:`` formula, in
    simple expressions only (no Python runs in the file). ``inputs``: every file read, which
    OUTPUT may not be (``api.files_read``)."""
    started = time.perf_counter()
    atomic.check_output(output, inputs, kind=BLEND)
    runner = find_blender(blender)
    rigs, entries = compile_rig(asset, correctives)
    if anim:
        scene = Scene([anim, correctives, asset], label=anim)
        for rig in rigs:
            validate_animation(scene, rig.path)
    layers = [asset, correctives, *([anim] if anim else [])]
    with tempfile.TemporaryDirectory(prefix="psdbake-blender-") as tmp, \
            atomic.replacing(output, inputs, kind=BLEND) as target:
        stack = os.path.join(tmp, "stack.usda")
        usdwrite.export_atomic(provenance.stamp(usdwrite.stack_layer(stack, layers), "stack"), stack,
                               usdwrite.files_read(layers))
        os.remove(target)  # Blender writes the file itself (beside, then renamed onto this name)
        report_path, plan_path = os.path.join(tmp, "report.json"), os.path.join(tmp, "plan.json")
        plan = {"stack": stack, "output": target, "report": report_path, "import_options": IMPORT_OPTIONS,
                "meshes": entries, "made_by": f"psdbake {__version__} export-blender"}
        with open(plan_path, "w", encoding="utf-8") as fh:
            json.dump(plan, fh)
        report = _run(runner, plan_path, report_path, output)
        if not os.path.isfile(target):
            raise PsdError(f"{output}: Blender ({runner.path}) reported success but wrote no file")
    made = {m["path"]: m for m in report["meshes"]}
    meshes = tuple(MeshRig(r.path, r.groups, r.graph, made[r.path]["object"], made[r.path]["armature"]) for r in rigs)
    return BlenderRigResult(output, meshes, report.get("blender", runner.version), anim, time.perf_counter() - started)


def _run(runner: Blender, plan: str, report_path: str, output: str) -> dict:
    """Run Blender on the plan; its report, or the error it reported, as a psdbake error."""
    proc = subprocess.run(runner.command(plan), capture_output=True, text=True)
    report: dict = {}
    if os.path.isfile(report_path):
        with open(report_path, encoding="utf-8") as fh:
            report = json.load(fh)
    if "error" in report:
        cls = InputError if proc.returncode == 3 else PsdError
        raise cls(f"{where(output)}: Blender ({runner.path}): {report['error']}")
    if proc.returncode != 0 or "meshes" not in report:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise PsdError(f"{output}: Blender ({runner.path}) failed (exit {proc.returncode}): {tail[0][:300]}")
    return report

