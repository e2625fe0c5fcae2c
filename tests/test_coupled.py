"""Chains that couple vertices: the reference Delta Mush deformer, the coupling probe and the
coupled inverse (``psdbake.solver.coupled``), on a small bench rig (1.3k points)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import ROOT, sculpt
from scipy.sparse.csgraph import connected_components, shortest_path

from psdbake import tolerances as tol
from psdbake.delta_mush import DeltaMush, make
from psdbake.normals import Topology
from psdbake.solver import coupled, pieces, powell, smoothstart, structured, subspace
from psdbake.solver.inverse import Counted, InverseResult, invert_example, sculpted_vertices
from psdbake.solver.smoothbasis import edge_adjacency
from psdbake.usd import blackbox
from psdbake.usd.blackbox import ChainSkinning
from psdbake.usd.meshrest import rest_mesh

sys.path.insert(0, ROOT)
from benchmarks import characters, rigs

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)

#: Elbow bends small enough that LBS does not fold the elbow (a folded elbow makes Delta
#: Mush's frames flip: the chain is then discontinuous there).
POSES = {1.0: {"Elbow": ((0, 0, 1), 20.0), "Wrist": ((1, 0, 0), 25.0)},
         2.0: {"Elbow": ((0, 0, 1), 28.0), "Wrist": ((1, 0, 0), -20.0)}}
#: Black-box calls one coupled example may take here (measured: 20 and 29: the per-vertex
#: linearised start, 5 calls, in which the coupling shows, then Newton-Krylov).
CALL_BUDGET = 32
#: The same with the mesh's edges, from the smooth start (measured: 24 and 32), pinned at the
#: issue's goal for the 100k bench rig.
SMOOTH_CALL_BUDGET = 40
#: Calls before the joint stages: the per-vertex linearised start (5, in which the coupling
#: shows; the joint stages reuse its chain at rest and its blocks).
BEFORE_JOINT = 5


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("coupled")
    poses_layer = rigs.generate.write_animation(str(folder / "poses.usda"), POSES)
    return str(folder), poses_layer


def _rig(rig_folder, variant: str) -> rigs.Rig:
    folder, poses_layer = rig_folder
    return rigs.build(folder, variant, "1.3k", POSES, poses_layer)


def _tube() -> tuple[np.ndarray, Topology]:
    counts, indices = rigs.generate.tube_faces(30, 12)
    rest = rigs.generate.tube_points(30, 12)
    return rest, Topology(np.array(counts), np.array(indices), len(rest))


def test_delta_mush_identity_pose_returns_rest_and_couples_neighbours():
    rest, topology = _tube()
    for iterations, step in ((10, 0.5), (3, 0.2), (0, 0.5)):
        dm = DeltaMush(rest, topology, iterations, step)
        assert np.abs(dm(rest) - rest).max() <= 1e-14 * np.abs(rest).max()
    dm = DeltaMush(rest, topology)
    assert np.abs(dm.smooth(rest) - rest).max() > 1e-3  # it does smooth
    moved = rest.copy()
    moved[100] += 0.01
    changed = np.nonzero(np.linalg.norm(dm(moved) - dm(rest), axis=1) > 1e-12)[0]
    ring = topology.ring([100])
    assert set(ring) <= set(changed) and len(changed) > len(ring)  # neighbours and beyond
    # a rigid motion of the whole mesh moves the result rigidly
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert np.abs(dm(rest @ rot.T + 0.3) - (rest @ rot.T + 0.3)).max() <= 1e-12
    with pytest.raises(ValueError):
        make(iterations=-1)


@pytest.mark.parametrize("variant, expected", [("lbs+deltamush", True), ("lbs", False), ("lbs+bulge", False)])
def test_probe_detects_coupling(rig_folder, variant, expected):
    rig = _rig(rig_folder, variant)
    scene = rig.scene()
    for t in rig.times:
        box = rig.blackbox(scene, t)
        base = box(rig.rest)
        diagonal, _, idx = sculpted_vertices(rig.rest, base, rig.sculpts[t])
        probed = coupled.probe_vertices(rig.rest, idx)
        assert len(probed) == coupled.PROBE_VERTICES
        assert coupled.is_coupled(box, rig.rest, base, probed, tol.JACOBIAN_STEP_RTOL * diagonal) is expected
        assert box.evaluations == 2  # the probe is one call


def test_coupled_inverse_reaches_tolerance_within_budget(rig_folder):
    rig = _rig(rig_folder, "lbs+deltamush")
    scene = rig.scene()
    for t in rig.times:
        res = coupled.invert(rig.blackbox(scene, t), rig.rest, rig.sculpts[t])
        assert res.regime == "coupled" and len(res.missed) == 0
        assert res.evaluations <= CALL_BUDGET
        moved = rig.rest.copy()
        moved[res.indices] += res.offsets
        residual = np.linalg.norm(rig.sculpts[t][res.indices] - rig.blackbox(scene, t)(moved)[res.indices], axis=1)
        assert residual.max() <= res.atol
        np.testing.assert_allclose(residual, res.residual, atol=1e-12)
        # the per-vertex solver, as is, does not get there on this chain
        per_vertex = invert_example(rig.blackbox(scene, t), rig.rest, rig.sculpts[t])
        assert len(per_vertex.missed) > 0


def test_per_vertex_chains_keep_the_per_vertex_solver(rig_folder):
    rig = _rig(rig_folder, "lbs+bulge")
    scene = rig.scene()
    t = rig.times[0]
    alone = invert_example(rig.blackbox(scene, t), rig.rest, rig.sculpts[t])
    res = coupled.invert(rig.blackbox(scene, t), rig.rest, rig.sculpts[t])
    # coupling shows (or not) in the per-vertex solver's own Jacobian calls: no extra call
    assert res.regime == "per-vertex" and res.evaluations == alone.evaluations
    np.testing.assert_array_equal(res.offsets, alone.offsets)
    lbs = _rig(rig_folder, "lbs")
    assert coupled.invert(lbs.blackbox(lbs.scene(), t), lbs.rest, lbs.sculpts[t]).evaluations == 5


def test_fit_and_points_cache_with_delta_mush_end_to_end(run, rig_folder, tmp_path):
    rig = _rig(rig_folder, "lbs+deltamush")
    (tmp_path / "first").mkdir()  # beside "single" below: each layer records its inputs relative to itself
    corr, report, weights, cache = (tmp_path / "first" / name for name in ("c.usda", "r.json", "w.usda", "cache.usda"))
    spec = rigs.DELTA_MUSH_SPEC
    code, _, err = run("fit", rig.asset, rig.examples, "-o", corr, "--deformer", spec, "--report", report, "-q")
    assert code == 0, err
    examples = json.loads(report.read_text())["meshes"][0]["examples"]
    assert [ex["regime"] for ex in examples] == ["coupled, from the smooth start"] * 2
    assert all(ex["missed"] == 0 and ex["evaluations"] <= SMOOTH_CALL_BUDGET for ex in examples)
    code, _, err = run("eval", rig.asset, corr, "--anim", rig.poses_layer, "-o", weights, "--points-cache", cache,
                       "--deformer", spec, "-q")
    assert code == 0, err
    for t in rig.times:  # the cache (skinning + correctives + Delta Mush) reproduces each sculpt
        cached = sculpt(str(cache), rigs.MESH, t)
        diagonal = tol.bbox_diagonal(rig.sculpts[t])
        assert np.abs(cached - rig.sculpts[t]).max() <= 1e-5 * diagonal


def test_a_folded_elbow_reaches_the_tolerance_from_the_smooth_start(run, tmp_path):
    """13k bench rig, elbow at 80 degrees: LBS folds the inner elbow and Delta Mush's smoothed
    mesh collapses there. The chain's Jacobian is so ill-conditioned that Newton-Krylov from
    zero stalls, and the per-vertex solver leaves over 500 of the 4,604 sculpted vertices above
    the tolerance. fit's Gauss-Newton on the region's smoothest fields, then on measured
    directions, brings every one within it, and the points cache of the written stack
    reproduces the sculpt (measured: 0 missed in 21 calls; 51 with Newton-Krylov's finish
    instead, 300 when the span's Jacobian was measured)."""
    poses_layer, poses = rigs.write_poses(str(tmp_path), 8)
    rig = rigs.build(str(tmp_path), "lbs+deltamush", "13k", {4.0: poses[4.0]}, poses_layer)
    assert len(invert_example(rig.blackbox(rig.scene(), 4.0), rig.rest, rig.sculpts[4.0]).missed) > 500
    (tmp_path / "first").mkdir()  # beside "single" below: each layer records its inputs relative to itself
    corr, report, weights, cache = (tmp_path / "first" / name for name in ("c.usda", "r.json", "w.usda", "cache.usda"))
    code, _, err = run("fit", rig.asset, rig.examples, "-o", corr, "--deformer", rigs.DELTA_MUSH_SPEC,
                       "--report", report, "-q")
    assert code == 0, err
    (ex,) = json.loads(report.read_text())["meshes"][0]["examples"]
    assert ex["regime"].startswith("coupled, from the smooth start") and ex["missed"] == 0
    assert ex["evaluations"] <= SMOOTH_CALL_BUDGET
    # the same bytes from a process whose BLAS has one thread (a farm machine with one core):
    # the joint stages' sums do not depend on the machine
    single = tmp_path / "single" / "c.usda"
    single.parent.mkdir()
    done = subprocess.run([sys.executable, "-m", "psdbake", "fit", rig.asset, rig.examples, "-o", str(single),
                           "--deformer", rigs.DELTA_MUSH_SPEC, "--report", str(single.parent / "r.json"), "-q"],
                          capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr
    assert single.read_bytes() == corr.read_bytes()
    code, _, err = run("eval", rig.asset, corr, "--anim", rig.poses_layer, "-o", weights, "--points-cache", cache,
                       "--deformer", rigs.DELTA_MUSH_SPEC, "-q")
    assert code == 0, err
    # the fit's own tolerance (the larger of 1e-6 of the diagonal and 16 float32 ulps of the
    # coordinates), plus the cache's float32 rounding of each point (half an ulp, per axis)
    residual = np.linalg.norm(sculpt(str(cache), rigs.MESH, 4.0) - rig.sculpts[4.0], axis=1)
    half_ulp = 0.5 * float(np.spacing(np.float32(np.abs(rig.sculpts[4.0]).max())))
    assert residual.max() <= ex["tolerance"] + np.sqrt(3) * half_ulp


#: Calls the joint stages of one example may take when every one runs: the smooth start's
#: probe of the chain's smoothing and its two span solves, its Newton-Krylov finish; where that
#: misses short of an optimum, the solve on measured directions (before and after the
#: escalation, each with a call at its start), and the escalation: the blocks' smooth start
#: (its steps) and Newton-Krylov from it, the span's Jacobian measured (3 calls a field), its
#: steps and Newton-Krylov from it, the joint solve from zero (each stage's budget counted from
#: its start). Before them: the
#: per-vertex solver's calls, and the chain at rest, the probe and the blocks (3) when the
#: per-vertex solver's own calls did not show the coupling. After them, on a mesh of pieces
#: small enough for it (the 1.3k rig is one piece of 1,312 vertices), the pieces' exact
#: Jacobians (their budget, and a call before and after), and the out-of-reach stage.
JOINT_STAGES_BOUND = (1 + coupled.COARSE_SPAN_CALLS + coupled.FINE_SPAN_CALLS + coupled.FINISH_EVALUATIONS
                      + coupled.MEASURED_STEPS + coupled.MAX_EVALUATIONS + coupled.FROM_ZERO_EVALUATIONS
                      + 3 * coupled.MEASURED_FIELDS + coupled.MEASURED_STEPS + coupled.MAX_EVALUATIONS
                      + 2 * (1 + subspace.CALLS) + 1 + 3
                      + coupled.EXACT_CALLS + 2 + coupled.OUT_OF_REACH_EVALUATIONS)


SNAPPING_DEFORMER = '''
import numpy as np
from psdbake.delta_mush import make


_mush = make()


def snap(stage, mesh_path, time):
    """Delta Mush, then every output coordinate rounded to a 1e-3 grid: coupled, not smooth."""
    inner = _mush(stage, mesh_path, time)
    return lambda points: np.round(inner(points) / 1e-3) * 1e-3
'''


def test_a_coupled_chain_that_snaps_to_a_grid_stalls_cleanly(run, rig_folder, tmp_path):
    """A deformer that couples vertices and is not invertible (Delta Mush, then outputs snapped
    to a 1e-3 grid, 3.8e-4 of this rig's diagonal: far above the 7.6e-6 tolerance) cannot
    reach a sculpt that is off the grid. fit must say so per vertex and in its summary, in a
    bounded number of calls, without a traceback; the product misses the sculpts, so the fit
    fails (exit 7) and writes only its report; --strict refuses and writes nothing either."""
    rig = _rig(rig_folder, "lbs+deltamush")
    deformer = tmp_path / "snapping.py"
    deformer.write_text(SNAPPING_DEFORMER)
    out, report = tmp_path / "c.usda", tmp_path / "r.json"
    code, _, err = run("fit", rig.asset, rig.examples, "-o", out, "--deformer", f"{deformer}:snap",
                            "--report", report)
    assert code == 7 and not out.exists(), err
    assert json.loads(report.read_text())["written"] is False
    examples = json.loads(report.read_text())["meshes"][0]["examples"]
    scene = rig.scene()
    why: dict[str, int] = {}
    for t, ex in zip(rig.times, examples, strict=True):
        box = rig.blackbox(scene, t)
        per_vertex = invert_example(lambda p, box=box: np.round(box(p) / 1e-3) * 1e-3, rig.rest, rig.sculpts[t])
        # every vertex misses (the grid is 50x the tolerance) and says why: the solver stalled,
        # or spent its calls on steps the grid rounds away
        assert ex["missed"] == ex["vertices_solved"] > 0
        assert set(ex["missed_statuses"]) <= {"stalled", "max_cycles"}
        assert sum(ex["missed_statuses"].values()) == ex["missed"]
        assert ex["evaluations"] <= per_vertex.evaluations + 2 + JOINT_STAGES_BOUND and ex["regime"].startswith("coupled")
        for name, count in ex["missed_statuses"].items():
            why[name] = why.get(name, 0) + count
    total = sum(ex["missed"] for ex in examples)
    detail = ", ".join(f"{name} {count}" for name, count in sorted(why.items()))
    assert f"{total} vertices missed the fit tolerance ({detail};" in err
    assert "DEGRADED: the product misses example" in err and "Traceback" not in err
    strict = tmp_path / "strict.usda"
    code, _, err = run("fit", rig.asset, rig.examples, "-o", strict, "--deformer", f"{deformer}:snap", "--strict")
    assert code == 7 and not strict.exists()
    last = err.strip().splitlines()[-1]
    assert last.startswith("psdbake: error:") and "missed the tolerance (--strict)" in last


def test_without_mesh_edges_the_per_vertex_solution_stands_in(tmp_path):
    """A library caller (or a prim with no faces) gives no edge adjacency: where the joint
    solve misses, the per-vertex solve and Newton-Krylov restarted from it are the fallback,
    within their own bound."""
    poses_layer = rigs.generate.write_animation(str(tmp_path / "poses.usda"), POSES)
    rig = rigs.build(str(tmp_path), "lbs+deltamush", "1.3k", POSES, poses_layer)
    t = rig.times[0]
    box = rig.blackbox(rig.scene(), t)

    def snapped(points: np.ndarray) -> np.ndarray:
        return np.round(box(points) / 1e-3) * 1e-3

    res = coupled.invert(snapped, rig.rest, rig.sculpts[t])
    per_vertex = invert_example(snapped, rig.rest, rig.sculpts[t])
    assert res.regime in ("coupled", "coupled chain, per-vertex kept", "coupled, from the per-vertex solution")
    assert len(res.missed) == len(res.indices) > 0
    assert res.evaluations <= BEFORE_JOINT + coupled.FROM_ZERO_EVALUATIONS + per_vertex.evaluations + coupled.MAX_EVALUATIONS


def test_a_coupled_chain_that_returns_nan_ends_without_a_crash():
    """A coupling chain that gives non-finite points for any moved input (a broken deformer):
    every stage, the smooth start included, stops on it and the vertices say why."""
    rest, topology = _tube()
    mush = DeltaMush(rest, topology, iterations=3)
    target = mush(rest)
    target[100:140] += 0.01  # a sculpt on a few rings

    def broken(points: np.ndarray) -> np.ndarray:
        out = mush(points)
        return out if np.array_equal(points, rest) else np.full_like(out, np.nan)

    adjacency = edge_adjacency(topology)
    res = coupled.invert(broken, rest, target, neighbours=lambda: adjacency)
    assert len(res.indices) and len(res.missed) == len(res.indices)
    assert set(res.missed_statuses) <= {"nonfinite", "stalled", "max_cycles"}


#: Calls an example of CesiumMan's shipped sculpts may take through LBS + Delta Mush.
SHIPPED_BUDGET = 3000
#: The ripple's amplitude (the 1.3k rig's diagonal is 5.3, the reachable sculpt moves up to 0.05).
RIPPLE = 0.004
#: Offsets may reach this multiple of the sculpt's largest displacement (the regularisation's
#: bound; measured with the ripple 1.1 on the tube's exact Jacobian, 3.3 from the smooth start's
#: finish alone).
OFFSET_BOUND = 5.0


def _blend_shape_offsets(path: str) -> np.ndarray:
    """Every BlendShape's offsets in a CORRECTIVES layer, stacked (m, 3)."""
    from pxr import Usd, UsdSkel

    stage = Usd.Stage.Open(path)
    found = [np.array(UsdSkel.BlendShape(p).GetOffsetsAttr().Get(), dtype=np.float64)
             for p in stage.TraverseAll() if p.IsA(UsdSkel.BlendShape)]
    return np.concatenate(found) if found else np.zeros((0, 3))


def test_a_sculpt_the_chain_smooths_away_is_reported_as_such(run, tmp_path):
    """A ripple that alternates around the tube (every other vertex of a ring band moved in,
    the others out) is detail no smoothing passes, added to a sculpt the chain can reach. The
    fit must keep the offsets bounded, and its report must say how much of the sculpt the
    chain does not reproduce (the ripple's own share, measured here independently) and where
    (the ripple's rings); the summary says so, and the degraded-fit rule holds: exit 7 unless
    --allow-degraded, and --strict refuses even then."""
    poses_layer = rigs.generate.write_animation(str(tmp_path / "poses.usda"), POSES)
    rig = rigs.build(str(tmp_path), "lbs+deltamush", "1.3k", POSES, poses_layer)
    t = rig.times[0]
    box = rig.blackbox(rig.scene(), t)
    base = box(rig.rest)
    n, segments = len(rig.rest), rigs.SIZES["1.3k"][1]
    ring, around = np.arange(n) // segments, np.arange(n) % segments
    band = (ring >= 30) & (ring <= 36)
    outward = rig.rest * np.array([0.0, 1.0, 1.0])
    outward /= np.linalg.norm(outward, axis=1, keepdims=True)
    ripple = (RIPPLE * np.where(around % 2 == 0, 1.0, -1.0) * band)[:, None] * outward
    rippled = (rig.sculpts[t] + ripple).astype(np.float32).astype(np.float64)
    examples = rigs.generate.write_examples(str(tmp_path / "rippled.usda"), rig.poses_layer, {t: rippled})
    _, _, idx = sculpted_vertices(rig.rest, base, rippled)
    share = np.sqrt(np.mean(np.sum(ripple[idx] ** 2, axis=1)) / np.mean(np.sum((rippled - base)[idx] ** 2, axis=1)))
    corr, report = tmp_path / "c.usda", tmp_path / "r.json"
    code, _, err = run("fit", rig.asset, examples, "-o", corr, "--deformer", rigs.DELTA_MUSH_SPEC)
    assert code == 7 and not corr.exists()  # the degraded-fit rule: the product misses the example
    assert "of the sculpt not reproduced" in err and "--allow-degraded" in err
    assert err.count("of the sculpt not reproduced") == 1  # once for the example, not once per group
    code, _, err = run("fit", rig.asset, examples, "-o", corr, "--deformer", rigs.DELTA_MUSH_SPEC, "--report", report,
                       "--allow-degraded", "--group", "main")  # one cardinal RBF: its shape is the inverse's offsets
    assert code == 0, err
    (ex,) = json.loads(report.read_text())["meshes"][0]["examples"]
    # the tube is one piece of 1,312 vertices: solved on its exact Jacobian, at the optimum of
    # the documented regularisation (coupled.UNREACHABLE_RIDGE), not stopped short of it
    assert ex["missed"] > 0 and ex["regime"].endswith(coupled.EXACT) and ex["at_optimum"]
    np.testing.assert_allclose(ex["unreachable_fraction"], share, rtol=0.1)  # measured 0.0809 against 0.0794
    assert {v // segments for v, _ in ex["worst_vertices"]} <= set(range(29, 38))
    assert all(residual <= ex["max_residual_rel"] for _, residual in ex["worst_vertices"])
    assert "DEGRADED" in err and "of the sculpt not reproduced" in err
    offsets = _blend_shape_offsets(str(corr))
    assert np.abs(offsets).max() <= OFFSET_BOUND * np.abs(rippled - base).max()  # measured 1.1x
    strict = tmp_path / "strict.usda"
    code, _, _ = run("fit", rig.asset, examples, "-o", strict, "--deformer", rigs.DELTA_MUSH_SPEC, "--strict",
                     "--allow-degraded")
    assert code == 7 and not strict.exists()


def _tube_and_small_pieces() -> tuple[np.ndarray, Topology]:
    """The tube and, around it, 24 separate triangles and 6 strips of 5 vertices (3 triangles):
    a character's small UV shells, which Delta Mush collapses and then rotates by their frames."""
    rest, topology = _tube()
    counts, indices, points = [topology.face_vertex_counts], [topology.face_vertex_indices], [rest]
    n = len(rest)
    rng = np.random.default_rng(7)
    for k in range(30):
        angle, x = 2.0 * np.pi * k / 30.0, float(rest[:, 0].min()) + (k + 0.5) / 30.0 * float(np.ptp(rest[:, 0]))
        radius = 1.15 * float(np.abs(rest[:, 1:]).max())
        centre = np.array([x, radius * np.cos(angle), radius * np.sin(angle)])
        size = 5 if k % 5 == 0 else 3
        corners = centre + 0.04 * rng.normal(size=(size, 3))
        faces = [[0, 1, 2]] if size == 3 else [[0, 1, 2], [1, 3, 2], [2, 3, 4]]
        points.append(corners)
        counts.append(np.full(len(faces), 3))
        indices.append((np.array(faces) + n).ravel())
        n += size
    return np.concatenate(points), Topology(np.concatenate(counts), np.concatenate(indices), n)


def _turned_tube_and_small_pieces():
    """The tube with small pieces behind a rigid turn and Delta Mush, and known smooth offsets
    (a bump at its middle): (rest, topology, chain, offsets)."""
    rest, topology = _tube_and_small_pieces()
    mush = DeltaMush(rest, topology)
    turn = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])

    def chain(points: np.ndarray) -> np.ndarray:
        return mush(points @ turn.T + 0.25)

    bump = np.exp(-((np.linalg.norm(rest - rest.mean(axis=0), axis=1) / 1.5) ** 2))
    return rest, topology, chain, 0.03 * bump[:, None] * np.array([0.2, 1.0, 0.5])


def _turned_tube_sculpt():
    """The turned tube's sculpt made through the chain from its known offsets, and what stage
    4 is given with it: (chain, rest, offsets, sculpt, adjacency, chain at rest, diagonal,
    float32 floor, sculpted vertices, tolerance)."""
    rest, topology, chain, truth = _turned_tube_and_small_pieces()
    target = chain(rest + truth)
    base = chain(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, target)
    atol = max(tol.INVERSE_RTOL * diagonal, floor)
    return chain, rest, truth, target, edge_adjacency(topology), base, diagonal, floor, idx, atol


def _stage_4(call, chain, rest, target, idx, begun, adjacency, blocks):
    """Stage 4 (``coupled._exact_pieces``) from ``begun`` through ``call``, and each sculpted
    vertex's residual checked by running the chain on rest + its offsets: (result, residual)."""
    res = coupled._exact_pieces(call, rest, target, idx, begun, adjacency, blocks)
    moved = rest.copy()
    moved[idx] += res.offsets
    return res, np.linalg.norm(chain(moved)[idx] - target[idx], axis=1)


#: Calls for the tube with small pieces (measured: 40, of which 3 x 5 probe the pieces; 72
#: without the small-piece stage, which needed the per-vertex polish at the end).
SMALL_PIECES_BUDGET = 48


def test_small_pieces_riding_on_the_rests_calls_end_where_they_end_alone(monkeypatch):
    """The small pieces' calls after the first ride on the rest's solve: their offsets are the
    ones their stage reaches on its own calls, to the bit (the pieces do not move each other),
    every sculpted vertex is within the tolerance, and the example takes fewer calls."""
    rest, topology, chain, truth = _turned_tube_and_small_pieces()
    target = chain(rest + truth)
    adjacency = edge_adjacency(topology)
    ridden = coupled.invert(chain, rest, target, neighbours=lambda: adjacency)
    monkeypatch.setattr(coupled, "SMALL_PIECES_RIDE", False)
    alone = coupled.invert(chain, rest, target, neighbours=lambda: adjacency)
    assert np.array_equal(ridden.indices, alone.indices) and not len(ridden.missed) and not len(alone.missed)
    small = np.concatenate([p.positions for p in pieces.small_pieces(adjacency, ridden.indices)])
    assert np.array_equal(ridden.offsets[small], alone.offsets[small])
    assert ridden.evaluations < alone.evaluations


def test_small_pieces_of_the_mesh_are_solved_by_their_own_jacobians():
    """Delta Mush after a rigid pose on a tube with small separate pieces, the sculpt made
    through the chain from a smooth offset (so an exact answer exists): the small pieces take
    their exact Jacobians (3 calls a vertex of the largest, shared by all), the tube the smooth
    start, and every sculpted vertex ends within the tolerance, checked by running the chain."""
    rest, topology, chain, truth = _turned_tube_and_small_pieces()
    target = chain(rest + truth)
    adjacency = edge_adjacency(topology)
    res = coupled.invert(chain, rest, target, neighbours=lambda: adjacency)
    base = chain(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, target)
    moved = rest.copy()
    moved[res.indices] += res.offsets
    residual = np.linalg.norm(chain(moved)[idx] - target[idx], axis=1)
    assert np.array_equal(res.indices, idx)
    assert "small pieces by their Jacobians" in res.regime
    assert residual.max() <= max(tol.INVERSE_RTOL * diagonal, floor)
    assert not len(res.missed)
    assert res.evaluations <= SMALL_PIECES_BUDGET


#: Calls for CesiumMan through LBS + Delta Mush (measured 187 and 189 at its two examples: 5
#: for the per-vertex solver's first calls, 1 for the small pieces' first, whose others ride on
#: the rest's calls (284 and 313 when they came first, 88 and 115 of them), 15 and 16 for the
#: smooth start, 1 for its blocks tried finely, 39 for Newton-Krylov, and 120 and 121 for its
#: large pieces on their own Krylov spaces, which the fast path leaves up to 10 and 15 times the
#: tolerance away; one Krylov space shared by them took 400 at the first
#: and missed at the second. Measured directions on trial, which share one space across the
#: pieces too, kept no step there in 10 calls: they are left out where more than one piece misses).
CESIUM_BUDGET = 230
#: The same with that stage left out, through the pieces' exact Jacobians (measured 439 and
#: 476 before the small pieces rode on the rest's calls: 270 measure the 251-vertex piece's
#: Jacobian on the vertices left above the tolerance and their 1-ring, coloured by two-fifths
#: of the chain's reach, as its pieces start within ``pieces.TRUNCATE_NEAR_WITHIN`` of the
#: tolerance: 3 calls a colour, 90 colours; 584 by half
#: the reach in index order (142 colours), 902 by the whole reach (248), 1,271 with every vertex
#: of a piece an unknown, 2,350 a vertex a call, 2,749 while the slower stages still ran before).
CESIUM_EXACT_BUDGET = 560


def _inverted_through_chain(case: characters.Case, skinning=None) -> tuple[InverseResult, np.ndarray, np.ndarray,
                                                                          float]:
    """``coupled.invert`` on a real character's example, and its check by running the chain on
    rest + offsets: (result, sculpted vertices, each one's residual, the fit's tolerance)."""
    res = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda: case.adjacency, skinning=skinning)
    diagonal, floor, idx = sculpted_vertices(case.rest, case.box(case.rest), case.sculpt)
    moved = case.rest.copy()
    moved[res.indices] += res.offsets
    residual = np.linalg.norm(case.box(moved)[idx] - case.sculpt[idx], axis=1)
    return res, idx, residual, max(tol.INVERSE_RTOL * diagonal, floor)


@pytest.mark.parametrize("example", [0, 1])
def test_cesiumman_through_delta_mush_reaches_every_vertex_with_each_piece_on_its_own_krylov_space(example,
                                                                                                    monkeypatch):
    """CesiumMan (the shipped DCC character, 138 pieces of the mesh) behind LBS + Delta Mush,
    its swelling sculpted through the chain, so an exact answer exists: the fast stages leave
    hundreds of its six large pieces' vertices at up to 15 times the tolerance (the directions
    they need pass the chain at 1e-3 of its gain). Each piece on its own Krylov space, one
    product of every piece a call, brings every sculpted vertex within the tolerance, checked
    by running the chain on rest + offsets, before the exact Jacobians are needed. Its misses
    lie on six pieces, so measured directions, one space for all of them, are not tried first."""
    trials: list[int | None] = []
    measured = coupled._measured

    def spied(*args, **kwargs):
        trials.append(kwargs.get("trial_rounds"))
        return measured(*args, **kwargs)

    monkeypatch.setattr(coupled, "_measured", spied)
    res, idx, residual, atol = _inverted_through_chain(characters.cesium()[example])
    assert all(rounds is None for rounds in trials), trials
    assert np.array_equal(res.indices, idx)
    assert res.regime.endswith(coupled.KRYLOV_PIECES), res.regime
    assert residual.max() <= atol  # measured 0.85 and 0.74 times the tolerance
    assert not len(res.missed)
    assert res.evaluations <= CESIUM_BUDGET


#: Calls an example of CesiumMan through LBS + Delta Mush where the skinning is known apart
#: (``fit``'s path): measured 45 and 46 (the whole region on the structured Jacobian from the
#: linearised start, turned with its smoothed 1-rings where its steps stall), against 56 and 57
#: with the operator refitted there from 15 products, and 97 and 124 through the small pieces'
#: exact Jacobians and the smooth start. The skinning's 4 calls count here (a plain callable):
#: 45 and 46 with the ring read as a gradient and two modes; ``fit`` reads them from the
#: chain's own calls (``ChainSkinning``: 41 and 42).
CESIUM_WHOLE_BUDGET = 55


@pytest.mark.parametrize("example", [0, 1])
def test_cesiumman_through_delta_mush_reaches_every_vertex_on_a_structured_jacobian(example):
    """With the skinning callable on its own, as ``fit`` gives it, CesiumMan's whole region,
    its small pieces (130 of the mesh's 138, up to 25 vertices) with the large ones, is solved on the model J = A S^s M
    (``solver.structured``) from the linearised start: 25 products of the chain fit its local
    operator, turned with its smoothed 1-rings where its steps stall, and every sculpted vertex comes within the
    tolerance, checked by running the chain on rest + offsets, in fewer calls than the small
    pieces' exact Jacobians alone would take (76)."""
    case = characters.cesium()[example]
    res, idx, residual, atol = _inverted_through_chain(case, skinning=case.box.skin)
    assert np.array_equal(res.indices, idx)
    assert res.regime.startswith("coupled, from the linearised start" + coupled.STRUCTURED), res.regime
    assert residual.max() <= atol
    assert not len(res.missed)
    assert res.evaluations <= CESIUM_WHOLE_BUDGET


#: Calls of CesiumMan@12 as ``fit`` runs it, the skinning read from the chain's own calls
#: (measured 41; 42 at @30).
CESIUM_FIT_BUDGET = 45


def test_the_skinnings_blocks_are_read_from_the_chains_own_calls():
    """``fit`` hands the solver the skinning as ``ChainSkinning``: the chain skins on the way
    to its deformers, so the skinning at the per-vertex solver's points (rest, every sculpted
    vertex moved along x, y, z) is read from those calls. On CesiumMan the offsets are the same
    to the bit as with the skinning run on its own, no skinning runs afresh, the example counts
    4 calls fewer, and its count is every call the box made for it."""
    case = characters.cesium()[0]
    alone = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda: case.adjacency,
                           skinning=case.box.skin)
    skinning = ChainSkinning(case.box)
    before = case.box.evaluations
    read = coupled.invert(case.box, case.rest, case.sculpt, neighbours=lambda: case.adjacency, skinning=skinning)
    assert read.regime.startswith("coupled, from the linearised start" + coupled.STRUCTURED), read.regime
    assert np.array_equal(read.offsets, alone.offsets) and not len(read.missed)
    assert skinning.fresh == 0
    assert read.evaluations == alone.evaluations - 4
    assert read.evaluations == case.box.evaluations - before
    assert read.evaluations <= CESIUM_FIT_BUDGET


def test_chain_skinning_runs_the_skinning_where_no_call_of_the_chain_was_made():
    """Points the chain was not called at are skinned afresh, counted in ``fresh``, with the
    same bits as the skinning alone; the box keeps only its latest calls."""
    case = characters.cesium()[0]
    skinning = ChainSkinning(case.box)
    moved = case.rest + 1e-3
    assert np.array_equal(skinning(moved), case.box.skin(moved)) and skinning.fresh == 1
    case.box(moved)
    assert np.array_equal(skinning(moved), case.box.skin(moved)) and skinning.fresh == 1
    for k in range(blackbox.REMEMBERED_CALLS):
        case.box(case.rest + 1e-3 * (k + 2))
    assert np.array_equal(skinning(moved), case.box.skin(moved)) and skinning.fresh == 2


#: The same where the whole-region stage does not apply (measured 97 and 124: 36 and 61 of them
#: the small pieces' own calls once the large ones finish on the structured Jacobian after the
#: smooth start; 187 and 189 without it).
CESIUM_STRUCTURED_BUDGET = 135


@pytest.mark.parametrize("example", [0, 1])
def test_cesiumman_finishes_the_smooth_start_on_a_structured_jacobian(example, monkeypatch):
    """Without the whole-region stage, CesiumMan's small pieces go by their exact Jacobians and
    the smooth start on its large pieces is finished on the structured model: every sculpted
    vertex within the tolerance, in about half the calls of the pieces' Krylov spaces."""
    monkeypatch.setattr(coupled, "_whole_structured", lambda *args, **kwargs: None)
    case = characters.cesium()[example]
    res, idx, residual, atol = _inverted_through_chain(case, skinning=case.box.skin)
    assert np.array_equal(res.indices, idx)
    assert "the rest coupled, from the smooth start" + coupled.STRUCTURED in res.regime, res.regime
    assert residual.max() <= atol  # measured 0.999 and 0.998 times the tolerance
    assert not len(res.missed)
    assert res.evaluations <= CESIUM_STRUCTURED_BUDGET


def test_the_structured_model_explains_delta_mushs_products():
    """On CesiumMan through the reference Delta Mush the fitted model (a local operator reading
    each output's ring as its own point, gradient and two quadratic modes; umbrella smoothing;
    the skinning's blocks) explains its own 25 products to within three times float32's noise
    on their differences (measured 1.7e-2 at rest; the noise alone ~6e-3), and Delta Mush's own
    10 smoothing steps explain them best (8 and 12: 4.5e-2 and 4.4e-2; 4: 0.13)."""
    case = characters.cesium()[0]
    base = case.box(case.rest)
    diagonal, _, idx = sculpted_vertices(case.rest, base, case.sculpt)
    call = Counted(case.box)
    offsets = np.zeros((len(idx), 3))
    directions, images = structured._products(call, case.rest, idx, offsets, base[idx], diagonal,
                                                     structured.PRODUCTS)
    assert call.calls == structured.PRODUCTS
    posed = coupled.blocks_at(case.box.skin, case.rest, idx, offsets, case.box.skin(case.rest)[idx],
                              tol.JACOBIAN_STEP_RTOL * diagonal)
    ring = (case.adjacency + sp.identity(len(case.rest), format="csr")).tocsr()
    groups = structured.region_pieces(case.adjacency, idx)
    misfit = {steps: structured._fit(case.rest, idx, posed, smoothed, ring, groups, directions, images, build=False)[1]
              for steps, smoothed in structured.smoothings(case.adjacency, idx, structured.SMOOTHING_STEPS)}
    assert misfit[10] <= 2e-2, misfit  # float32 outputs over a 1e-5 difference: ~6e-3; the ring's finer variation
    assert misfit[10] <= structured.MAX_MISFIT / 1.5  # its steps are tried, with a margin
    assert min(misfit, key=misfit.__getitem__) == 10 and min(v for s, v in misfit.items() if s != 10) > 2 * misfit[10]


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def test_the_turned_model_follows_a_rigid_turn_of_each_ring_and_never_spins_a_line():
    """The turn the whole-region stage makes where its steps stall (``structured._turned``):
    where an output's smoothed 1-ring turns rigidly by R, its local operator becomes R A R^T
    block by block, which is what a rotation-equivariant deformer's Jacobian does; where the
    ring lies on one line (a strip's vertex of valence 2), which shows no turn about itself, by
    the least rotation that takes the line where it went, not spun about it at random (1e-12:
    float64 round-off)."""
    rng = np.random.default_rng(3)
    fan = np.concatenate([[[0.0, 0.0, 0.0]], [[np.cos(t), np.sin(t), 0.1 * np.sin(3 * t)]
                                              for t in np.linspace(0, 2 * np.pi, 6, endpoint=False)]])
    line = np.array([[3.0, 0.0, 0.0], [4.0, 0.5, 0.0], [5.0, 1.0, 0.0]])
    points = np.concatenate([fan, line])
    edges = [(0, j) for j in range(1, 7)] + [(j, j % 6 + 1) for j in range(1, 7)] + [(7, 8), (8, 9)]
    rows, cols = np.array(edges).T
    adjacency = sp.csr_matrix((np.ones(2 * len(edges)), (np.r_[rows, cols], np.r_[cols, rows])), shape=(10, 10))
    ring = (adjacency + sp.identity(10, format="csr")).tocsr()
    idx = np.arange(10)
    local = [rng.standard_normal((3, 3 * (ring.indptr[v + 1] - ring.indptr[v]))) for v in idx]
    turn = _rotation(np.array([0.3, -0.5, 0.8]), 0.7)
    moved = points @ turn.T + np.array([0.2, -1.0, 0.5])
    turned = structured._turned(local, idx, ring, points, moved)
    for q in range(7):  # the fan: every ring turned rigidly
        blocks = local[q].reshape(3, -1, 3)
        expected = np.einsum("ab,btc,dc->atd", turn, blocks, turn).reshape(3, -1)
        assert np.allclose(turned[q], expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    before, after = line[2] - line[0], turn @ (line[2] - line[0])  # the line turned with the fan
    before, after = before / np.linalg.norm(before), after / np.linalg.norm(after)
    least = _rotation(np.cross(before, after), float(np.arccos(before @ after)))  # no turn about the line
    for q in (7, 8, 9):
        blocks = local[q].reshape(3, -1, 3)
        expected = np.einsum("ab,btc,dc->atd", least, blocks, least).reshape(3, -1)
        assert np.allclose(turned[q], expected, rtol=0, atol=1e-12 * np.abs(expected).max())


@pytest.mark.parametrize("example", [0, 1])
def test_cesiumman_through_delta_mush_reaches_every_vertex_on_its_pieces_exact_jacobians(example, monkeypatch):
    """The same sculpts with the Krylov stage left out: the pieces' exact Jacobians bring every
    sculpted vertex within the tolerance. At the second example, the rough Jacobians' steps
    left one vertex at 1.01 times the tolerance: an optimum over the few vertices measured
    again there is not the piece's, and the piece goes on until that vertex is within it."""
    monkeypatch.setattr(coupled, "KRYLOV_PIECES_CALLS", 0)
    res, idx, residual, atol = _inverted_through_chain(characters.cesium()[example])
    assert np.array_equal(res.indices, idx) and coupled.EXACT in res.regime
    assert coupled.KRYLOV_PIECES not in res.regime
    assert residual.max() <= atol  # measured 0.9977 times the tolerance at the second
    assert not len(res.missed)
    assert res.evaluations <= CESIUM_EXACT_BUDGET


#: Calls for the character fixture's 135 degree elbow with its blocks measured again finely
#: (measured 63: 29 for the first smooth start, which stalls 22 times the tolerance away in RMS,
#: 3 for the fine blocks, 31 for the smooth start again on them, which ends within the
#: tolerance; 131 on the per-vertex solver's blocks, below).
FINE_BLOCKS_BUDGET = 80
#: The same elbow on the per-vertex solver's blocks alone (measured 132: 58 for the smooth start
#: and Newton-Krylov, which keeps no step and leaves all 168 vertices of its arm above the
#: tolerance, 1 for the fine blocks' probe, 73 on measured directions that start from
#: Newton-Krylov's 24; 171 when they measured those again, 319 through the pieces' exact
#: Jacobians, 84 colours of its 168 vertices).
FOLDED_ARM_BUDGET = 150


def _folded_arm() -> characters.Case:
    return next(c for c in characters.whole_character() if "r_elbow" in c.name and "135 deg" in c.name)


def test_a_fold_whose_blocks_were_measured_across_it_is_started_again_on_fine_blocks():
    """The character fixture's arm bent 135 degrees behind LBS + Delta Mush, sculpted through the
    chain. The per-vertex solver's blocks, measured over 1e-2 of the diagonal, cross the fold's
    non-linearity (a few crease vertices' blocks are off by 80-100%), and the smooth start on
    them stalls far from the sculpt. The probe along x, y and z at a step 100 times smaller
    shows the blocks' prediction off by more than ``BLOCKS_DISAGREE``; on the blocks measured
    there the smooth start, run again, reaches every vertex within the tolerance (checked by
    running the chain) in under half the calls the coarse blocks' stages took."""
    res, _idx, residual, atol = _inverted_through_chain(_folded_arm())
    assert res.regime == "coupled, from the smooth start" + coupled.FINE_BLOCKS, res.regime
    assert residual.max() <= atol  # measured 0.73 times the tolerance
    assert res.evaluations <= FINE_BLOCKS_BUDGET


def test_a_piece_within_reach_of_itself_is_learnt_on_measured_directions_on_trial(monkeypatch):
    """The same elbow on the per-vertex solver's blocks (the fine blocks never taken):
    Newton-Krylov leaves every vertex of the 168-vertex piece above the tolerance, and the piece
    lies within the chain's reach of itself, so its exact Jacobian costs nearly a colour a
    vertex. Measured directions on trial keep their first round's step and go on: every vertex
    within the tolerance, checked by running the chain, in fewer calls than the exact Jacobian."""
    monkeypatch.setattr(coupled, "BLOCKS_DISAGREE", np.inf)
    res, _idx, residual, atol = _inverted_through_chain(_folded_arm())
    assert res.regime.endswith(coupled.MEASURED) and coupled.EXACT not in res.regime, res.regime
    assert coupled.FINE_BLOCKS not in res.regime
    assert residual.max() <= atol  # measured 0.93 times the tolerance
    assert res.evaluations <= FOLDED_ARM_BUDGET


def test_a_colouring_separates_its_colours_and_is_near_the_fewest_possible():
    """Stage 4's colourings (``pieces.colouring``, by ``pieces.dsatur``) on CesiumMan's
    251-vertex piece: no two vertices of one colour within twice the reach of each other
    (else a call's outputs mix their columns), and, since each colour is 3 calls, near the
    fewest any colouring can have: the vertices within ``reach`` edges of one vertex are all
    within twice it of each other, so each needs its own colour. At reach 5 the colouring
    meets that bound (130); at reach 4 it is within 10% of it (89 against 83; coloured in
    index order, 103)."""
    case = characters.cesium()[0]
    _, label = connected_components(case.adjacency, directed=False)
    piece_label = int(np.nonzero(np.bincount(label) == 251)[0][0])
    vertices = np.nonzero(label == piece_label)[0]
    piece = pieces.Piece(np.arange(len(vertices)), vertices)
    rings = shortest_path(case.adjacency[vertices][:, vertices], unweighted=True, directed=False)
    for reach, slack in ((5, 1.0), (4, 1.1)):
        plan = pieces.colouring(case.adjacency, piece, vertices, reach)
        for members in plan.classes:
            apart = rings[np.ix_(members, members)]
            assert np.all(apart[~np.eye(len(members), dtype=bool)] > 2 * reach)
        fewest = int((rings <= reach).sum(axis=1).max())
        assert fewest <= len(plan.classes) <= slack * fewest


def test_cesiummans_shipped_sculpts_end_at_an_optimum_with_bounded_offsets(run, tmp_path):
    """CesiumMan's own sculpts, made on the plain-skinned mesh as an artist makes them, through
    LBS + Delta Mush: no offset reproduces them (47% and 30% of the sculpt is detail the chain
    smooths away). The fit ends at the regularised optimum and says so once per example, and
    its offsets stay bounded: within OFFSET_BOUND of the sculpt's largest move (measured 2.9x;
    17x before pieces the chain cannot reproduce were solved on coupled.UNREACHABLE_RIDGE)."""
    asset = os.path.join(ROOT, "fixtures", "cesiumman", rigs.generate.CESIUM)
    examples = os.path.join(ROOT, "fixtures", "cesiumman", "cesiumman_examples.usda")
    corr, report = tmp_path / "c.usda", tmp_path / "r.json"
    code, _, err = run("fit", asset, examples, "-o", corr, "--deformer", rigs.DELTA_MUSH_SPEC, "--allow-degraded",
                       "--group", "main", "--report", report)  # one cardinal RBF: its shapes are the inverse's offsets
    assert code == 0, err
    assert err.count("at a least-squares optimum: the deformer chain reproduces no more of it from any nearby "
                     "offset") == 2, err
    found = json.loads(report.read_text())["meshes"][0]["examples"]
    missed = sum(ex["missed"] for ex in found)  # the summary's count says why, as each example's line does
    assert f"{missed} vertices missed the fit tolerance (out of the chain's reach {missed};" in err, err
    assert [ex["at_optimum"] for ex in found] == [True, True]
    assert all(0.2 < ex["unreachable_fraction"] < 0.6 for ex in found)  # measured 0.472 and 0.300
    # pieces far off the tolerance go on to the stronger ridge without a second Jacobian on the
    # objective's own: measured 2,693 and 1,480 calls (5,245 and 4,587 with it); after the
    # structured Jacobian's stage, 2,173 and 1,987; with the whole-region stage tried first
    # and given up, 2,237 and 2,063; with its refit for the change of the local operators,
    # 2,227 and 2,041; with the model turned with its 1-rings instead, 2,222 and 2,036
    assert all(ex["evaluations"] <= SHIPPED_BUDGET for ex in found)
    largest_move = max(float(np.abs(case.sculpt - case.box(case.rest)).max()) for case in characters.cesium(shipped=True))
    assert np.abs(_blend_shape_offsets(str(corr))).max() <= OFFSET_BOUND * largest_move


def test_pieces_exact_jacobians_reach_a_sculpt_in_batches(monkeypatch):
    """Stage 4 alone, from zero offsets, on the tube with small pieces (a sculpt made through
    Delta Mush after a rigid turn, so an exact answer exists), with its memory budget so small
    that the tube's Jacobian fills a batch and the small pieces take another: each batch is
    measured and solved from where the last left the offsets, and every sculpted vertex ends
    within the tolerance, checked by running the chain."""
    chain, rest, _, target, adjacency, base, diagonal, floor, idx, atol = _turned_tube_sculpt()
    found = pieces.small_pieces(adjacency, idx, pieces.EXACT_PIECE)
    tube = max(found, key=lambda p: len(p.positions))
    monkeypatch.setattr(pieces, "EXACT_ENTRIES", (3 * len(tube.positions)) ** 2)
    assert [len(b) for b in pieces.batches(found)] == [1, len(found) - 1]
    call = Counted(chain)
    blocks = coupled.chain_blocks(call, rest, base, idx, diagonal, floor)
    zero = InverseResult(idx, np.zeros((len(idx), 3)), np.linalg.norm(target[idx] - base[idx], axis=1),
                         np.full(len(idx), powell.MAX_CYCLES, dtype=np.int8), 0, diagonal, atol, 0.0)
    res, residual = _stage_4(call, chain, rest, target, idx, zero, adjacency, blocks)
    small = np.concatenate([p.positions for p in found if p is not tube])
    assert np.all(zero.residual[small] > atol)  # so the second batch was solved too
    assert residual.max() <= atol and not len(res.missed)
    # a batch whose Jacobian (a vertex a call, at most) would pass the stage's calls is not
    # started: with the small pieces first and 200 calls, the tube is left where it was, and
    # the result claims no optimum for it
    batches = pieces.batches
    monkeypatch.setattr(pieces, "batches", lambda found: list(reversed(batches(found))))
    monkeypatch.setattr(coupled, "EXACT_CALLS", 200)
    capped = coupled._exact_pieces(Counted(chain), rest, target, idx, zero, adjacency, blocks)
    assert not np.any(capped.offsets[tube.positions]) and np.all(capped.status[tube.positions] == powell.MAX_CYCLES)
    assert not capped.at_optimum and np.all(capped.status[small] == powell.CONVERGED)


def test_a_snapping_chain_on_small_pieces_is_not_called_an_optimum():
    """A chain whose outputs snap to a 1e-3 grid, on a mesh small enough for the pieces' exact
    Jacobians: its finite differences say nothing of its response at the scale of a step, so
    every step is cut. The solve must not claim an optimum there (the summary would tell the
    TD the deformer smooths the sculpt away): the vertices stay max_cycles and at_optimum is
    False."""
    rest, topology = _tube()
    mush = DeltaMush(rest, topology)
    turn = np.array([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])

    def chain(points: np.ndarray) -> np.ndarray:
        return np.round(mush(points @ turn.T + 0.25) / 1e-3) * 1e-3

    bump = np.exp(-((np.linalg.norm(rest - rest.mean(axis=0), axis=1) / 1.5) ** 2))
    target = mush((rest + 0.03 * bump[:, None] * np.array([0.2, 1.0, 0.5])) @ turn.T + 0.25) + 3e-4  # off the grid
    adjacency = edge_adjacency(topology)
    res = coupled.invert(chain, rest, target, neighbours=lambda: adjacency)
    assert coupled.EXACT in res.regime and len(res.missed) == len(res.indices)
    assert not res.at_optimum and set(res.missed_statuses) == {"max_cycles"}


def _measured_tube():
    """The tube under Delta Mush as one piece, every vertex sculpted, and the chain's reach
    through it (``pieces.measure_reach``)."""
    rest, topology = _tube()
    mush = DeltaMush(rest, topology)
    adjacency = edge_adjacency(topology)
    idx = np.arange(len(rest))
    (tube,) = pieces.small_pieces(adjacency, idx, pieces.EXACT_PIECE)
    where = [idx[tube.positions]]
    base = mush(rest)
    reach = pieces.measure_reach(mush, rest, base, adjacency, [tube], where, 1e-5)
    assert reach is not None
    return rest, mush, adjacency, idx, tube, where, base, reach


def test_a_coloured_jacobian_is_the_plain_one_in_fewer_calls():
    """The pieces' Jacobians coloured by the chain's measured reach (two vertices of a colour
    more than twice the reach apart, moved in one call) are the ones measured a vertex a call,
    to the bit (an output within reach of one moved vertex sees none of the others), in fewer
    calls; a reach that is too short shows as an output beyond it that moved, and the coloured
    measurement gives up rather than return a wrong Jacobian."""
    rest, mush, adjacency, idx, tube, where, base, reach = _measured_tube()
    assert 10 <= reach <= 12  # 10 smoothing steps; the frames' neighbours
    plan = pieces.colouring(adjacency, tube, idx, reach + pieces.REACH_MARGIN)
    coloured = pieces.jacobians(mush, rest, base, [tube], where, 1e-5, [plan])
    plain = pieces.jacobians(mush, rest, base, [tube], where, 1e-5)
    assert coloured is not None and plain is not None
    np.testing.assert_array_equal(coloured[0][0], plain[0][0])
    assert coloured[1] == 3 * len(plan.classes) < plain[1] == 3 * len(rest)
    short = pieces.colouring(adjacency, tube, idx, 3)
    assert pieces.jacobians(mush, rest, base, [tube], where, 1e-5, [short]) is None


def test_a_jacobian_over_some_vertices_is_those_columns_of_the_whole_one():
    """Where the stages leave a few of a piece's vertices above the tolerance, stage 4 takes
    only them and their 1-ring as unknowns: their columns, read on every sculpted vertex's
    output, coloured among themselves, are the whole Jacobian's columns to the bit, in as many
    calls as their own colours take (fewer than the whole piece's)."""
    rest, mush, adjacency, idx, tube, where, base, reach = _measured_tube()
    some = np.arange(0, len(rest), 7)[:12]  # a scattered few
    whole = pieces.jacobians(mush, rest, base, [tube], where, 1e-5)
    plan = pieces.colouring(adjacency, tube, idx, reach + pieces.REACH_MARGIN, some)
    part = pieces.jacobians(mush, rest, base, [tube], where, 1e-5, [plan], [where[0][some]])
    full_plan = pieces.colouring(adjacency, tube, idx, reach + pieces.REACH_MARGIN)
    assert whole is not None and part is not None
    columns = (3 * some[:, None] + np.arange(3)).ravel()
    assert part[0][0].shape == (3 * len(rest), 3 * len(some))
    np.testing.assert_array_equal(part[0][0], whole[0][0][:, columns])
    assert part[1] == 3 * len(plan.classes) < 3 * len(full_plan.classes)


def test_a_truncated_colouring_reads_each_output_as_its_nearest_moved_vertex():
    """Coloured by half the chain's reach, a piece's Jacobian takes far fewer calls; each
    output is read as the column of the nearest vertex its call moved, so where two moved
    vertices' reaches overlap a column holds a little of the other's: on the tube through
    Delta Mush, within 3% of the exact column (measured 1.4% of the whole, 2.4% at worst)."""
    rest, mush, adjacency, idx, tube, where, base, reach = _measured_tube()
    full = reach + pieces.REACH_MARGIN
    span = int(pieces.TRUNCATED_REACH * full)
    plan = pieces.colouring(adjacency, tube, idx, span, nearest=True)
    exact_plan = pieces.colouring(adjacency, tube, idx, full)
    rings = pieces._rings(adjacency, tube, np.arange(len(rest)))
    for members, owner in zip(plan.classes, plan.owner, strict=True):
        assert np.all(owner >= 0)  # every output has a column, however far its moved vertex
        np.testing.assert_array_equal(rings[owner, np.arange(len(rest))], rings[members].min(axis=0))
    rough = pieces.jacobians(mush, rest, base, [tube], where, 1e-5, [plan])
    exact = pieces.jacobians(mush, rest, base, [tube], where, 1e-5, [exact_plan])
    assert rough is not None and exact is not None
    assert rough[1] == 3 * len(plan.classes) < exact[1] / 2  # measured 252 calls against 684
    err = np.linalg.norm(rough[0][0] - exact[0][0], axis=0) / np.linalg.norm(exact[0][0], axis=0)
    assert 0.0 < err.max() <= 0.03


def _tube_near_its_answer(ripple: float = 0.0, share: float = 0.99):
    """Stage 4's start on the tube with small pieces through a rigid turn and Delta Mush: the
    sculpt made through the chain from known offsets (plus ``ripple`` times the tolerance of
    noise no offset reproduces), the offsets at ``share`` of the known ones (at them, with
    noise), so the RMS residual is within ``pieces.TRUNCATE_WITHIN`` of the tolerance (18.9
    and 25.6 times; at 0.997, 5.7 times), as the stages before leave a sculpt the chain
    reproduces."""
    chain, rest, truth, target, adjacency, base, diagonal, floor, idx, atol = _turned_tube_sculpt()
    target[idx] += ripple * atol * np.random.default_rng(3).normal(size=(len(idx), 3))
    start = (share if not ripple else 1.0) * truth[idx]
    moved = rest.copy()
    moved[idx] += start
    residual = np.linalg.norm(chain(moved)[idx] - target[idx], axis=1)
    blocks = coupled.chain_blocks(Counted(chain), rest, base, idx, diagonal, floor)
    begun = InverseResult(idx, start, residual, np.full(len(idx), powell.MAX_CYCLES, dtype=np.int8), 0, diagonal,
                          atol, 0.0)
    assert atol < np.sqrt(np.mean(residual**2)) <= pieces.TRUNCATE_WITHIN * atol
    return chain, rest, target, idx, begun, adjacency, blocks


@pytest.mark.parametrize("ripple", [0.0, 15.0])
def test_truncated_jacobians_end_where_exact_ones_do(monkeypatch, ripple):
    """Stage 4 with each piece's first Jacobian coloured by half the chain's reach ends where
    it ends with exact ones: a sculpt the chain reproduces within the tolerance everywhere, in
    fewer calls (measured 257 against 689); one with noise no offset reproduces at the same
    optimum, called one both ways, since what a truncated Jacobian leaves above the tolerance
    is measured again exactly: the objective within ``coupled.OPTIMUM_SHARE`` (1%, what the
    stage calls an optimum; measured 0.16%), the RMS residual within 0.5% (measured 0.08%)."""
    chain, rest, target, idx, begun, adjacency, blocks = _tube_near_its_answer(ripple)
    assert begun.rms_residual > pieces.TRUNCATE_NEAR_WITHIN * begun.atol  # coloured by half the reach
    rho = smoothstart.ridge(blocks)
    found = []
    for share in (pieces.TRUNCATED_REACH, 1.0):
        monkeypatch.setattr(pieces, "TRUNCATED_REACH", share)
        call = Counted(chain)
        res, residual = _stage_4(call, chain, rest, target, idx, begun, adjacency, blocks)
        found.append((call.calls, residual, res, float(np.sum(residual**2) + rho * np.sum(res.offsets**2))))
    (calls, residual, res, objective), (exact_calls, exact_residual, exact, exact_objective) = found
    if not ripple:
        assert residual.max() <= begun.atol and exact_residual.max() <= begun.atol
        assert calls < exact_calls / 2
    else:
        assert res.at_optimum and exact.at_optimum and len(res.missed) and len(exact.missed)
        assert abs(objective - exact_objective) <= coupled.OPTIMUM_SHARE * exact_objective
        rms, exact_rms = np.sqrt(np.mean(residual**2)), np.sqrt(np.mean(exact_residual**2))
        assert abs(rms - exact_rms) <= 5e-3 * exact_rms


def test_near_the_answer_a_rougher_colouring_reaches_the_tolerance_in_fewer_calls(monkeypatch):
    """A piece within ``pieces.TRUNCATE_NEAR_WITHIN`` of the tolerance when stage 4 starts has
    its first Jacobian coloured by ``pieces.TRUNCATED_REACH_NEAR`` of the chain's reach: on the
    tube 5.7 times away, every sculpted vertex within the tolerance (checked by running the
    chain), in fewer calls than coloured by half the reach (measured 185 against 257)."""
    chain, rest, target, idx, begun, adjacency, blocks = _tube_near_its_answer(share=0.997)
    assert begun.rms_residual <= pieces.TRUNCATE_NEAR_WITHIN * begun.atol
    found = []
    for share in (pieces.TRUNCATED_REACH_NEAR, pieces.TRUNCATED_REACH):
        monkeypatch.setattr(pieces, "TRUNCATED_REACH_NEAR", share)
        call = Counted(chain)
        res, residual = _stage_4(call, chain, rest, target, idx, begun, adjacency, blocks)
        assert residual.max() <= begun.atol and not len(res.missed)
        found.append(call.calls)
    assert found[0] < found[1]


def test_a_chord_step_is_the_regularised_least_squares_step_on_the_measured_jacobian():
    """Stage 4's chord steps solve ``|r - J s|^2 + rho |D + s|^2`` through the Cholesky factor of
    ``J^T J + rho I`` (``pieces.NormalEquations``), not an SVD of J: on the tube's measured
    Delta Mush Jacobian, at the ridges the solve uses (the objective's and the unreachable
    one's, from the chain's 3x3 blocks), the step is the augmented least-squares problem's own
    solution (numpy's lstsq on ``[J; sqrt(rho) I]``, which never forms the Gram matrix). The
    Gram matrix squares J's condition number, which the ridge bounds: here at 2.7e8 (J's
    largest singular value 1.05, the blocks' gain 0.064, rho 1e-6 of its square), so float64
    leaves up to ~6e-8 of the step (measured 1.2e-8, and 1.6e-12 on the unreachable ridge);
    allowed 1e-6."""
    rest, mush, _, _, tube, where, base, _ = _measured_tube()
    measured = pieces.jacobians(mush, rest, base, [tube], where, 1e-5)
    assert measured is not None
    jac = measured[0][0]
    blocks = np.array([jac[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(len(rest))])
    rng = np.random.default_rng(7)
    residual, offsets = rng.normal(size=len(jac)) * 1e-3, rng.normal(size=jac.shape[1]) * 1e-2
    normal = pieces.NormalEquations(jac)
    for rho in (smoothstart.ridge(blocks), smoothstart.ridge(blocks, coupled.UNREACHABLE_RIDGE)):
        step = normal.step(residual, offsets, rho)
        augmented = np.vstack([jac, np.sqrt(rho) * np.eye(jac.shape[1])])
        expected = np.linalg.lstsq(augmented, np.concatenate([residual, -np.sqrt(rho) * offsets]), rcond=None)[0]
        assert np.linalg.norm(step - expected) <= 1e-6 * np.linalg.norm(expected)


def test_results_that_leave_most_of_the_sculpt_are_ranked_by_their_misfit():
    """``coupled.invert`` keeps the best of its stages' results. Fewer vertices above the
    tolerance ranks first while the polish can take them; where every result leaves more (a
    sculpt mostly beyond the chain's reach), the count says nothing and the smaller sum of
    squared residuals wins: the 3k rig's plain-skinned sculpts kept Newton-Krylov from zero by
    the count, with offsets 27x the sculpt's move and a larger RMS."""
    n = 3 * coupled.POLISH_VERTICES

    def result(missed: int, size: float) -> InverseResult:
        residual = np.full(n, 1e-6)
        residual[:missed] = size
        status = np.where(residual > 1e-5, powell.STALLED, powell.CONVERGED).astype(np.int8)
        return InverseResult(np.arange(n), np.zeros((n, 3)), residual, status, 1, 1.0, 1e-5, 0.0)

    few, worse_few = result(coupled.POLISH_VERTICES, 2e-5), result(coupled.POLISH_VERTICES, 3e-5)
    many_small, many_large = result(n, 1e-4), result(2 * coupled.POLISH_VERTICES, 1e-3)
    assert min([many_large, many_small, worse_few, few], key=coupled._rank) is few
    assert min([many_large, many_small], key=coupled._rank) is many_small  # more vertices above it, less misfit
    assert min([worse_few, many_small], key=coupled._rank) is worse_few


def _plain_skinned(tmp_path_factory, elbow: float):
    """The 1.3k rig (one piece of 1,312 vertices) under LBS + Delta Mush, and the sculpt made on
    its plain LBS mesh at the ``elbow`` degree pose, as an artist makes it: (black box, rest,
    sculpt, edges, the sculpt's largest move)."""
    folder = str(tmp_path_factory.mktemp("plain"))
    poses_layer, poses = rigs.write_poses(folder)
    t = next(t for t, pose in poses.items() if pose["Elbow"][1] == elbow)
    chain = rigs.build(folder, "lbs+deltamush", "1.3k", {t: poses[t]}, poses_layer)
    plain = rigs.build(folder, "lbs", "1.3k", {t: poses[t]}, poses_layer)
    move = float(np.linalg.norm(plain.sculpts[t] - plain.blackbox(plain.scene(), t)(plain.rest), axis=1).max())
    scene = chain.scene()
    adjacency = edge_adjacency(rest_mesh(scene.stage, rigs.MESH)[1])
    return chain.blackbox(scene, t), chain.rest, plain.sculpts[t], adjacency, move


@pytest.fixture(scope="module")
def plain_skinned_60(tmp_path_factory):
    """The 60 degree elbow's (``_plain_skinned``): the example whose offsets reached 10.4x the
    sculpt's largest move before stage 4 took single pieces of this size."""
    return _plain_skinned(tmp_path_factory, 60.0)


#: Calls for the 1.3k rig's plain-skinned sculpt at the 20 degree elbow (measured 874; 2,035
#: where measured directions went on trial before stage 4).
PLAIN_20_BUDGET = 960


def test_a_sculpt_out_of_reach_is_not_tried_on_measured_directions_first(tmp_path_factory):
    """The 20 degree elbow's plain-skinned sculpt is out of the chain's reach (its optimum leaves
    190 times the tolerance). Measured directions on trial before stage 4 kept their first
    round's step there, a step towards that far optimum, and ran to their budget, leaving stage 4
    a worse start: 2,035 calls against 876, 89 s against 9. Only an example that Newton-Krylov
    leaves within ``pieces.TRUNCATE_WITHIN`` times the tolerance goes on trial."""
    box, rest, target, adjacency, _move = _plain_skinned(tmp_path_factory, 20.0)
    res = coupled.invert(box, rest, target, neighbours=lambda: adjacency)
    assert coupled.MEASURED not in res.regime and res.regime.endswith(coupled.EXACT) and res.at_optimum, res.regime
    assert res.evaluations <= PLAIN_20_BUDGET


def test_a_one_piece_mesh_sculpted_on_its_plain_skinning_ends_at_an_optimum(plain_skinned_60):
    """On a one-piece mesh small enough for stage 4 (pieces.EXACT_PIECE), a sculpt made on the
    plain-skinned mesh ends at the regularised optimum (the fit says the chain cannot reproduce
    it) with offsets within 2x the sculpt's largest move (measured 1.64x; 10.4x, not called an
    optimum, before)."""
    box, rest, target, adjacency, move = plain_skinned_60
    res = coupled.invert(box, rest, target, neighbours=lambda: adjacency)
    assert res.regime.endswith(coupled.EXACT) and res.at_optimum
    assert np.linalg.norm(res.offsets, axis=1).max() <= 2.0 * move


def test_a_piece_too_large_for_stage_4_keeps_its_offsets_bounded(plain_skinned_60, monkeypatch):
    """The same sculpt where the piece is beyond stage 4's reach (as a one-piece body of 3k-13k
    vertices is): the offsets stay within 2.5x the sculpt's move (measured 1.96x, RMS 5.66e-4
    of the diagonal against stage 4's optimum's 5.84e-4, which pays for its smaller offsets;
    10.4x before the out-of-reach stage on the machine the budgets were first measured on), and
    the result is not called an optimum."""
    monkeypatch.setattr(pieces, "EXACT_PIECE", 1000)
    box, rest, target, adjacency, move = plain_skinned_60
    res = coupled.invert(box, rest, target, neighbours=lambda: adjacency)
    assert not res.regime.endswith(coupled.EXACT) and not res.at_optimum
    assert np.linalg.norm(res.offsets, axis=1).max() <= 2.5 * move


def test_the_out_of_reach_stage_bounds_offsets_the_chain_does_not_see(plain_skinned_60):
    """Offsets grown where the chain does not look (a checkerboard around the 16-segment tube,
    which Delta Mush's step of 1/2 annihilates, ten times the sculpt's move) leave the residual
    as it was; the out-of-reach stage (``coupled._regularised``: Newton-Krylov from zero on the
    unreachable ridge) returns offsets within 2.5x the move, with a lower objective, not called
    an optimum."""
    box, rest, target, _adjacency, move = plain_skinned_60
    base = box(rest)
    diagonal, floor, idx = sculpted_vertices(rest, base, target)
    blocks = coupled.chain_blocks(box, rest, base, idx, diagonal, floor)
    ring, segment = np.divmod(idx, 16)
    checker = np.where((ring + segment) % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.0, 0.0, 10.0 * move])
    moved = rest.copy()
    moved[idx] += checker
    residual = np.linalg.norm(target[idx] - box(moved)[idx], axis=1)
    start = InverseResult(idx, checker, residual, np.full(len(idx), powell.STALLED, dtype=np.int8), 0, diagonal,
                          max(1e-6 * diagonal, floor), 0.0, regime="grown")
    assert coupled._out_of_bounds(start, target, base, blocks)
    call = Counted(box)
    kept = coupled._regularised(call, rest, target, base, idx, diagonal, floor, start, blocks, rtol=1e-6, started=0.0)
    rho = smoothstart.ridge(blocks, coupled.UNREACHABLE_RIDGE)

    def objective(result: InverseResult) -> float:
        return float(np.sum(result.residual**2) + rho * np.sum(result.offsets**2))

    assert kept.regime == "grown" + coupled.OUT_OF_REACH and not kept.at_optimum
    assert objective(kept) < objective(start) and np.linalg.norm(kept.offsets, axis=1).max() <= 2.5 * move


def test_the_summary_tells_a_sculpt_out_of_reach_from_a_solve_that_stopped():
    """The summary's line for an example that missed: at an optimum, the chain cannot reproduce
    the sculpt; short of one but far off (RMS at least pieces.REACHABLE_SLACK times the
    tolerance, where sculpts the chain can reproduce end within 2x), mostly what the chain
    cannot reproduce, with how far; short of one and near, the solver stopped."""
    from psdbake.console import _unreachable_line

    n = 10

    def result(size: float, optimum: bool) -> InverseResult:
        residual = np.full(n, size)
        status = np.full(n, powell.STALLED, dtype=np.int8)
        return InverseResult(np.arange(n), np.zeros((n, 3)), residual, status, 1, 1.0, 1e-5, 0.0, regime="coupled",
                             sculpt_rms=1e-2, at_optimum=optimum)

    assert _unreachable_line("x", result(1e-3, True)).endswith("at a least-squares optimum: the deformer chain "
                                                                "reproduces no more of it from any nearby offset")
    far = _unreachable_line("x", result(1e-3, False))
    assert far.endswith("stopped short of an optimum; at 100x the tolerance (RMS) it is mostly what the chain "
                        "cannot reproduce")
    assert _unreachable_line("x", result(2e-5, False)).endswith("; the solver stopped short of an optimum")
