"""psdbake.model.evaluate_weights: the documented formula as one function of psd: values and
joint transforms, with no USD in it (tests/test_layering.py checks psdbake.model loads no pxr),
giving exactly the weights ``psdbake eval`` writes."""

from __future__ import annotations

import numpy as np
from conftest import fixture, run_cli
from pxr import Sdf

from psdbake.model import evaluate_weights
from psdbake.usd.read import Scene

ASSET, EXAMPLES, ANIM = (fixture("humanoid", n) for n in ("humanoid.usda", "humanoid_examples.usda", "humanoid_anim.usda"))
ANIM_PRIM = "/Humanoid/Skel/Anim"


def test_evaluate_weights_gives_what_eval_writes(tmp_path):
    corr, weights = tmp_path / "c.usda", tmp_path / "w.usda"
    assert run_cli("fit", ASSET, EXAMPLES, "-o", corr, "-q")[0] == 0
    assert run_cli("eval", ASSET, corr, "--anim", ANIM, "-o", weights, "-q")[0] == 0
    scene = Scene([ANIM, str(corr), ASSET])
    (info,) = scene.skinned_meshes()
    groups = scene.driver_groups(info.path)
    times = np.arange(1.0, 101.0)
    local = np.array([scene.joint_local_transforms(info.path, float(t)) for t in times])
    got = evaluate_weights(groups, local, info.joints)
    layer = Sdf.Layer.FindOrOpen(str(weights))
    channels = list(layer.GetAttributeAtPath(f"{ANIM_PRIM}.blendShapes").default)
    path = Sdf.Path(ANIM_PRIM).AppendProperty("blendShapeWeights")
    written = np.array([layer.QueryTimeSample(path, float(t)) for t in times], dtype=np.float32)
    assert sorted(got) == sorted(channels) and len(channels) == 24
    for c, name in enumerate(channels):  # eval stores float32: the same float32 values, bit for bit
        assert np.array_equal(got[name].astype(np.float32), written[:, c]), name
    assert max(float(w.max()) for w in got.values()) > 0.4  # the shot does drive the correctives
