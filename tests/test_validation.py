"""Every layer psdbake writes passes pxr.UsdValidation (usdSkelValidators included),
alone and stacked over its asset."""

from __future__ import annotations

import pytest
from conftest import CESIUM, CESIUM_EXAMPLES, fixture
from pxr import Sdf, Usd, UsdValidation

ERROR = UsdValidation.ValidationErrorType.Error


@pytest.fixture(scope="module")
def context():
    registry = UsdValidation.ValidationRegistry()
    return UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())


def _errors(context, target) -> list[str]:
    return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(target) if e.GetType() == ERROR]


@pytest.mark.slow
@pytest.mark.parametrize("rig", ["arm_lbs", "cesiumman"])
def test_written_layers_validate(rig, run, tmp_path, context):
    if rig == "cesiumman":
        asset, examples, anim = CESIUM, CESIUM_EXAMPLES, CESIUM
    else:
        asset, examples, anim = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), fixture("arm_anim.usda")
    out = {k: tmp_path / f"{k}.usda" for k in ("to_sculpt", "corr", "weights", "cache", "shot")}
    assert run("pose", asset, "--anim", examples, "-o", out["to_sculpt"], "-q")[0] == 0
    assert run("fit", asset, examples, "-o", out["corr"], "-q")[0] == 0
    assert run("eval", asset, out["corr"], "--anim", anim, "-o", out["weights"], "--points-cache", out["cache"], "-q")[0] == 0
    assert run("stack", asset, out["corr"], anim, out["weights"], "-o", out["shot"])[0] == 0
    for name, path in out.items():
        assert _errors(context, Sdf.Layer.FindOrOpen(str(path))) == [], name
        if name != "shot":
            assert _errors(context, Usd.Stage.Open(str(path))) == [], name
    # stacked over the asset, psdbake adds no error to whatever the asset already has
    baseline = set(_errors(context, Usd.Stage.Open(asset)))
    assert set(_errors(context, Usd.Stage.Open(str(out["shot"])))) <= baseline
