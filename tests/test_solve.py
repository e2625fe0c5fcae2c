"""Per-fit reading (``psdbake.solver.solve``, ``api.fit``): each input read once, nothing kept after.

A mesh's rest points and shading are read once per fit, not once per example (at 1M points
the topology behind the shading took 0.13 s an example), and the fit's result keeps the input
layers open so that writing CORRECTIVES parses no input again; both die with their owner.
"""

from __future__ import annotations

import gc
import shutil

import numpy as np
from conftest import fixture
from pxr import Sdf

from psdbake import api
from psdbake.solver import solve

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")


def test_rest_points_and_shading_are_read_once_per_fit(monkeypatch):
    reads = []
    real = solve.read_mesh_shading

    def counted(prim, label="", **options):
        reads.append(str(prim.GetPath()))
        return real(prim, label, **options)

    monkeypatch.setattr(solve, "read_mesh_shading", counted)
    result = api.fit(ASSET, [EXAMPLES])
    examples = [e for m in result.meshes for e in m.examples]
    assert len(examples) >= 3 and reads == [result.meshes[0].mesh]  # one read for every example and the note
    assert solve.cached_rest.cache_info().currsize == 0 and solve.cached_shading.cache_info().currsize == 0
    assert solve.cached_scene.cache_info().currsize == 0


def test_cached_rest_points_are_read_only():
    rest = solve.cached_rest(ASSET, "/Arm/Geo/Tube")
    try:
        assert not rest.flags.writeable  # shared by every example of the mesh
        np.testing.assert_array_equal(rest, solve.cached_scene((ASSET,)).rest_points("/Arm/Geo/Tube"))
    finally:
        solve.clear_caches()


def test_the_result_keeps_the_inputs_open_until_it_is_dropped(tmp_path):
    asset, examples = (shutil.copy(f, tmp_path) for f in (ASSET, EXAMPLES))  # open nowhere else
    result = api.fit(asset, [examples])
    assert {asset, examples} <= {layer.realPath for layer in result.input_layers}
    assert Sdf.Layer.Find(asset) is not None  # write_correctives finds it open: no second parse
    out = str(tmp_path / "corr.usda")
    api.write_correctives(result, out)
    del result
    gc.collect()
    assert Sdf.Layer.Find(asset) is None and Sdf.Layer.Find(examples) is None
    assert Sdf.Layer.FindOrOpen(out) is not None
