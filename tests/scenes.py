"""Scene shapes for tests/test_scenes.py, built in a test's tmp folder from the arm rig
(``fixtures/generate.py``) with small Sdf/Usd edits:

- ``own_joints``: the mesh carries its own ``skel:joints`` (a subset of the skeleton's
  joints, in another order) and ``jointIndices`` into that list;
- ``nested``: a prop rig (its own SkelRoot, Skeleton and mesh) inside the character's
  SkelRoot, plus a mesh in the prop's SkelRoot that is bound to the *character's*
  skeleton only through a ``skel:skeleton`` inherited from above the inner SkelRoot;
- ``instanced``: a shot that references a character twice with ``instanceable = true``
  (each instance bound to its own SkelAnimation on its instance root), and a variant with
  the meshes inside an instance under an ordinary SkelRoot.

The sculpts are ground truth from Pixar's own code: ``UsdSkel.BakeSkinning`` of the rest
points plus a known rest-space bulge, as in ``generate.bake_sculpt``, but for any mesh
paths, baked over the whole stage so that nested SkelRoots are handled the way UsdSkel
handles them.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from conftest import generate, stage_of
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

SPEC = generate.ArmSpec(rings=12, segments=8)  # 96 points: fast, and every feature of the arm rig
TIMES = (1.0, 2.0, 3.0)
Pose = dict  # joint leaf name -> (axis, degrees), as generate.EXAMPLE_POSES


@dataclass(frozen=True)
class Built:
    """A scene on disk: the asset, its examples (poses + sculpts) and the sculpts themselves."""

    asset: str
    examples: str
    sculpts: dict  # mesh -> {time: sculpted points (n, 3) in mesh local space}
    anim: str  # the poses alone (examples without points), usable as ANIM


def _open_or_create(path: str) -> Sdf.Layer:
    if os.path.exists(path):
        os.remove(path)
    return Sdf.Layer.CreateNew(path)


def author_animation(layer: Sdf.Layer, anim: str, poses: dict[float, Pose], bind_on: str | None) -> None:
    """The arm's joints that any pose moves, at ``anim``, bound on ``bind_on`` (a Skeleton, or
    an ancestor such as an instance root: UsdSkel inherits the binding)."""
    generate.author_animation(layer, poses, anim=anim, bind_on=bind_on)


def bulge(spec: generate.ArmSpec = SPEC, scale: float = 1.0) -> Callable[[float], np.ndarray]:
    """Rest-space corrective in the mesh's authored point space at each example time: the
    arm fixture's ground-truth bulge (generate.elbow_bulge), times ``scale``."""
    bind = generate.tube_points(spec.rings, spec.segments)
    g_inv = np.linalg.inv(np.array(generate.geom_bind_matrix(), dtype=np.float64)[:3, :3])
    angles = {t: (p.get("Elbow", (None, 0.0))[1], p.get("Wrist", (None, 0.0))[1]) for t, p in generate.EXAMPLE_POSES.items()}
    return lambda t: scale * generate.elbow_bulge(bind, *angles[t]) @ g_inv


def bake_sculpts(layers: list[str], offsets: dict[str, Callable[[float], np.ndarray]]) -> dict:
    """Ground truth at TIMES: mesh -> {t: points} (generate.bake_mesh_sculpts)."""
    return generate.bake_mesh_sculpts(layers, TIMES, offsets)


write_examples = generate.write_mesh_examples


def arm(folder: str) -> Built:
    """The plain arm (small), its example poses and sculpts: the asset that gets instanced."""
    asset = generate.build_arm(os.path.join(folder, "arm.usda"), SPEC)
    anim = _open_or_create(os.path.join(folder, "arm_poses.usda"))
    author_animation(anim, generate.ANIM, generate.EXAMPLE_POSES, generate.SKEL)
    anim.Save()
    sculpts = bake_sculpts([anim.identifier, asset], {generate.MESH: bulge()})
    examples = write_examples(os.path.join(folder, "arm_examples.usda"), anim.identifier, sculpts)
    return Built(asset, examples, sculpts, anim.identifier)


# --- 1. a mesh with its own skel:joints ---------------------------------------------------

#: The mesh's own joint list: a subset of the skeleton (no Hand), in another order.
MESH_JOINTS = ["Shoulder/Elbow/Wrist", "Shoulder", "Shoulder/Elbow"]


def own_joints(folder: str) -> Built:
    """The arm with ``skel:joints`` on the mesh: three of the four joints, reordered; each
    point's Hand weight is merged into the Wrist, so UsdSkel must map mesh joint k to its
    skeleton joint for the skinning (and psdbake's black box) to be right."""
    asset = generate.build_arm(os.path.join(folder, "own_joints.usda"), SPEC)
    stage = Usd.Stage.Open(asset)
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath(generate.MESH))
    idx = np.array(binding.GetJointIndicesPrimvar().Get(), dtype=np.int64).reshape(-1, 4)
    w = np.array(binding.GetJointWeightsPrimvar().Get(), dtype=np.float64).reshape(-1, 4)
    per_joint = np.zeros((len(idx), 4))
    np.add.at(per_joint, (np.repeat(np.arange(len(idx)), 4), idx.reshape(-1)), w.reshape(-1))
    per_joint[:, 2] += per_joint[:, 3]  # Hand -> Wrist
    skeleton_to_mesh = [generate.JOINTS.index(j) for j in MESH_JOINTS]
    new_w = per_joint[:, skeleton_to_mesh]  # columns in mesh joint order
    new_idx = np.tile(np.arange(3, dtype=np.int32), (len(idx), 1))
    binding.CreateJointsAttr(MESH_JOINTS)
    binding.CreateJointIndicesPrimvar(False, 3).Set(Vt.IntArray.FromNumpy(new_idx.reshape(-1)))
    binding.CreateJointWeightsPrimvar(False, 3).Set(Vt.FloatArray.FromNumpy(new_w.astype(np.float32).reshape(-1)))
    stage.GetRootLayer().Save()
    anim = _open_or_create(os.path.join(folder, "own_joints_poses.usda"))
    author_animation(anim, generate.ANIM, generate.EXAMPLE_POSES, generate.SKEL)
    anim.Save()
    sculpts = bake_sculpts([anim.identifier, asset], {generate.MESH: bulge()})
    examples = write_examples(os.path.join(folder, "own_joints_examples.usda"), anim.identifier, sculpts)
    return Built(asset, examples, sculpts, anim.identifier)


# --- 2. nested SkelRoots ------------------------------------------------------------------

PROP = "/Arm/Prop"  # the inner SkelRoot (the prop rig, referenced from its own file)
PROP_SKEL, PROP_MESH, PROP_ANIM = PROP + "/Skel", PROP + "/Geo/Tube", PROP + "/Skel/Anim"
SLEEVE = PROP + "/Sleeve"  # in the inner SkelRoot, bound to the character's skeleton by inheritance

#: The prop's own poses: different from the character's at every time code.
PROP_POSES = {
    1.0: {"Elbow": ((0, 1, 0), 60.0)},
    2.0: {"Elbow": ((0, 0, 1), -70.0), "Wrist": ((1, 0, 0), 40.0)},
    3.0: {"Shoulder": ((0, 0, 1), 30.0), "Elbow": ((0, 0, 1), 110.0)},
}


def nested(folder: str) -> Built:
    """A character SkelRoot </Arm> holding a prop rig: the SkelRoot </Arm/Prop>
    (a reference to a second arm file) with its own Skeleton and Tube, plus </Arm/Prop/Sleeve>,
    a copy of the character's Tube with no ``skel:skeleton`` of its own: the character's
    binding is authored on </Arm> and reaches the Sleeve only through the outer SkelRoot."""
    generate.build_arm(os.path.join(folder, "prop.usda"), SPEC)  # the prop rig's own file
    asset = generate.build_arm(os.path.join(folder, "nested.usda"), SPEC)
    layer = Sdf.Layer.FindOrOpen(asset)
    stage = Usd.Stage.Open(layer)
    UsdSkel.BindingAPI.Apply(stage.GetPrimAtPath(generate.ROOT)).CreateSkeletonRel().SetTargets([Sdf.Path(generate.SKEL)])
    stage.GetPrimAtPath(generate.MESH).GetRelationship("skel:skeleton").ClearTargets(True)
    inner = stage.DefinePrim(PROP)
    inner.GetReferences().AddReference("./prop.usda")
    UsdGeom.Xformable(inner).AddTranslateOp(opSuffix="prop").Set(Gf.Vec3d(0.0, 1.5, 0.0))
    Sdf.CopySpec(layer, generate.MESH, layer, SLEEVE)  # no skel:skeleton either: inherited from </Arm>
    layer.Save()
    poses = _open_or_create(os.path.join(folder, "nested_poses.usda"))
    author_animation(poses, generate.ANIM, generate.EXAMPLE_POSES, generate.SKEL)
    author_animation(poses, PROP_ANIM, PROP_POSES, PROP_SKEL)
    poses.Save()
    offsets = {generate.MESH: bulge(), PROP_MESH: bulge(scale=0.6), SLEEVE: bulge(scale=1.4)}
    sculpts = bake_sculpts([poses.identifier, asset], offsets)
    examples = write_examples(os.path.join(folder, "nested_examples.usda"), poses.identifier, sculpts)
    return Built(asset, examples, sculpts, poses.identifier)


# --- 3. instances -------------------------------------------------------------------------

INSTANCES = {"/World/CharA": "/World/Anims/A", "/World/CharB": "/World/Anims/B"}

#: Instance B plays the example poses in another order: at time t it shows example B_ORDER[t].
B_ORDER = {1.0: 3.0, 2.0: 1.0, 3.0: 2.0}


def instanced_shot(folder: str, asset: str, name: str = "shot.usda", animate: bool = True) -> str:
    """A shot referencing ``asset`` twice with ``instanceable = true``, each instance moved
    and (``animate``) bound on its instance root, outside the prototype, to its own
    SkelAnimation: A plays the example poses at their own times, B in the order ``B_ORDER``."""
    layer = _open_or_create(os.path.join(folder, name))
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    UsdGeom.Scope.Define(stage, "/World/Anims")
    for k, (path, anim) in enumerate(sorted(INSTANCES.items())):
        prim = stage.DefinePrim(path)
        prim.GetReferences().AddReference("./" + os.path.relpath(asset, folder))
        prim.SetInstanceable(True)
        UsdGeom.Xformable(prim).AddTranslateOp(opSuffix="shot").Set(Gf.Vec3d(8.0 * k - 4.0, 0.0, 3.0 * k))
        if animate:
            poses = generate.EXAMPLE_POSES if path.endswith("A") else {t: generate.EXAMPLE_POSES[s] for t, s in B_ORDER.items()}
            author_animation(layer, anim, poses, path)
    layer.Save()
    return layer.identifier


def meshes_in_instance(folder: str) -> str:
    """An ordinary character SkelRoot whose geometry </Arm/Geo> is an instance of a
    separate geometry file; the skeleton binding is authored on the instance root."""
    arm = Sdf.Layer.FindOrOpen(generate.build_arm(os.path.join(folder, "arm_for_geo.usda"), SPEC))
    geo = _open_or_create(os.path.join(folder, "geo.usda"))
    Sdf.CopySpec(arm, "/Arm/Geo", geo, "/Geo")
    geo.GetPrimAtPath("/Geo/Tube").RemoveProperty(geo.GetPropertyAtPath("/Geo/Tube.skel:skeleton"))
    geo.defaultPrim = "Geo"
    geo.Save()
    layer = _open_or_create(os.path.join(folder, "geo_instanced.usda"))
    layer.TransferContent(arm)
    del layer.GetPrimAtPath("/Arm").nameChildren["Geo"]
    stage = Usd.Stage.Open(layer)
    prim = stage.DefinePrim("/Arm/Geo")
    prim.GetReferences().AddReference("./geo.usda")
    prim.SetInstanceable(True)
    UsdSkel.BindingAPI.Apply(prim).CreateSkeletonRel().SetTargets([Sdf.Path(generate.SKEL)])
    author_animation(layer, generate.ANIM, generate.EXAMPLE_POSES, generate.SKEL)
    layer.Save()
    return layer.identifier


def deinstanced(layers: list[str]) -> Usd.Stage:
    """The same layers with every instance made ordinary (``instanceable = false`` in the
    strongest layer): what each instance shows, in a form ``BakeSkinning`` accepts."""
    stage = stage_of(layers)
    for prim in list(stage.Traverse()):
        if prim.IsInstance():
            prim.SetInstanceable(False)
    return stage

