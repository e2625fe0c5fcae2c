"""Client-safe channels (psdbake/channels.py): written weights in [0, 1], names of at most 63
bytes, and the same shape as the unclamped design."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import ROOT, bake, diagonal, fixture, generate, points, stage_of
from scipy.spatial.transform import Rotation

from psdbake import api
from psdbake.channels import MAX_NAME_BYTES, short_name, weight_range
from psdbake.rbf_model import MIN_DEGREE
from psdbake.settings import FitSettings
from psdbake.weights import group_weights

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
def test_weight_bounds_hold_over_every_pose(kernel, degree, space):
    """weight_range bounds each corrective's weight over the whole rotation group: no sampled
    pose (20,000 uniform rotations per driver and turns of nearly pi) leaves it. This is what
    keeps every written channel weight in [0, 1]."""
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
    v4 = api.write_correctives(result, os.path.join(folder, "v4.usda"))
    v2 = os.path.join(ROOT, "tests", "data", "correctives_v2.usda")
    out = {}
    for name, corr in (("v2", v2), ("v4", v4)):
        weights = api.write_weights(api.evaluate(ASSET, corr, ANIM), os.path.join(folder, f"w_{name}.usda"))
        stage = bake([weights, ANIM, corr, ASSET], 1.0, 48.0)
        out[name] = np.stack([points(stage, generate.MESH, float(t)) for t in range(1, 49)])
    diag = diagonal(out["v2"][0])
    assert np.abs(out["v4"] - out["v2"]).max() <= 1e-6 * diag
