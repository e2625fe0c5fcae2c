"""BlendShape normalOffsets: area-weighted vertex normals, what UsdSkel does with normals,
and the check that matters: UsdSkel.BakeSkinning of the stack ASSET + CORRECTIVES + ANIM +
WEIGHTS shades the sculpted region as the sculpt is shaded, up to exactly the error plain
skinning already has there (skinned normals are not the normals of the skinned mesh)."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from conftest import bake, baked_normal_errors, fixture, generate, pose_only, sculpt
from pxr import Gf, Sdf, Usd, Vt

from psdbake.normals import (
    PosedNormals,
    Topology,
    angle_between,
    corrective_normals,
    face_area_vectors,
    normal_maps_from_probes,
    rotate_between,
    vertex_normals,
)
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.normalbox import NormalBlackBox, read_mesh_shading
from psdbake.usd.read import Scene

MESH = generate.MESH


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _grid(n: int = 5, left_handed: bool = False) -> tuple[np.ndarray, Topology]:
    """An n x n grid of unit quads in the z = 0 plane, counter-clockwise seen from +z."""
    xs, ys = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="xy")
    points = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    faces = [[r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c] for r in range(n - 1) for c in range(n - 1)]
    return points, Topology(np.full(len(faces), 4), np.array(faces).ravel(), n * n, left_handed)


def _uv_sphere(rings: int, segments: int) -> tuple[np.ndarray, Topology]:
    """Unit UV sphere: quads between latitude rings, triangle fans at the poles, outward
    (counter-clockwise seen from outside)."""
    theta = np.linspace(0, math.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * math.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    body = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    points = np.vstack([[0, 0, 1], body, [0, 0, -1]])
    north, south = 0, len(points) - 1
    faces = []
    for s in range(segments):
        s1 = (s + 1) % segments
        faces.append([north, 1 + s, 1 + s1])
        for r in range(rings - 2):
            a, b = 1 + r * segments, 1 + (r + 1) * segments
            faces.append([a + s, b + s, b + s1, a + s1])
        last = 1 + (rings - 2) * segments
        faces.append([last + s1, last + s, south])
    return points, Topology(np.array([len(f) for f in faces]), np.concatenate(faces), len(points))


# --- vertex normals ----------------------------------------------------------------------

def test_flat_grid_normals_are_the_plane_normal_and_flip_with_orientation():
    points, topo = _grid()
    assert np.array_equal(vertex_normals(points, topo), np.tile([0.0, 0.0, 1.0], (25, 1)))
    _, left = _grid(left_handed=True)
    assert np.array_equal(vertex_normals(points, left), np.tile([0.0, 0.0, -1.0], (25, 1)))
    # leftHanded is the same as reversing every face's winding
    reversed_faces = Topology(topo.face_vertex_counts, topo.face_vertex_indices.reshape(-1, 4)[:, ::-1].ravel(), 25)
    assert np.array_equal(vertex_normals(points, reversed_faces), vertex_normals(points, left))


def test_sphere_normals_converge_to_the_radius():
    # Area-weighted normals are first-order accurate in general and second-order where the
    # faces around a vertex are symmetric. On a UV sphere the faces poleward of a vertex are
    # smaller than those equatorward, which biases the worst vertices by O(h) (halving the
    # spacing halves the worst error) while the typical vertex errs by O(h^2) (a quarter).
    worst, typical = [], []
    for rings, segments in ((12, 24), (24, 48)):
        points, topo = _uv_sphere(rings, segments)
        err = angle_between(vertex_normals(points, topo), points)
        worst.append(err.max())
        typical.append(np.median(err))
    assert worst[0] < 0.07  # measured 0.065 rad at 12 x 24 (15 degree spacing)
    assert 1.8 < worst[0] / worst[1] < 2.2  # measured 1.98
    assert 3.6 < typical[0] / typical[1] < 4.4  # measured 4.03
    # outward everywhere, and symmetric about the equator plane
    points, topo = _uv_sphere(12, 24)
    n = vertex_normals(points, topo)
    assert np.all(np.sum(n * points, axis=1) > 0.99)
    mirror = np.array([1.0, 1.0, -1.0])
    order = [int(np.argmin(np.linalg.norm(points - p * mirror, axis=1))) for p in points]
    assert np.abs(n[order] * mirror - n).max() < 1e-12


def test_tube_normals_are_radial():
    # The arm's tube (fixtures/generate.py): every face is a rectangle parallel to the axis
    # and each ring vertex sits between mirror-image faces, so its normal is exactly radial
    # and outward (the fixture's winding), end rings included (their faces are radial too).
    rings, segments = 24, 16
    points = generate.tube_points(rings, segments)
    counts, indices = generate.tube_faces(rings, segments)
    n = vertex_normals(points, Topology(np.array(counts), np.array(indices), len(points)))
    radial = _unit(points * [0.0, 1.0, 1.0])
    assert angle_between(n, radial).max() < 1e-12


def test_polygons_of_three_four_and_five_sides():
    # A triangle, a quad and a regular pentagon in a tilted plane, sharing nothing.
    pent = np.stack([np.cos(np.arange(5) * 2 * math.pi / 5), np.sin(np.arange(5) * 2 * math.pi / 5), np.zeros(5)], 1)
    triangle, quad = [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[3, 0, 0], [5, 0, 0], [5, 1, 0], [3, 1, 0]]
    flat = np.vstack([triangle, quad, pent + np.array([8.0, 0.0, 0.0])])
    rot = Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(1, 2, 3), 37.0))
    tilt = np.array(rot, dtype=float)
    points = flat @ tilt
    topo = Topology(np.array([3, 4, 5]), np.arange(12), 12)
    areas = np.linalg.norm(face_area_vectors(points, topo), axis=1)
    np.testing.assert_allclose(areas, [0.5, 2.0, 2.5 * math.sin(2 * math.pi / 5)], rtol=0, atol=1e-12)  # float64, areas ~1
    assert np.abs(vertex_normals(points, topo) - np.array([0, 0, 1.0]) @ tilt).max() < 1e-12
    # A non-planar pentagon: its vector area does not depend on the fan's first vertex.
    bent = pent + np.array([[0, 0, 0.3], [0, 0, -0.2], [0, 0, 0.1], [0, 0, 0.4], [0, 0, -0.3]])
    fans = [face_area_vectors(bent, Topology(np.array([5]), np.roll(np.arange(5), k), 5))[0] for k in range(5)]
    assert np.abs(np.array(fans) - fans[0]).max() < 1e-14


def test_normals_of_some_vertices_are_those_rows_of_all():
    points, topo = _uv_sphere(12, 24)
    points = points + np.random.default_rng(4).normal(scale=0.05, size=points.shape)  # no symmetry left
    some = np.array([0, 5, 77, 200, len(points) - 1])
    assert np.array_equal(vertex_normals(points, topo, some), vertex_normals(points, topo)[some])


def test_ring_is_every_vertex_sharing_a_face():
    _, topo = _grid()
    assert topo.ring([12]).tolist() == [6, 7, 8, 11, 12, 13, 16, 17, 18]  # interior: its 3 x 3 block
    assert topo.ring([0]).tolist() == [0, 1, 5, 6]  # corner
    assert topo.ring([]).tolist() == []


def test_bad_topology_is_refused():
    with pytest.raises(ValueError, match="at least 3"):
        Topology(np.array([2]), np.array([0, 1]), 2)
    with pytest.raises(ValueError, match="sum to 4"):
        Topology(np.array([4]), np.array([0, 1, 2]), 4)
    with pytest.raises(ValueError, match="out of range"):
        Topology(np.array([3]), np.array([0, 1, 3]), 3)


def test_rotate_between_is_the_smallest_rotation():
    rng = np.random.default_rng(1)
    a, b, v = rng.normal(size=(3, 100, 3))
    out = rotate_between(a, b, v)
    assert np.abs(angle_between(rotate_between(a, b, a), b)).max() < 1e-12  # a goes to b
    # a rotation: lengths kept to float64 round-off (lengths of normal(0, 1) vectors: < 10)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), np.linalg.norm(v, axis=1), rtol=0, atol=1e-12)
    axis = np.cross(a, b)
    assert np.allclose(np.sum(out * axis, 1), np.sum(v * axis, 1), atol=1e-12)  # about a x b
    assert np.array_equal(rotate_between(np.zeros((1, 3)), b[:1], v[:1]), v[:1])  # no direction: unchanged


def test_normal_maps_are_recovered_from_normalised_probes():
    rng = np.random.default_rng(2)
    maps = rng.normal(size=(50, 3, 3)) + 3 * np.eye(3)

    def box(n):
        return _unit(np.einsum("ni,nij->nj", n, maps))

    probes = [box(np.tile(v, (50, 1))) for v in np.vstack([np.eye(3), np.ones(3)])]
    got = normal_maps_from_probes(*probes)
    v = rng.normal(size=(50, 3))
    assert angle_between(_unit(np.einsum("ni,nij->nj", v, got)), box(v)).max() < 1e-12
    maps[0] = np.outer([1, 2, 3], [0, 0, 1.0])  # rank one: cannot be inverted
    probes = [box(np.tile(v, (50, 1))) for v in np.vstack([np.eye(3), np.ones(3)])]
    assert np.isnan(normal_maps_from_probes(*probes)[0]).all()


# --- normalOffsets -----------------------------------------------------------------------

def _bump(points, topo, vertex=12, height=0.5):
    return np.array([vertex]), np.array([[0.0, 0.0, height]])


def test_no_offsets_without_per_point_normals():
    points, topo = _grid()
    idx, off = _bump(points, topo)
    assert corrective_normals(points, topo, idx, off, None) is None
    assert corrective_normals(points, topo, idx, off, np.tile([0, 0, 1.0], (25, 1)), "faceVarying") is None


def test_rest_space_offsets_give_the_corrected_shapes_normals():
    points, topo = _grid()
    idx, off = _bump(points, topo)
    rest_normals = vertex_normals(points, topo)
    cn = corrective_normals(points, topo, idx, off, rest_normals)
    # pointIndices grow to the bump's 1-ring, with zero point offsets there
    assert cn.indices.tolist() == [6, 7, 8, 11, 12, 13, 16, 17, 18] and cn.ring_added == 8
    assert np.array_equal(cn.offsets[cn.indices == 12], off) and not cn.offsets[cn.indices != 12].any()
    corrected = points.copy()
    corrected[idx] += off
    want = vertex_normals(corrected, topo)[cn.indices]
    assert np.abs(rest_normals[cn.indices] + cn.normal_offsets - want).max() < 1e-12
    assert np.abs(cn.normal_offsets[cn.indices == 12]).max() < 1e-12  # the apex keeps its normal (symmetry)
    turn = angle_between(rest_normals, vertex_normals(corrected, topo)).max()
    assert cn.rest_space == 9 and cn.max_turn == pytest.approx(turn, rel=0, abs=1e-12)  # radians, float64


def test_authored_normals_keep_their_deviation_and_length():
    points, topo = _grid()
    idx, off = _bump(points, topo)
    tilt = np.array(Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(1, 0, 0), 10.0)), dtype=float)
    authored = 2.0 * vertex_normals(points, topo) @ tilt  # smoothed/edited: 10 degrees off, length 2
    cn = corrective_normals(points, topo, idx, off, authored)
    corrected = points.copy()
    corrected[idx] += off
    new = authored[cn.indices] + cn.normal_offsets
    np.testing.assert_allclose(np.linalg.norm(new, axis=1), 2.0, rtol=0, atol=1e-12)  # float64
    assert np.allclose(angle_between(new, vertex_normals(corrected, topo)[cn.indices]), math.radians(10.0), atol=1e-12)


def test_posed_offsets_invert_the_normal_skinning():
    # A synthetic pose: per-vertex linear normal maps (rotation times shear, as LBS blends),
    # plain points an affine image of the rest, the sculpt a bump on the plain points.
    points, topo = _grid()
    rng = np.random.default_rng(3)
    maps = np.array([np.array(Gf.Matrix3d(Gf.Rotation(Gf.Vec3d(*rng.normal(size=3)), 40.0)), dtype=float)
                     @ (np.eye(3) + 0.2 * rng.normal(size=(3, 3))) for _ in range(25)])
    plain = points @ maps[0] + [1.0, 2.0, 3.0]
    sculpted = plain.copy()
    sculpted[12] += np.array([0.0, 0.0, 0.7]) @ maps[0]
    authored = vertex_normals(points, topo)
    pose = PosedNormals(plain, sculpted, maps)
    cn = corrective_normals(points, topo, np.array([12]), np.array([[0.0, 0.0, 0.6]]), authored, pose=pose)
    assert cn.rest_space == 0 and cn.ring_added == 8
    baked = _unit(np.einsum("ni,nij->nj", authored[cn.indices] + cn.normal_offsets, maps[cn.indices]))
    skinned = _unit(np.einsum("ni,nij->nj", authored[cn.indices], maps[cn.indices]))
    want = rotate_between(vertex_normals(plain, topo)[cn.indices], vertex_normals(sculpted, topo)[cn.indices], skinned)
    assert angle_between(baked, want).max() < 1e-12
    # a singular map falls back to the rest-space offset for that vertex only
    maps[12] = 0.0
    cn = corrective_normals(points, topo, np.array([12]), np.array([[0.0, 0.0, 0.6]]), authored,
                            pose=PosedNormals(plain, sculpted, normal_maps_from_probes(*[maps[:, k] for k in range(3)],
                                                                                       maps.sum(axis=1))))
    assert cn.rest_space == 1


def test_bad_corrective_input_is_refused():
    points, topo = _grid()
    normals = vertex_normals(points, topo)
    with pytest.raises(ValueError, match="rows"):
        corrective_normals(points, topo, [1, 2], [[0, 0, 1.0]], normals)
    with pytest.raises(ValueError, match="repeated"):
        corrective_normals(points, topo, [1, 1], [[0, 0, 1.0]] * 2, normals)
    with pytest.raises(ValueError, match="expected"):
        corrective_normals(points, topo, [1], [[0, 0, 1.0]], normals[:3])


# --- what UsdSkel does with normals (usd-core 26.11) -------------------------------------

def _asset_with_normals(tmp_path, name="arm_lbs.usda", interpolation="vertex", primvar=False, mesh_path=MESH) -> str:
    """A copy of a fixture whose mesh authors rest normals computed by psdbake.normals."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(fixture(name)))
    mesh = layer.GetPrimAtPath(mesh_path)
    points = np.array(mesh.properties["points"].default, dtype=np.float64)
    topo = Topology(np.array(mesh.properties["faceVertexCounts"].default),
                    np.array(mesh.properties["faceVertexIndices"].default), len(points))
    normals = vertex_normals(points, topo)
    if interpolation == "faceVarying":
        normals = normals[topo.face_vertex_indices]
    spec = Sdf.AttributeSpec(mesh, "primvars:normals" if primvar else "normals", Sdf.ValueTypeNames.Normal3fArray)
    spec.default = Vt.Vec3fArray.FromNumpy(normals.astype(np.float32))
    spec.SetInfo("interpolation", interpolation)
    path = str(tmp_path / f"normals_{interpolation}_{int(primvar)}_{os.path.basename(name)}")
    layer.Export(path)
    return path


def test_read_mesh_shading(tmp_path):
    def shading(path):
        stage = Usd.Stage.Open(path)
        return read_mesh_shading(stage.GetPrimAtPath(MESH))

    plain = shading(fixture("arm_lbs.usda"))
    assert plain.normals is None and "no authored normals" in plain.why_not and plain.topology.face_count == 368
    ok = shading(_asset_with_normals(tmp_path))
    assert ok.why_not == "" and ok.interpolation == "vertex" and ok.normals.shape == (384, 3)
    fv = shading(_asset_with_normals(tmp_path, interpolation="faceVarying"))
    assert fv.normals is None and "faceVarying" in fv.why_not
    pv = shading(_asset_with_normals(tmp_path, primvar=True))
    assert pv.normals is None and "primvars:normals" in pv.why_not


def _anim(examples: str) -> Sdf.Layer:
    """The examples' pose alone (conftest.pose_only), as a layer Scene can compose."""
    return Sdf.Layer.Find(pose_only(examples))


BOX_RIGS = {  # asset, animation, mesh, time
    "arm_lbs": ("arm_lbs.usda", "arm_lbs_examples.usda", MESH, 3.0),
    "arm_dqs": ("arm_dqs.usda", "arm_dqs_examples.usda", MESH, 3.0),
    "sleeve_own_joint_order": ("character/character.usda", "character/character_anim.usda", "/Character/Geo/Sleeve", 10.0),
}


@pytest.mark.parametrize("rig", sorted(BOX_RIGS))
def test_normal_black_box_is_what_bake_skinning_writes(rig, tmp_path):
    name, anim, mesh, t = BOX_RIGS[rig]
    asset, anim = _asset_with_normals(tmp_path, name, mesh_path=mesh), pose_only(fixture(anim))
    scene = Scene([Sdf.Layer.Find(anim), asset])
    rest_normals = read_mesh_shading(scene.prim(mesh)).normals
    box = NormalBlackBox(scene, mesh, t)
    stage = bake([anim, asset], t)
    baked = np.array(stage.GetPrimAtPath(mesh).GetAttribute("normals").Get(t), dtype=np.float64)
    # The same UsdSkel code in float32 (measured 1e-16 rad: bit-identical before the local transform)
    assert angle_between(box(rest_normals), baked).max() < 1e-6
    maps = box.normal_maps()  # rebuilt from four normalised float32 probes: ~1e-7 rad (measured 1.5e-7)
    assert angle_between(np.einsum("ni,nij->nj", rest_normals, maps), baked).max() < 1e-5
    assert angle_between(box(rest_normals), rest_normals).max() > 1.0  # the pose really turns them


def test_bake_skinning_skins_only_the_normals_attribute(tmp_path):
    examples = pose_only(fixture("arm_lbs_examples.usda"))
    stage = bake([examples, _asset_with_normals(tmp_path, primvar=True)], 3.0)
    assert not stage.GetPrimAtPath(MESH).GetAttribute("primvars:normals").GetTimeSamples()  # left at rest: stale
    stage = bake([examples, _asset_with_normals(tmp_path, interpolation="faceVarying")], 3.0)
    assert len(stage.GetPrimAtPath(MESH).GetAttribute("normals").Get(3.0)) == 1472  # faceVarying normals are skinned


# --- the product: BakeSkinning of the stack shades the sculpt ----------------------------

def _without_normal_offsets(corr: str, out: str) -> int:
    """CORRECTIVES minus its normalOffsets (the point offsets unchanged): what the shading
    would be without them. Returns how many BlendShapes carried them."""
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(Sdf.Layer.FindOrOpen(corr))
    found: list[Sdf.Path] = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: found.append(p) if p.IsPropertyPath() and p.name == "normalOffsets" else None)
    for path in found:
        layer.GetPrimAtPath(path.GetPrimPath()).RemoveProperty(layer.GetPropertyAtPath(path))
    layer.Export(out)
    return len(found)


@pytest.mark.parametrize("rig", ["arm_lbs", "arm_dqs"])
def test_baked_stack_shades_the_sculpt_as_plain_skinning_shades_its_own_mesh(rig, run, tmp_path):
    """Per vertex of the sculpted region (moved vertices and their 1-ring), the angle
    between baked and sculpt normals equals the angle plain skinning has against its own
    mesh: measured equal to 3e-6..2e-5 rad (float32 offsets, skinning and points; the
    inner elbow's nearly folded faces amplify point round-off), hence 1e-4. Without
    normalOffsets it is off by 0.27..1.7 rad (so >= 1000x worse, and > 0.1 rad). That
    error itself is large at the bent elbow (up to 2.9 rad: LBS/DQS normals ignore how the
    weights vary), which no rest-space offset can remove without a seam at the ring's edge.
    Outside the ring nothing changes."""
    asset, examples = _asset_with_normals(tmp_path, f"{rig}.usda"), fixture(f"{rig}_examples.usda")
    corr, corr_n, weights = (str(tmp_path / f) for f in ("corr.usda", "corr_normals.usda", "weights.usda"))
    assert run("fit", asset, examples, "-o", corr_n, "-q")[0] == 0  # fit writes normalOffsets itself
    assert _without_normal_offsets(corr_n, corr) >= 3  # every channel of the three correctives
    assert run("eval", asset, corr_n, "--anim", examples, "-o", weights, "-q")[0] == 0
    rest_scene = Scene([asset])
    topo, rest = read_mesh_shading(rest_scene.prim(MESH)).topology, rest_scene.rest_points(MESH)
    anim, anim_scene = pose_only(examples), Scene([_anim(examples), asset])
    for t in (1.0, 2.0, 3.0):
        target = sculpt(examples, MESH, t)
        with_offsets = baked_normal_errors([weights, anim, corr_n, asset], MESH, t, target)
        without = baked_normal_errors([weights, anim, corr, asset], MESH, t, target)
        own = baked_normal_errors([anim, asset], MESH, t)  # plain skinning against its own mesh
        plain_points = SkinningBlackBox(anim_scene, MESH, t)(rest)
        moved = np.nonzero(np.linalg.norm(target - plain_points, axis=1) > 1e-6 * np.ptp(target, axis=0).max())[0]
        region = topo.ring(moved)
        outside = np.setdiff1d(np.arange(topo.point_count), region)
        assert len(region) > 100
        deviation = np.abs(with_offsets - own)[region].max()
        assert deviation < 1e-4, f"t={t}: {deviation:.2e} rad"
        assert np.abs(without - own)[region].max() > max(0.1, 1000 * deviation)
        assert np.abs(with_offsets - without)[outside].max() < 1e-6


def test_points_cache_blocks_the_rest_normals(run, tmp_path):
    """The cache's points are posed; the asset's authored normals are rest normals, so the
    cache blocks them and renderers derive normals from the cached points."""
    asset = _asset_with_normals(tmp_path)
    corr, weights, cache = (str(tmp_path / f) for f in ("c.usda", "w.usda", "cache.usda"))
    assert run("fit", asset, fixture("arm_lbs_examples.usda"), "-o", corr, "-q")[0] == 0
    assert run("eval", asset, corr, "--anim", fixture("arm_anim.usda"), "--frames", "1:3", "-o", weights,
               "--points-cache", cache, "-q")[0] == 0
    root = Sdf.Layer.CreateAnonymous(".usda")
    root.subLayerPaths.append(cache)
    root.subLayerPaths.append(asset)
    stage = Usd.Stage.Open(root)
    normals = stage.GetPrimAtPath(MESH).GetAttribute("normals")
    assert Usd.Stage.Open(asset).GetPrimAtPath(MESH).GetAttribute("normals").Get() is not None
    assert normals.Get(2.0) is None and normals.Get() is None
