"""The long-path fixture: the arm rig of fixtures/generate.py with its mesh nested under Xforms with
long names, so that psdbake's readable channel names (``psd_<group>_<mesh path below the
SkelRoot>_<k>_pos``) are longer than Blender's 63-byte shape-key names, and the mesh's parent has
the skeleton's world transform (a layout Blender's import places as UsdSkel does).

Generated at run time (deterministic: the arm, its poses and its ground-truth sculpts are
generate.py's own) into a folder the caller gives: ``write(folder)`` returns the asset, examples
and animation paths. Runs in the project venv (needs pxr).
"""

from __future__ import annotations

import os
import sys

import numpy as np
from pxr import Sdf, Usd, UsdGeom

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "fixtures"))

import generate  # noqa: E402  (fixtures/generate.py)

LONG_GROUP = "A_very_long_group_name_for_the_left_sleeve_geometry"
NESTED = ("/Arm/Geo", LONG_GROUP, "Sleeve_parts_upper_arm_and_forearm")
MESH = "/".join((*NESTED, "Tube"))


def _reroot_mesh(asset: str) -> None:
    """Move the arm's mesh from generate.MESH to MESH (identity Xforms in between)."""
    layer = Sdf.Layer.FindOrOpen(asset)
    parent = Sdf.Path(NESTED[0])
    for name in NESTED[1:]:
        parent = parent.AppendChild(name)
        spec = Sdf.CreatePrimInLayer(layer, parent)
        spec.specifier, spec.typeName = Sdf.SpecifierDef, "Xform"
    if not Sdf.CopySpec(layer, Sdf.Path(generate.MESH), layer, Sdf.Path(MESH)):
        raise RuntimeError(f"could not copy {generate.MESH} to {MESH} in {asset}")
    old = layer.GetPrimAtPath(generate.MESH)
    del old.nameParent.nameChildren[old.name]
    layer.Save()
    stage = Usd.Stage.Open(layer)
    # a layout Blender places as UsdSkel does (psdbake inspect: no warning): the mesh's parent
    # gets the skeleton's world transform (world = local * parent world, row vectors)
    cache = UsdGeom.XformCache()
    skel_world = cache.GetLocalToWorldTransform(stage.GetPrimAtPath(generate.SKEL))
    first = stage.GetPrimAtPath(Sdf.Path(NESTED[0]).AppendChild(NESTED[1]))
    UsdGeom.Xformable(first).AddTransformOp().Set(skel_world * cache.GetParentToWorldTransform(first).GetInverse())
    stage.GetRootLayer().Save()
    if not stage.GetPrimAtPath(MESH).IsA(UsdGeom.Mesh) or stage.GetPrimAtPath(generate.MESH):
        raise RuntimeError(f"re-rooting {generate.MESH} to {MESH} failed in {asset}")


def write(folder: str) -> tuple[str, str, str]:
    """Write asset, examples and shot animation of the long-path arm into folder."""
    os.makedirs(folder, exist_ok=True)
    spec = generate.ArmSpec()
    asset = generate.build_arm(os.path.join(folder, "arm_long.usda"), spec)
    _reroot_mesh(asset)
    poses = generate.write_animation(os.path.join(folder, "arm_long_poses.usda"), generate.EXAMPLE_POSES)
    anim = generate.write_animation(os.path.join(folder, "arm_long_anim.usda"), generate.shot_poses())
    # ground truth as generate.bake_sculpt makes it, for the moved mesh: bind-space offsets
    # mapped through the geomBindTransform into the mesh's authored point space
    g = np.array(generate.geom_bind_matrix(), dtype=np.float64)
    g_inv = np.linalg.inv(g[:3, :3])
    offsets = generate.example_offsets(spec)
    times = sorted(generate.EXAMPLE_POSES)
    sculpts = generate.bake_mesh_sculpts([poses, asset], times, {MESH: lambda t: offsets(t) @ g_inv})
    examples = generate.write_mesh_examples(os.path.join(folder, "arm_long_examples.usda"), poses, sculpts)
    return asset, examples, anim


if __name__ == "__main__":
    for path in write(sys.argv[1] if len(sys.argv) > 1 else "."):
        print(path)
