"""The fit's fast paths (issue 16: a 100k-point fit within 60 skinnings) give the very bits of
the numpy expressions they replaced: row norms and weight sums column by column, USD arrays read
in place, the C library's atan2 skipped at the identity rotation, the black box's own
skel -> local transform, the linearised start without masks, a Powell run with nothing left to
do, and faces checked without building the topology. Each is held to the expression it replaced,
on random and edge-case input (signed zeros, NaN, inf, magnitudes far apart)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import fixture, generate
from pxr import Usd, UsdGeom, Vt

from psdbake import tolerances
from psdbake.arrays import row_norms
from psdbake.errors import InputError
from psdbake.model.quaternions import Rotations, _atan2, _canonical
from psdbake.solver import powell
from psdbake.solver.inverse import _conjugate_start
from psdbake.usd.blackbox import SkinningBlackBox
from psdbake.usd.inplace import numbers as _numbers
from psdbake.usd.normalbox import read_mesh_shading
from psdbake.usd.posedpoints import to_local_rows, work_rows, writable
from psdbake.usd.read import Scene
from psdbake.usd.validate import _row_sums

ASSET, ANIM = fixture("arm_lbs.usda"), fixture("arm_anim.usda")


def _bits(a: np.ndarray) -> np.ndarray:
    """float64 values as bit patterns: equal arrays are equal bit for bit (-0 is not +0, NaNs compare)."""
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def _wild(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Numbers 40 orders of magnitude apart, with signed zeros."""
    a = rng.normal(size=shape) * 10.0 ** rng.integers(-20, 20, shape)
    a[rng.random(shape) < 0.05] = 0.0
    a[rng.random(shape) < 0.05] = -0.0
    return a


@pytest.mark.parametrize("seed", range(4))
def test_row_norms_are_numpys(seed):
    rng = np.random.default_rng(seed)
    for k in range(1, 8):
        a, b = _wild(rng, (3000, k)), _wild(rng, (3000, k))
        a[0, 0], a[1, -1], b[2, 0], a[3, 0], b[3, 0] = np.nan, np.inf, 1e300, -1e300, 1e300
        with np.errstate(all="ignore"):
            assert np.array_equal(_bits(row_norms(a, b)), _bits(np.linalg.norm(a - b, axis=1))), k
            assert np.array_equal(_bits(row_norms(a)), _bits(np.linalg.norm(a, axis=1))), k


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_weight_row_sums_are_numpys(dtype):
    rng = np.random.default_rng(7)
    for k in range(1, 11):
        w = (rng.random((5000, k)) * 10.0 ** rng.integers(-12, 2, (5000, k))).astype(dtype)
        w[rng.random((5000, k)) < 0.2] = 0
        assert np.array_equal(_bits(_row_sums(w)), _bits(w.astype(np.float64).sum(axis=1))), k


def test_usd_arrays_are_read_in_place_and_anything_else_converted():
    ints, floats = Vt.IntArray([3, -1, 2]), Vt.FloatArray([0.5, 0.25])
    assert _numbers(ints, np.int64).dtype == np.int32 and _numbers(floats, np.float64).dtype == np.float32
    assert _numbers(ints, np.int64).tolist() == [3, -1, 2]
    assert _numbers(None, np.int64).dtype == np.int64 and not _numbers(Vt.IntArray(), np.int64).size
    assert _numbers(floats, np.int64).tolist() == [0, 0]  # another kind: converted as np.array did


def test_float32_floor_is_the_largest_magnitude():
    rng = np.random.default_rng(3)
    for points in [np.zeros((0, 3)), -np.zeros((2, 3)), np.array([[1.0, -np.inf, 2.0]]), np.array([[np.nan, 1, 2]]),
                   *(_wild(rng, (50, 3)) for _ in range(50))]:
        scale = float(np.max(np.abs(points))) if points.size else 0.0
        expected = tolerances.FLOAT32_FLOOR_ULPS * tolerances.EPS32 * max(scale, 1e-30)
        assert _bits(np.array(tolerances.float32_floor(points))) == _bits(np.array(expected))


def test_atan2_is_the_c_librarys_with_the_identity_skipped():
    s = np.array([0.0, 0.0, 0.0, 0.0, 1e-300, 0.5, np.nan, 0.0, 2.0, np.inf])
    w = np.array([1.0, 0.0, -0.0, 1e-300, 1.0, -0.5, 1.0, np.nan, np.inf, 1.0])
    expected = np.array([math.atan2(a, b) for a, b in zip(s, w, strict=True)])
    assert np.array_equal(_bits(_atan2(s, w)), _bits(expected))


def test_rotation_vectors_and_angles_keep_their_bits():
    """As the formulas were: atan2 and sin on every row (the C library's), numpy's where."""
    def libm(fn, *args):
        return np.array(list(map(fn, *(a.tolist() for a in args))), dtype=np.float64)

    rng = np.random.default_rng(11)
    q = rng.normal(size=(4000, 4))
    q[:1000] *= [1e-4, 1e-4, 1e-4, 1.0]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[1000:1500] = [0.0, 0.0, 0.0, 1.0]  # the identity: a joint at bind
    q = np.concatenate([q, [[0, 0, 0, -1.0], [-0.0, 0, 0, 1], [0, -1, 0, 0.0], [0, 0, 0, -0.0], [np.nan, 0, 0, 1]]])
    with np.errstate(all="ignore"):
        flip = (q[:, 3] < 0) | ((q[:, 3] == 0) & ((q[:, 0] < 0) | ((q[:, 0] == 0) & ((q[:, 1] < 0) | (
            (q[:, 1] == 0) & (q[:, 2] < 0))))))
        canonical = np.where(flip[:, None], q * -1.0, q)
        x, y, z, w = canonical.T
        angle = 2 * libm(math.atan2, np.sqrt(x * x + y * y + z * z), w)
        small = angle <= 1e-3
        a2 = angle * angle
        series = 2 + a2 / 12 + 7 * a2 * a2 / 2880
        rotvec = np.where(small, series, angle / np.where(small, 1.0, libm(math.sin, angle / 2)))[:, None] * canonical[:, :3]
        x, y, z, w = q.T
        magnitude = 2 * libm(math.atan2, np.sqrt(x * x + y * y + z * z), np.abs(w))
        assert np.array_equal(_bits(_canonical(q)), _bits(canonical))
        assert np.array_equal(_bits(Rotations(q).as_rotvec()), _bits(rotvec))
        assert np.array_equal(_bits(Rotations(q).magnitude()), _bits(magnitude))


@pytest.mark.parametrize("asset", ["arm_lbs.usda", "arm_dqs.usda"])
def test_black_box_is_the_rows_formula_call_after_call(asset):
    """The black box skins into one VtArray it keeps and transforms with its own buffers: every
    call's float64 result is to_local_rows' (the points cache's formula), and a later call
    writes over neither an earlier result nor its input."""
    scene = Scene([ANIM, fixture(asset)])
    rest = scene.rest_points(generate.MESH)
    rng = np.random.default_rng(5)
    for t in scene.animation_times(generate.MESH)[:2]:
        box = SkinningBlackBox(scene, generate.MESH, t)
        results, inputs = [], []
        for trial in range(4):
            points = rest + (rng.normal(scale=0.01, size=rest.shape) if trial else 0.0)
            kept = points.copy()
            results.append((box(points), points))
            inputs.append(kept)
        for (result, points), kept in zip(results, inputs, strict=True):
            vt = Vt.Vec3fArray(len(points))
            writable(vt)[...] = points
            box._skin_vt(vt)
            rows = to_local_rows(vt, box._linear, box._translate, work_rows(len(points)))
            assert np.array_equal(_bits(result), _bits(rows.T)) and np.array_equal(points, kept)
        assert len({id(r) for r, _ in results}) == len(results)


def test_linearised_start_without_masks_is_the_masked_one():
    rng = np.random.default_rng(2)
    jac, r0 = np.eye(3) + rng.normal(scale=0.05, size=(500, 3, 3)), _wild(rng, (500, 3))
    r0[:5] = 0.0
    directions, start, ok = _conjugate_start(jac, r0)
    assert ok.all()
    _, inv = powell.conditioned_inverses(jac, tolerances.JACOBIAN_RCOND)
    masked_dirs, masked_start = np.tile(np.eye(3), (len(jac), 1, 1)), np.zeros_like(r0)
    masked_dirs[ok] = np.transpose(inv, (0, 2, 1))
    masked_start[ok] = np.einsum("kab,kb->ka", inv, r0[ok])
    assert np.array_equal(_bits(directions), _bits(masked_dirs)) and np.array_equal(_bits(start), _bits(masked_start))
    *cofactors, det = powell._cofactors(jac)
    assert np.array_equal(_bits(inv), _bits(powell._adjugate_over([c[ok] for c in cofactors], det[ok])))


def test_powell_with_every_problem_done_at_the_start():
    """Nothing to run: no calls, the start returned, the model a copy of the one given."""
    x0, r0, jac = np.ones((4, 3)), np.full((4, 3), 1e-9), np.tile(np.eye(3), (4, 1, 1))

    def residual(x):
        raise AssertionError("no call expected")

    res = powell.minimize_lockstep(residual, x0, directions=jac, jacobian=jac, r0=r0, atol=1e-6, quasi_newton=True)
    assert res.nfev == 0 and res.cycles == 0 and res.qn_steps == 0 and (res.status == powell.CONVERGED).all()
    assert np.array_equal(res.x, x0) and res.x is not x0 and np.array_equal(res.residual, r0)
    assert res.jacobian is not None and res.jacobian is not jac and np.array_equal(res.jacobian, jac)
    inf = powell.minimize_lockstep(residual, x0, r0=np.full((4, 3), np.inf), atol=np.inf)
    assert (inf.status == powell.NONFINITE).all()


def _mesh(counts, indices, points=4, normals=False) -> tuple[Usd.Stage, Usd.Prim]:
    """(stage, its mesh): the stage is returned to be kept alive while the prim is read."""
    stage = Usd.Stage.CreateInMemory()
    mesh = UsdGeom.Mesh.Define(stage, "/M")
    mesh.CreatePointsAttr([(0, 0, 0)] * points)
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    if normals:
        mesh.CreateNormalsAttr([(0, 0, 1)] * points)
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    return stage, mesh.GetPrim()


@pytest.mark.parametrize("counts, indices", [([2], [0, 1]), ([4], [0, 1, 2]), ([3], [0, 1, 4]), ([3], [0, -1, 2])])
def test_faces_are_checked_without_the_topology(counts, indices):
    _stage, prim = _mesh(counts, indices)
    with pytest.raises(InputError) as full:
        read_mesh_shading(prim, "asset.usda")
    with pytest.raises(InputError) as checked:
        read_mesh_shading(prim, "asset.usda", normals_only=True)
    assert str(checked.value) == str(full.value)


def test_topology_only_for_meshes_with_normals():
    (_s1, plain), (_s2, shaded) = _mesh([4], [0, 1, 2, 3]), _mesh([4], [0, 1, 2, 3], normals=True)
    assert read_mesh_shading(plain, normals_only=True).topology is None
    full = read_mesh_shading(plain)
    assert full.topology is not None and full.why_not == read_mesh_shading(plain, normals_only=True).why_not
    topology = read_mesh_shading(shaded, normals_only=True).topology
    assert topology is not None and topology.triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
