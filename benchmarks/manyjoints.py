"""A big skeleton with a small sculpt: fit and eval scale with the sculpt, not the skeleton.

The rig (``build``): ``JOINTS`` joints (a spine of ``SPINE`` joints, then chains of
``CHAIN`` joints hanging from it, the way facial and secondary joints hang from a head), and a
mesh with ``POINTS_PER_JOINT`` points around each joint, each point skinned to its own joint and
its parent (weights 0.7 / 0.3). ``EXAMPLES`` examples each rotate **every** joint (5 to 20
degrees about a random axis, seeded); their sculpts move ``SCULPTED`` points near one chain's
tip, a bulge of 0.5 cm that grows with that chain's bend (Pixar's ``BakeSkinning`` of rest +
offsets: the ground truth, as every fixture's).

Measured in a fresh process each (``child``): ``psdbake.api.fit`` with default settings, then
``psdbake.api.evaluate`` of the result over the examples' own poses; seconds of each and the
process's peak resident memory (``VmHWM``), and the groups the fit made (drivers, points moved).
``--global-joints N`` also measures one global group (``FitSettings(group="main")``: every joint an
example moves becomes a driver of one RBF, what a default fit made before per-joint terms) at N
joints; ``make bench`` runs it at the same 1,200.

Run: ``python -m benchmarks.manyjoints`` (part of ``make bench``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt
from scipy.spatial.transform import Rotation

from . import processes, results

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "fixtures"))

import generate as gen  # noqa: E402

JOINTS = 1200
SPINE = 10
CHAIN = 10
POINTS_PER_JOINT = 8
EXAMPLES = 8
SCULPTED = 12
SKEL_ROOT, GEO, SKEL, ANIM, MESH = "/Rig", "/Rig/Geo", "/Rig/Skel", "/Rig/Skel/Anim", "/Rig/Geo/Body"


def topology(count: int) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(joint paths, parent indices, bind positions): a spine along +y, then chains of CHAIN
    joints along +x from each spine joint in turn, each chain 1 cm above the last."""
    names: list[str] = []
    parents: list[int] = []
    positions: list[tuple[float, float, float]] = []
    for s in range(min(SPINE, count)):
        names.append("Spine" if s == 0 else f"{names[-1]}/S{s}")
        parents.append(s - 1)
        positions.append((0.0, 10.0 * s, 0.0))
    chain = 0
    while len(names) < count:
        anchor = chain % SPINE
        for c in range(min(CHAIN, count - len(names))):
            parent = anchor if c == 0 else len(names) - 1
            names.append(f"{names[parent]}/C{chain}_{c}")
            parents.append(parent)
            positions.append((2.0 * (c + 1), 10.0 * anchor + 0.1 * (chain // SPINE), 0.0))
        chain += 1
    return names, np.array(parents), np.array(positions, dtype=np.float64)


def _local(parents: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Rest translations relative to each parent (joints are unrotated at rest)."""
    return np.array([world[j] - (world[p] if p >= 0 else 0.0) for j, p in enumerate(parents)])


def build(folder: str, count: int = JOINTS, seed: int = 0) -> tuple[str, str, list[int]]:
    """(ASSET, EXAMPLES, the sculpted point indices) written into folder."""
    names, parents, world = topology(count)
    rng = np.random.default_rng(seed)
    asset = os.path.join(folder, f"rig_{count}.usda")
    stage, skel = gen.new_character_stage(asset, SKEL_ROOT, GEO, SKEL, names)
    skel.CreateBindTransformsAttr([Gf.Matrix4d().SetTranslate(Gf.Vec3d(*p)) for p in world])
    skel.CreateRestTransformsAttr([Gf.Matrix4d().SetTranslate(Gf.Vec3d(*p)) for p in _local(parents, world)])
    ring = np.array([[0.3 * np.cos(a), 0.3 * np.sin(a), 0.3 * ((k % 2) - 0.5)]
                     for k, a in enumerate(np.linspace(0, 2 * np.pi, POINTS_PER_JOINT, endpoint=False))])
    points = (world[:, None, :] + ring[None]).reshape(-1, 3)
    owner = np.repeat(np.arange(count), POINTS_PER_JOINT)
    mesh = UsdGeom.Mesh.Define(stage, MESH)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    tris = np.arange(len(points) - len(points) % 3).reshape(-1, 3)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(tris)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.reshape(-1).astype(np.int32)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([SKEL])
    second = np.where(parents[owner] >= 0, parents[owner], owner)
    binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray.FromNumpy(np.stack([owner, second], 1).reshape(-1)
                                                                          .astype(np.int32)))
    weights = np.where(parents[owner] >= 0, 0.3, 0.0)
    binding.CreateJointWeightsPrimvar(False, 2).Set(Vt.FloatArray.FromNumpy(
        np.stack([1.0 - weights, weights], 1).reshape(-1).astype(np.float32)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    UsdSkel.BindingAPI.Apply(stage.GetPrimAtPath(SKEL_ROOT))
    stage.GetRootLayer().Save()

    # the examples: every joint turned, each by its own angle
    times = [float(t) for t in range(1, EXAMPLES + 1)]
    axes = rng.normal(size=(EXAMPLES, count, 3))
    axes /= np.linalg.norm(axes, axis=2, keepdims=True)
    angles = np.radians(rng.uniform(5.0, 20.0, size=(EXAMPLES, count, 1)))
    quats = Rotation.from_rotvec((axes * angles).reshape(-1, 3)).as_quat().reshape(EXAMPLES, count, 4)
    poses_path = os.path.join(folder, f"poses_{count}.usda")
    if os.path.exists(poses_path):
        os.remove(poses_path)
    layer = Sdf.Layer.CreateNew(poses_path)
    pstage = Usd.Stage.Open(layer)
    anim = UsdSkel.Animation.Define(pstage, ANIM)
    anim.CreateJointsAttr(names)
    anim.CreateTranslationsAttr(Vt.Vec3fArray.FromNumpy(_local(parents, world).astype(np.float32)))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * count))
    rot = anim.CreateRotationsAttr()
    for k, t in enumerate(times):
        rot.Set(Vt.QuatfArray([Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])) for q in quats[k]]), t)
    UsdSkel.BindingAPI.Apply(pstage.OverridePrim(SKEL)).CreateAnimationSourceRel().SetTargets([ANIM])
    layer.Save()

    # the sculpt: SCULPTED points at the tip of the first chain, growing with its tip's bend
    tip = SPINE + CHAIN - 1
    sculpted = [int(i) for i in np.arange(tip * POINTS_PER_JOINT - SCULPTED + POINTS_PER_JOINT,
                                          (tip + 1) * POINTS_PER_JOINT)]
    bend = {t: float(angles[k, tip, 0]) for k, t in enumerate(times)}

    def offsets(t: float) -> np.ndarray:
        out = np.zeros_like(points)
        out[sculpted, 1] = 0.5 * np.sin(3.0 * bend[t])
        return out

    sculpts = gen.bake_mesh_sculpts([poses_path, asset], times, {MESH: offsets})
    examples = gen.write_mesh_examples(os.path.join(folder, f"examples_{count}.usda"), poses_path, sculpts)
    return asset, examples, sculpted


def child(asset: str, examples: str, folder: str, group: str) -> None:
    """One fit and one eval in this process (group "": the default fit): prints a JSON line."""
    from psdbake import api
    from psdbake.settings import FitSettings

    out: dict = {"start_mib": processes.peak_rss_mib()}
    t0 = time.perf_counter()
    result = api.fit(asset, [examples], FitSettings(group=group or None))
    out["fit_seconds"] = time.perf_counter() - t0
    path = os.path.join(folder, f"correctives_{group or 'default'}.usda")
    api.write_correctives(result, path)
    t0 = time.perf_counter()
    weights = api.evaluate(asset, path, examples)
    out["eval_seconds"] = time.perf_counter() - t0
    out["eval_frames"] = len(weights.animations[0].times)
    out["peak_mib"] = processes.peak_rss_mib()
    out["roundtrip_max"] = max(c.error for c in result.checks)
    out["groups"] = [{"group": m.group, "drivers": len(m.drivers), "points": m.vertices, "role": m.role}
                     for m in result.meshes]
    print(json.dumps(out))


def measure(asset: str, examples: str, folder: str, group: str | None = None) -> dict:
    return processes.in_child("manyjoints", [asset, examples, folder, group or ""])


ABOUT = (
    f"A big skeleton with a small sculpt. {JOINTS} joints (a spine of {SPINE}, then chains of {CHAIN} hanging from "
    f"it, as facial and secondary joints hang from a head), {POINTS_PER_JOINT} points around each joint skinned to it "
    f"and its parent; {EXAMPLES} examples each rotate every joint (5 to 20 degrees, random axes) and sculpt "
    f"{SCULPTED} points at one chain's tip. Each fit and eval runs in a fresh process: seconds, and the process's "
    "peak resident memory (VmHWM, Python and USD included). Beside it, on the same skeleton, one global group "
    "(`--group main`: every moved joint a driver of one RBF), which is what a default fit of these examples made "
    "before per-joint terms."
)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Fit and eval of a small sculpt on a 1,200-joint skeleton.")
    parser.add_argument("--joints", type=int, default=JOINTS)
    parser.add_argument("--global-joints", type=int, default=0,
                        help="also measure --group main at this many joints (0: not)")
    parser.add_argument("--record", default=results.path_of("manyjoints"), help="where to write the results record")
    args = parser.parse_args(argv)
    rows, raw = [], {}
    with tempfile.TemporaryDirectory() as folder:
        cases = [(args.joints, None)] + ([(args.global_joints, "main")] if args.global_joints else [])
        for joints, group in cases:
            asset, examples, _ = build(folder, joints)
            m = measure(asset, examples, folder, group)
            label = "default fit" if group is None else "one global group (--group main)"
            raw[f"{joints} {label}"] = m
            drivers = max(g["drivers"] for g in m["groups"])
            rows.append([str(joints), label, f"{m['fit_seconds']:.2f}", f"{m['eval_seconds']:.2f}",
                         f"{m['peak_mib']:.0f}", str(len(m["groups"])), str(drivers),
                         str(max(g["points"] for g in m["groups"])), f"{m['roundtrip_max']:.1e}"])
            print(f"{joints} joints, {label}: fit {m['fit_seconds']:.2f} s, eval {m['eval_seconds']:.2f} s "
                  f"({m['eval_frames']} frames), peak {m['peak_mib']:.0f} MiB, {len(m['groups'])} group(s), "
                  f"most drivers {drivers}, round trip {m['roundtrip_max']:.1e}", flush=True)
    table = results.table("Fit and eval of a small sculpt on a big skeleton",
                          ["joints", "fit", "fit s", "eval s", "peak MiB", "groups", "most drivers",
                           "most points moved", "round trip"], rows,
                          f"{EXAMPLES} examples rotating every joint; {SCULPTED} sculpted points.")
    results.write("manyjoints", argv, ABOUT, [table], raw=raw, path=args.record)


if __name__ == "__main__":
    main()
