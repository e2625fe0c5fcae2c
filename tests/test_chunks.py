"""Farm chunks for eval: 1,000 frames cut into 10 chunks, stitched by value clips, give
exactly (bit for bit) what one eval gives, through UsdSkel's own BakeSkinning."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, bake, fixture, generate, points, run_cli, stage_of
from pxr import Sdf, Usd, UsdValidation

from psdbake.farm import plan as chunks
from psdbake.fitting import rbf_fit as rbf

ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
FRAMES, SIZE = 1000, 100
ANIM_PRIM = generate.ANIM


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """CORRECTIVES fitted by the CLI, a 1,000-frame ANIM, one eval of it and one in 10 chunks."""
    d = tmp_path_factory.mktemp("chunks")
    corr, anim = d / "corr.usda", d / "anim.usda"
    assert run_cli("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    generate.write_animation(str(anim), generate.shot_poses(FRAMES))
    (d / "one").mkdir()
    (d / "farm").mkdir()
    single, single_cache = d / "one" / "weights.usda", d / "one" / "cache.usda"
    assert run_cli("eval", ASSET, corr, "--anim", anim, "-o", single, "--points-cache", single_cache, "-q")[0] == 0
    manifest, cache = d / "farm" / "weights.usda", d / "farm" / "cache.usda"
    assert run_cli("eval", ASSET, corr, "--anim", anim, "-o", manifest, "--points-cache", cache,
                   "--frames", f"1:{FRAMES}", "--chunk-size", SIZE, "-q")[0] == 0
    return {"dir": d, "corr": corr, "anim": anim, "single": single, "single_cache": single_cache,
            "manifest": manifest, "cache": cache}


def _bake_all(layers) -> np.ndarray:
    """UsdSkel.BakeSkinning of the stack at frames 1..FRAMES: (frames, points, 3) float32."""
    stage = bake([str(p) for p in layers], 1, FRAMES)
    return np.stack([points(stage, generate.MESH, float(t), np.float32) for t in range(1, FRAMES + 1)])


@pytest.mark.slow
def test_ten_chunks_bake_exactly_like_one_eval(shot):
    names = sorted(os.listdir(shot["manifest"].parent))
    weights_chunks = [n for n in names if n.startswith("weights.f")]
    assert weights_chunks == [f"weights.f{lo:04d}-{lo + SIZE - 1:04d}.usda" for lo in range(1, FRAMES, SIZE)]
    base = [shot["anim"], shot["corr"], ASSET]
    one = _bake_all([shot["single"], *base])
    farm = _bake_all([shot["manifest"], *base])
    assert one.shape == (FRAMES, len(one[0]), 3)
    assert np.array_equal(one, farm)
    # the correctives do act in this shot: the baked points are not plain skinning
    plain = _bake_all(base)
    assert np.abs(one - plain).max() > 1e-3 * np.ptp(one[0], axis=0).max()

    # the weights themselves, through the clip stage: every frame and subframes at chunk boundaries
    stages = stage_of([shot["single"], *base]), stage_of([shot["manifest"], *base])
    a, b = (s.GetAttributeAtPath(f"{ANIM_PRIM}.blendShapeWeights") for s in stages)
    order = [list(s.GetAttributeAtPath(f"{ANIM_PRIM}.blendShapes").Get()) for s in stages]
    assert order[0] == order[1] and len(order[0]) >= 3
    times = [float(t) for t in range(1, FRAMES + 1)] + [100.25, 100.5, 100.999, 500.5, 999.75]
    for t in times:
        assert np.array_equal(np.array(a.Get(t)), np.array(b.Get(t))), t
    assert [float(t) for t in b.GetTimeSamples()] == [float(t) for t in range(1, FRAMES + 1)]


def test_points_cache_manifest_gives_the_single_cache(shot):
    one, farm = Usd.Stage.Open(str(shot["single_cache"])), Usd.Stage.Open(str(shot["cache"]))
    assert farm.GetPrimAtPath("/Arm").GetTypeName() == "Xform"  # the retyping lives in the manifest
    for name in ("points", "extent"):
        a = one.GetAttributeAtPath(f"{generate.MESH}.{name}")
        b = farm.GetAttributeAtPath(f"{generate.MESH}.{name}")
        for t in [*range(1, FRAMES + 1), 300.5]:
            assert np.array_equal(np.array(a.Get(t)), np.array(b.Get(t))), (name, t)


@pytest.mark.slow
def test_farm_tasks_write_the_same_bytes(shot, tmp_path):
    """Chunks by their own processes (at once, racing on the manifests) = the one-run files.
    Three of the ten tasks (first, middle, last): each process spends ~1 s importing USD."""
    env = {**os.environ, "PYTHONPATH": ROOT}
    # the inputs where the shot has them relative to its outputs: each layer records its inputs' relative paths
    corr, anim = shutil.copy(shot["corr"], tmp_path), shutil.copy(shot["anim"], tmp_path)
    tmp_path = tmp_path / "farm"
    tmp_path.mkdir()
    out, cache = tmp_path / "weights.usda", tmp_path / "cache.usda"
    procs = [
        subprocess.Popen([sys.executable, "-m", "psdbake", "eval", ASSET, str(corr), "--anim", str(anim),
                          "-o", str(out), "--points-cache", str(cache), "--frames", f"1:{FRAMES}",
                          "--chunk-size", str(SIZE), "--chunk", str(k), "-q"], env=env, stderr=subprocess.PIPE)
        for k in (1, 6, 10)
    ]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err.decode()
    ours = sorted(os.listdir(tmp_path))
    assert ours == sorted(f"{kind}{part}.usda" for kind in ("weights", "cache")
                          for part in ("", ".clipmanifest", ".f0001-0100", ".f0501-0600", ".f0901-1000"))
    _, mismatch, errors = filecmp.cmpfiles(tmp_path, shot["manifest"].parent, ours, shallow=False)
    assert (mismatch, errors) == ([], [])
    # asset paths are relative: the folder can move and still resolve its chunks
    moved = tmp_path / "moved"
    moved.mkdir()
    for name in ours:
        os.rename(tmp_path / name, moved / name)
    stages = Usd.Stage.Open(str(shot["single_cache"])), Usd.Stage.Open(str(moved / "cache.usda"))
    a, b = (s.GetAttributeAtPath(f"{generate.MESH}.points") for s in stages)
    for t in (1.0, 550.0, 1000.0):
        assert np.array_equal(np.array(a.Get(t)), np.array(b.Get(t))), t


def test_clip_manifest_is_what_usd_generates(shot):
    folder = shot["manifest"].parent
    layers = [Sdf.Layer.FindOrOpen(str(folder / n)) for n in sorted(os.listdir(folder)) if n.startswith("weights.f")]
    generated = Usd.ClipsAPI.GenerateClipManifestFromLayers(layers, ANIM_PRIM)
    ours = Sdf.Layer.FindOrOpen(str(folder / "weights.clipmanifest.usda"))

    def declared(layer) -> list[tuple]:
        found = []
        layer.Traverse("/", lambda p: found.append(p) if p.IsPropertyPath() else None)
        return sorted((str(p), str(layer.GetAttributeAtPath(p).typeName), layer.GetAttributeAtPath(p).variability,
                       layer.GetAttributeAtPath(p).HasDefaultValue()) for p in found)

    assert declared(ours) == declared(generated) == [
        (f"{ANIM_PRIM}.blendShapeWeights", "float[]", Sdf.VariabilityVarying, False)]


def test_manifests_validate(shot, run, tmp_path):
    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    error = UsdValidation.ValidationErrorType.Error

    def errors(target) -> list[str]:
        return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(target) if e.GetType() == error]

    folder = shot["manifest"].parent
    for name in ("weights.usda", "weights.clipmanifest.usda", "cache.usda", "cache.clipmanifest.usda"):
        assert errors(Sdf.Layer.FindOrOpen(str(folder / name))) == [], name
        assert errors(Usd.Stage.Open(str(folder / name))) == [], name
    view = tmp_path / "shot.usda"  # stacked over the asset, the manifest adds no error to the asset's own
    assert run("stack", ASSET, shot["corr"], shot["anim"], shot["manifest"], "-o", view)[0] == 0
    assert set(errors(Usd.Stage.Open(str(view)))) <= set(errors(Usd.Stage.Open(ASSET)))


def test_authored_fractional_samples_and_negative_frames(shot, tmp_path, run):
    """No --frames: the ANIM's own samples (here half frames from -2) are cut; names stay plain."""
    anim = tmp_path / "anim.usda"
    poses = generate.shot_poses(11)
    generate.write_animation(str(anim), {t / 2 - 2.5: p for t, p in poses.items()})  # -2, -1.5, ..., 3
    single, manifest = tmp_path / "one.usda", tmp_path / "w.usda"
    assert run("eval", ASSET, shot["corr"], "--anim", anim, "-o", single, "-q")[0] == 0
    code, out, err = run("eval", ASSET, shot["corr"], "--anim", anim, "-o", manifest, "--chunk-size", 4, "--json")
    assert code == 0, err
    assert sorted(n for n in os.listdir(tmp_path) if n.startswith("w.f")) == [
        "w.f0000-0001p5.usda", "w.f0002-0003.usda", "w.fm0002-m0000p5.usda"]
    summary = json.loads(out)  # --json lists what was written
    assert [(c["chunk"], c["first"], c["last"], c["frames"], os.path.basename(c["weights"])) for c in summary["chunks"]] == [
        (1, -2.0, -0.5, 4, "w.fm0002-m0000p5.usda"), (2, 0.0, 1.5, 4, "w.f0000-0001p5.usda"),
        (3, 2.0, 3.0, 3, "w.f0002-0003.usda")]
    assert summary["chunk_count"] == 3 and summary["output"] == str(manifest)
    assert summary["clip_manifest"] == str(tmp_path / "w.clipmanifest.usda")
    base = [anim, shot["corr"], ASSET]
    stages = stage_of([single, *base]), stage_of([manifest, *base])
    a, b = (s.GetAttributeAtPath(f"{ANIM_PRIM}.blendShapeWeights") for s in stages)
    assert a.GetTimeSamples() == b.GetTimeSamples() and len(a.GetTimeSamples()) == 11
    for t in [*a.GetTimeSamples(), -0.25, 0.75]:
        assert np.array_equal(np.array(a.Get(t)), np.array(b.Get(t))), t


@pytest.mark.parametrize(("args", "says"), [
    (["--chunk-size", "0"], "--chunk-size 0: must be at least 1 frame"),
    (["--chunk-size", "-3"], "--chunk-size -3: must be at least 1 frame"),
    (["--chunk", "2"], "--chunk needs --chunk-size"),
    (["--chunk-size", "100", "--chunk", "11", "--frames", "1:1000"], "--chunk 11: out of range: 1000 frame(s) in chunks"),
    (["--chunk-size", "100", "--chunk", "0", "--frames", "1:1000"], "numbered 1..10"),
    (["--chunk-size", "20", "--chunk", "4"], "--chunk 4: out of range: 48 frame(s) in chunks of 20 make 3"),
])
def test_bad_chunk_options(args, says, shot, run, tmp_path):
    out = tmp_path / "w.usda"
    code, _, err = run("eval", ASSET, shot["corr"], "--anim", fixture("arm_anim.usda"), "-o", out, *args)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("psdbake: error: ") and says in err, err
    assert os.listdir(tmp_path) == []


def test_plan_and_names():
    plan = chunks.plan_chunks(np.arange(-12.0, 1000.0), 250)
    assert [len(c.times) for c in plan.chunks] == [250, 250, 250, 250, 12]
    names = [os.path.basename(chunks.chunk_path("w.usda", plan, c)) for c in plan.chunks]
    assert names == ["w.fm0012-0237.usda", "w.f0238-0487.usda", "w.f0488-0737.usda", "w.f0738-0987.usda",
                     "w.f0988-0999.usda"]
    assert chunks.frame_label(123456.25, 4) == "123456p25" and chunks.frame_label(-0.1, 4) == "m0000p1"


@pytest.mark.parametrize("rows", [1, 2, 3, 7, 100, 101])
def test_rbf_weights_do_not_depend_on_how_many_frames_come_together(rows):
    """BLAS rounds a row differently with the number of rows (measured: 1 row in 3 differs for
    3-row calls); psdbake's product must not, or a chunk boundary would change weights."""
    rng = np.random.default_rng(7)
    model = rbf.fit_cardinal(rng.normal(size=(30, 12)), list(range(1, 30)), [str(i) for i in range(30)], degree=1)
    x = rng.normal(size=(505, 12))
    whole = model.weights(x)
    parts = np.concatenate([model.weights(x[i : i + rows]) for i in range(0, len(x), rows)])
    assert np.array_equal(whole, parts)
    assert np.abs(whole - _basis(model, x) @ model.coefficients).max() < 1e-12  # the same sum, BLAS-rounded


def _basis(model: rbf.CardinalRbf, x: np.ndarray) -> np.ndarray:
    from scipy.spatial.distance import cdist

    xd = x[:, model.dims]
    basis = rbf.KERNELS[model.kernel](model.epsilon * cdist(xd, model.centers))
    poly = np.prod(((xd - model.shift) / model.scale)[:, None, :] ** model.powers[None], axis=2)
    return np.concatenate([basis, poly], axis=1)
