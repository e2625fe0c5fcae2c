"""The library as a pipeline script uses it (``import psdbake``): what an outside audit found
going wrong there. A file rewritten between two fits in one process is read again; a degraded
fit is not written unless asked, as the command refuses it; paths may be ``pathlib.Path``; and
wrong argument types are a ``SettingError`` naming the parameter, not an AttributeError or a
C++ signature from deep inside."""

from __future__ import annotations

import pathlib
import shutil
import warnings

import numpy as np
import pytest
from conftest import fixture
from pxr import Sdf

import psdbake
from psdbake.errors import PsdWarning, SettingError, StrictError

HUMANOID = fixture("humanoid", "humanoid.usda")
EXAMPLES = fixture("humanoid", "humanoid_examples.usda")
ANIM = fixture("humanoid", "humanoid_anim.usda")
MESH = "/Humanoid/Geo/Body"


def _offsets(result) -> dict:
    return {key: inv.offsets.copy() for key, inv in result.solves.items()}


def _resculpted(path: pathlib.Path) -> None:
    """The examples with the first sculpt pushed 1% of a unit further out on its moved
    vertices (an artist's second pass), written to path."""
    layer = Sdf.Layer.OpenAsAnonymous(EXAMPLES)
    points = Sdf.Path(MESH).AppendProperty("points")
    first = layer.ListTimeSamplesForPath(points)[0]
    sculpt = np.array(layer.QueryTimeSample(points, first), dtype=np.float64)
    moved = np.linalg.norm(sculpt - sculpt.mean(axis=0), axis=1) > 0  # every vertex; the fit sees only the change
    sculpt[moved] *= 1.01
    layer.SetTimeSample(points, first, sculpt.astype(np.float32).tolist())
    layer.Export(str(path))


def test_a_file_rewritten_between_two_fits_is_read_again(tmp_path):
    """USD keeps one copy of each layer per process and a FitResult keeps its inputs open: the
    second fit got the first file's examples (13 where the file then held 11) and its CORRECTIVES
    recorded the new file's checksum. Now it fits what the file holds, as a fresh process would."""
    examples = tmp_path / "examples.usda"
    shutil.copyfile(EXAMPLES, examples)
    first = psdbake.fit(HUMANOID, [str(examples)])  # kept alive: its layers stay open
    _resculpted(examples)
    with warnings.catch_warnings():  # the whole body pushed out: said (points no moved joint skins), not asserted here
        warnings.simplefilter("ignore", PsdWarning)
        second = psdbake.fit(HUMANOID, [str(examples)])
        elsewhere = tmp_path / "never_opened.usda"
        shutil.copyfile(examples, elsewhere)
        fresh = psdbake.fit(HUMANOID, [str(elsewhere)])
    a, b, c = _offsets(first), _offsets(second), _offsets(fresh)
    assert a.keys() == b.keys()
    assert any(not np.array_equal(a[k], b[k]) for k in a), "the second fit saw the old sculpts"
    assert all(np.array_equal(b[k], c[(k[0], str(elsewhere), k[2])]) for k in b)


def test_a_degraded_fit_is_not_written_unless_asked(tmp_path):
    """The hinge under Delta Mush: the product misses its example through UsdSkel (degraded).
    The command exits 7 and writes nothing; the README's two library calls wrote it silently."""
    result = psdbake.fit(fixture("hinge", "hinge.usda"), [fixture("hinge", "hinge_examples.usda")],
                         psdbake.FitSettings(deformers=("psdbake.delta_mush:delta_mush",)))
    assert result.degraded
    out = tmp_path / "c.usda"
    with pytest.raises(StrictError, match=r"c.usda: not written: the product does not reproduce 1 of 1 .*allow_degraded"):
        psdbake.write_correctives(result, str(out))
    assert not out.exists()
    psdbake.write_correctives(result, str(out), allow_degraded=True)
    assert out.exists()


def test_paths_may_be_pathlib_paths_and_one_example_file_a_string(tmp_path):
    result = psdbake.fit(pathlib.Path(HUMANOID), EXAMPLES)  # one file, not a list of its characters
    out = tmp_path / "c.usda"
    psdbake.write_correctives(result, out)
    weights = psdbake.evaluate(pathlib.Path(HUMANOID), out, pathlib.Path(ANIM), frames=(1, 5))
    assert psdbake.write_weights(weights, tmp_path / "w.usda") == str(tmp_path / "w.usda")
    assert psdbake.describe(out)["kind"] == "correctives"


@pytest.mark.parametrize(("call", "names"), [
    (lambda r: psdbake.write_correctives("c.usda", r), "result 'str': must be the FitResult"),
    (lambda r: psdbake.write_weights(r, "w.usda"), "result 'FitResult': must be the WeightsResult"),
    (lambda r: psdbake.fit(HUMANOID, [EXAMPLES], {"kernel": "cubic"}), "settings 'dict': must be a psdbake.FitSettings"),
    (lambda r: psdbake.fit(HUMANOID, [EXAMPLES], jobs=0), "jobs 0: must be a whole number"),
    (lambda r: psdbake.fit(None, [EXAMPLES]), "asset 'NoneType': must be a file path"),
    (lambda r: psdbake.evaluate(HUMANOID, r, ANIM), "correctives 'FitResult': must be a file path"),
    (lambda r: psdbake.evaluate(HUMANOID, "c.usda", ANIM, frames="1:10"), "frames '1:10': must be \\(first, last\\)"),
    (lambda r: psdbake.FitSettings(sigma="1"), "sigma '1': must be a number"),
    (lambda r: psdbake.FitSettings(drivers=[1, 2]), "drivers \\[1, 2\\]: must be a list of names"),
])
def test_wrong_argument_types_are_setting_errors_naming_the_parameter(call, names):
    fitted = _FITTED.setdefault("r", psdbake.fit(HUMANOID, [EXAMPLES]))
    with pytest.raises(SettingError, match=names):
        call(fitted)


_FITTED: dict = {}


def test_one_driver_name_is_a_list_of_one():
    assert psdbake.FitSettings(drivers="L_Elbow").drivers == ("L_Elbow",)
