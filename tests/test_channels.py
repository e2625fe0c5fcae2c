"""Client-safe channels (psdbake/model/channels.py): written weights in [0, 1], names of at most 63
bytes, and the same shape as the unclamped design."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import ROOT, bake, diagonal, fixture, generate, points, stage_of
from scipy.spatial.transform import Rotation

from psdbake import api
from psdbake.model.channels import MAX_NAME_BYTES, short_name, weight_range
from psdbake.model.rbf import MIN_DEGREE
from psdbake.model.weights import group_weights
from psdbake.settings import FitSettings

ASSET, EXAMPLES = fixture("bad", "good_asset.usda"), fixture("bad", "good_examples.usda")
ANIM = fixture("arm_anim.usda")


def _random_rotations(n: int, seed: int) -> Rotation:
    """Uniform rotations, plus the extremes: turns of nearly pi about random axes."""
    rng = np.random.default_rng(seed)
    uniform = Rotation.random(n, random_state=rng)
    axes = rng.normal(size=(n // 4, 3))
    far = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1, keepdims=True) * (np.pi - 1e-9))
    return Rotation.concatenate([uniform, far])


@pytest.mark.parametrize(("kernel", "degree", "space"), [
    ("gaussian", None, "rotationVector"), ("gaussian", 1, "rotationVector"), ("gaussian", None, "quaternion"),
    ("gaussian", 0, "swingTwist"), ("thin_plate_spline", None, "rotationVector"), ("cubic", None, "rotationVector"),
    ("multiquadric", None, "rotationVector"), ("inverse_quadratic", 1, "rotationVector"),
    ("inverse_multiquadric", 1, "rotationVector"), ("linear", None, "rotationVector"),
])
@pytest.mark.slow
def test_weight_bounds_hold_over_every_pose(kernel, degree, space):
    """weight_range bounds each corrective's weight over the whole rotation group: no sampled
    pose (20,000 uniform rotations per driver and turns of nearly pi) leaves it. The scales
    use it wherever it is within 2x of the sampled reach: then no pose at all exceeds them."""
    twist = (1.0, 0.0, 0.0) if space == "swingTwist" else None
    settings = FitSettings(group="main", kernel=kernel, pose_space=space, twist_axis=twist,
                           degree=degree if degree is not None else MIN_DEGREE.get(kernel))
    (m,) = api.fit(ASSET, [EXAMPLES], settings).meshes
    data = m.driver_data
    lo, hi = weight_range(data, {"main": data})
    d = len(data.drivers)
    samples = [_random_rotations(20_000, seed) for seed in range(d)]
    n = len(samples[0])
    # rotations relative to bind, driver-major per frame: (n * d)
    delta = Rotation.from_quat(np.stack([s.as_quat() for s in samples], axis=1).reshape(-1, 4))
    b = group_weights([("main", data)], lambda _data: delta, n)["main"]
    assert np.all(b >= lo - 1e-12) and np.all(b <= hi + 1e-12), (b.min(axis=0), lo, b.max(axis=0), hi)
    # and a usable bound: within 1000x of what the samples reach (interval arithmetic is loose
    # for the growing polyharmonic kernels, ~230x here for cubic; looseness costs no precision,
    # as a channel's float32 weight and offsets each keep their own relative precision)
    assert np.all(hi <= 1000 * np.maximum(b.max(axis=0), 1e-3))
    assert np.all(lo >= 1000 * np.minimum(b.min(axis=0), -1e-3))


@pytest.mark.slow
def test_scales_keep_sampled_poses_in_range_and_examples_well_above_zero(tmp_path):
    """The channel scales (channels.channel_scales): over 20,000 other sampled poses per driver
    (another seed than the fit's) every channel weight stays within [0, 1], and at each
    corrective's own example its channel weighs at least 0.2 (UsdSkel skips weights below
    1e-6), on the humanoid's whole default fit, combinations included; and over the humanoid's
    shot, one global group included (whose 16 drivers uniform SO(3) samples alone miss: its
    weights reached 3x such scales), eval warns of no channel beyond its scale."""
    asset, examples = fixture("humanoid", "humanoid.usda"), fixture("humanoid", "humanoid_examples.usda")
    result = api.fit(asset, [examples])
    groups = [(m.group, m.driver_data) for m in result.meshes]
    from psdbake.model.channels import channel_weights
    from psdbake.model.weights import sampled_ranges

    joints = result.meshes[0].joints
    poses = np.array([e.pose for m in result.meshes for e in m.examples])
    anchors = {j: poses[:, i] for i, j in enumerate(joints)}
    for m in result.meshes:
        data = m.driver_data
        lo, hi = sampled_ranges(groups, 20_000, anchors, seed=12345)[m.group]
        top = channel_weights(data, np.stack([lo, hi]))  # both extremes, per channel
        assert top.max() <= 1.0, (m.group, top.max())
        own = channel_weights(data, np.eye(len(data.shapes)))  # b = 1 at its own example, 0 elsewhere
        assert min(own[s, data.channel_columns == s].max() for s in range(len(data.shapes))) >= 0.2
    import warnings

    from psdbake.errors import PsdWarning

    for settings in (FitSettings(), FitSettings(group="main")):
        corr = str(tmp_path / "c.usda")
        api.write_correctives(api.fit(asset, [examples], settings), corr)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PsdWarning)
            (anim,) = api.evaluate(asset, corr, fixture("humanoid", "humanoid_anim.usda")).animations
        assert not [w for w in caught if issubclass(w.category, PsdWarning)]
        assert anim.weights[:, -anim.psd_channels:].max() <= 1.0


@pytest.mark.slow
def test_an_ill_conditioned_group_keeps_usable_channels(tmp_path):
    """32 examples on the 13k bench rig: the RBF system's condition number is ~4e7 and the
    interval bound of its weights ~3e6; far from its examples the RBF does reach +-170 (the
    sampled reach), so the scales follow that (2x): at most 336 here, every example's channel
    weighs at least 1/336, and the stack reproduces every example (points cache) within 1e-5
    of the diagonal. With the interval bound as scale a channel would weigh 4e-7 at its own
    example, which UsdSkel skips (measured: 4.9e-2 of the diagonal off)."""
    from benchmarks import rigs

    poses_layer, poses = rigs.write_poses(str(tmp_path), 32)
    rig = rigs.build(str(tmp_path), "lbs", "13k", poses, poses_layer)
    result = api.fit(rig.asset, [rig.examples], FitSettings(group="main"))  # one RBF over all 32
    (m,) = result.meshes
    _lo, hi = weight_range(m.driver_data, {m.group: m.driver_data})
    assert hi.max() > 1e4  # the loose bound this test is about
    assert np.abs(m.driver_data.channel_scales).max() < 1e3
    corr = str(tmp_path / "c.usda")
    api.write_correctives(result, corr)
    cache = api.points_cache_layer(api.evaluate(rig.asset, corr, poses_layer))
    from pxr import Sdf

    spec = Sdf.Path(rigs.MESH).AppendProperty("points")
    diag = diagonal(rig.sculpts[rig.times[0]])
    worst = max(float(np.abs(np.array(cache.QueryTimeSample(spec, t), dtype=np.float64) - rig.sculpts[t]).max())
                for t in rig.times)
    assert worst <= 1e-5 * diag


def test_a_pose_beyond_the_scales_is_written_as_is_and_warned(tmp_path, cli):
    """Scales edited 100x smaller (standing in for a pose beyond the sampled reach): eval
    warns, naming the channel and time, and writes the weight above 1, so UsdSkel still
    gives the corrected shape; nothing is clamped silently."""
    from pxr import Sdf, Vt

    result = api.fit(ASSET, [EXAMPLES], FitSettings(group="main"))
    corr = str(tmp_path / "c.usda")
    api.write_correctives(result, corr)
    layer = Sdf.Layer.FindOrOpen(corr)
    attr = layer.GetAttributeAtPath(Sdf.Path(generate.MESH).AppendProperty("psd:main:channelScales"))
    attr.default = Vt.DoubleArray([v / 100.0 for v in attr.default])
    layer.Save()
    weights = tmp_path / "w.usda"
    code, _, err = cli("eval", ASSET, corr, "--anim", ANIM, "-o", weights)
    assert code == 0 and "psdbake: warning:" in err and "beyond the [0, 1]" in err and "at time" in err
    w = Sdf.Layer.FindOrOpen(str(weights))
    path = Sdf.Path(generate.ANIM).AppendProperty("blendShapeWeights")
    assert max(max(w.QueryTimeSample(path, t)) for t in w.ListTimeSamplesForPath(path)) > 1.0


def test_written_weights_are_in_unit_range_and_names_fit(run, tmp_path):
    """Every psdbake channel weight in WEIGHTS is in [0, 1] (Blender's default slider range)
    and every channel name, BlendShape name included, is at most 63 bytes and unique, even
    for a group name that makes the readable name far longer; the short names are stable."""
    group = "a_group_name_long_enough_to_push_every_channel_past_sixty_three_bytes"
    names = []
    for k in range(2):
        corr, weights = tmp_path / f"c{k}.usda", tmp_path / f"w{k}.usda"
        assert run("fit", ASSET, EXAMPLES, "--group", group, "-o", corr, "-q")[0] == 0
        assert run("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "-q")[0] == 0
        stage = stage_of([str(weights), ANIM, str(corr), ASSET])
        anim = stage.GetPrimAtPath(generate.ANIM)
        channels = list(anim.GetAttribute("blendShapes").Get())
        attr = anim.GetAttribute("blendShapeWeights")
        w = np.array([attr.Get(t) for t in attr.GetTimeSamples()])
        assert w.min() >= 0.0 and w.max() <= 1.0
        assert len(set(channels)) == len(channels) >= 3
        assert all(len(c.encode()) <= MAX_NAME_BYTES and c.startswith(f"psd_{group[:20]}") for c in channels)
        mesh = stage.GetPrimAtPath(generate.MESH)
        shapes = [p.GetName() for p in mesh.GetChildren() if p.GetTypeName() == "BlendShape"]
        assert sorted(shapes) == sorted(channels)
        names.append(channels)
    assert names[0] == names[1]


def test_short_names():
    assert short_name("psd_neck_Geo_Body_00_pos") == "psd_neck_Geo_Body_00_pos"
    long_a, long_b = "psd_" + "x" * 80 + "_00_pos", "psd_" + "x" * 80 + "_00_neg"
    a, b = short_name(long_a), short_name(long_b)
    assert len(a.encode()) == len(b.encode()) == MAX_NAME_BYTES and a != b and a.startswith("psd_xxxx")
    assert short_name(long_a) == a  # stable
    assert len(short_name("psd_" + "é" * 60).encode()) <= MAX_NAME_BYTES  # cut on a character boundary


def test_channels_bake_like_the_unclamped_design():
    """BakeSkinning of the stack with client-safe channels equals the same fit written as one
    unclamped channel per corrective (a v2 layer of these examples, tests/data) at every
    frame of the shot, within 1e-6 of the diagonal (float32 offsets and weights: each channel
    carries scale x d and b / scale, rounded apart)."""
    import tempfile

    folder = tempfile.mkdtemp()
    result = api.fit(ASSET, [EXAMPLES], FitSettings(group="main"))
    v4 = os.path.join(folder, "v4.usda")
    api.write_correctives(result, v4)
    v2 = os.path.join(ROOT, "tests", "data", "correctives_v2.usda")
    out = {}
    for name, corr in (("v2", v2), ("v4", v4)):
        weights = api.write_weights(api.evaluate(ASSET, corr, ANIM), os.path.join(folder, f"w_{name}.usda"))
        stage = bake([weights, ANIM, corr, ASSET], 1.0, 48.0)
        out[name] = np.stack([points(stage, generate.MESH, float(t)) for t in range(1, 49)])
    diag = diagonal(out["v2"][0])
    assert np.abs(out["v4"] - out["v2"]).max() <= 1e-6 * diag
