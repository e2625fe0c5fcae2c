"""psdbake compare: the report folder a person reads (HTML, figures, statistics)."""

from __future__ import annotations

import csv
import json
import os
from html.parser import HTMLParser

import numpy as np
import pytest
from conftest import fixture, run_cli
from test_fidelity import ANGLE_ATOL, _single_joint_rig

from psdbake import report

pytest.importorskip("matplotlib")

ASSET, EXAMPLES, ANIM = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda"), fixture("arm_anim.usda")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
METRIC_COLUMNS = [f"{k}_{s}" for k in ("forward_ssd", "inverse_ssd", "inverse_forward") for s in ("max", "mean")]


@pytest.fixture(scope="module")
def arm_report(tmp_path_factory):
    folder = tmp_path_factory.mktemp("arm") / "report"  # does not exist yet: compare creates it
    code, out, err = run_cli("compare", ASSET, EXAMPLES, "--anim", ANIM, "-o", folder)
    return folder, code, out, err


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []
        self.tags: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.links += [v for k, v in attrs if k in ("src", "href") and v]


@pytest.mark.slow
def test_compare_writes_the_report(arm_report):
    folder, code, out, err = arm_report
    assert code == 0, err
    assert "psdbake compare" in out and "index.html" in out
    names = sorted(os.listdir(folder))
    assert {"index.html", "correction_angle.png", "stats.csv", "stats.json"} <= set(names)
    views = [n for n in names if n.startswith("views_")]
    assert len(views) == 3
    assert not [n for n in names if n.startswith(".")]  # no temp files left behind
    assert sorted(json.loads((folder / "stats.json").read_text())["files"]) == names


def test_index_html_is_self_contained(arm_report):
    folder = arm_report[0]
    page = (folder / "index.html").read_text(encoding="utf-8")
    parser = _Links()
    parser.feed(page)
    assert "script" not in parser.tags
    assert "http://" not in page and "https://" not in page
    assert parser.links
    for link in parser.links:
        assert "://" not in link and not link.startswith(("/", "data:")), link
        assert (folder / link).is_file(), link
    images = [link for link in parser.links if link.endswith(".png")]
    assert "correction_angle.png" in images and len(images) == 4
    assert "CesiumMan" not in page  # credit only for the CesiumMan asset


def test_every_png_is_a_real_non_blank_image(arm_report):
    import matplotlib.image

    folder = arm_report[0]
    pngs = sorted(folder.glob("*.png"))
    assert len(pngs) == 4
    for path in pngs:
        assert path.read_bytes()[:8] == PNG_SIGNATURE, path.name
        pixels = matplotlib.image.imread(str(path))
        assert pixels.shape[0] > 100 and pixels.shape[1] > 100, path.name
        rgb = pixels[..., :3].reshape(-1, 3)
        assert rgb.std() > 0.05, path.name
        packed = np.round(rgb[::7] * 255).astype(np.uint32) @ np.array([65536, 256, 1], dtype=np.uint32)
        assert len(np.unique(packed)) > 50, path.name  # not a single flat colour


def test_stats_have_one_row_per_frame(arm_report):
    folder = arm_report[0]
    with open(folder / "stats.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    stats = json.loads((folder / "stats.json").read_text(encoding="utf-8"))
    assert len(rows) == 48 == len(stats["frames"])
    header = list(rows[0])
    assert header[0] == "time"
    assert [h for h in header if h.startswith("angle_rad:")] == [f"angle_rad:{d}" for d in stats["drivers"]]
    assert len([h for h in header if h.startswith("weight:")]) == 3
    for col in METRIC_COLUMNS:
        assert col in header and f"{col}_rel" in header
    assert [float(r["time"]) for r in rows] == [float(t) for t in range(1, 49)]
    diag = stats["diagonal"]
    for row, frame in zip(rows, stats["frames"], strict=True):
        for col in METRIC_COLUMNS:
            # stats.csv writes repr(float) and stats.json round-trips floats: the same float64
            # bit for bit, and *_rel is the same division (atol 0)
            assert float(row[col]) == pytest.approx(frame[col], rel=0, abs=0)
            assert float(row[f"{col}_rel"]) == pytest.approx(float(row[col]) / diag, rel=0, abs=0)
            assert float(row[col.replace("max", "mean")]) <= float(row[col.replace("mean", "max")]) + 1e-12
    # the bind pose: nothing to correct; elsewhere both PSDs correct
    assert float(rows[0]["inverse_ssd_max"]) < 1e-6 * diag
    assert max(float(r["inverse_ssd_max_rel"]) for r in rows) > 0.01
    assert stats["command"] == "compare" and stats["vertex_turn"]


@pytest.mark.slow
def test_rerun_replaces_its_own_files_and_drops_stale_views(run, tmp_path):
    asset, examples, anim = _single_joint_rig(tmp_path)
    out = tmp_path / "report"
    assert run("compare", asset, examples, "--anim", anim, "-o", out, "--views", "2,6")[0] == 0
    assert sorted(n for n in os.listdir(out) if n.startswith("views_")) == ["views_2.png", "views_6.png"]
    (out / "index.html").write_text("old")
    code, _, err = run("compare", asset, examples, "--anim", anim, "-o", out, "--views", "6,11")
    assert code == 0, err
    assert sorted(n for n in os.listdir(out) if n.startswith("views_")) == ["views_11.png", "views_6.png"]
    assert (out / "index.html").read_text(encoding="utf-8").startswith("<!DOCTYPE html>")


@pytest.mark.slow
def test_correction_angle_data_single_joint(run, tmp_path):
    """The figure's data on a quad bound to one joint: the inverse correction turns exactly by
    the joint's angle, the forward one not at all."""
    asset, examples, anim = _single_joint_rig(tmp_path)
    out = tmp_path / "report"
    code, stdout, err = run("compare", asset, examples, "--anim", anim, "-o", out, "--json")
    assert code == 0, err
    summary = json.loads(stdout)
    assert summary["vertex_turn"][0]["vertex"] == 3
    stats = json.loads((out / "stats.json").read_text(encoding="utf-8"))
    turn = stats["vertex_turn"][0]
    assert turn["vertex"] == 3 and turn["joint"] == "Root/Bend" and turn["reference_time"] == 11.0
    angles = np.array([f["angle_rad:Root/Bend"] for f in stats["frames"]])
    np.testing.assert_allclose(angles, np.radians(9.0 * np.arange(11)), atol=1e-6)
    inverse = np.array([np.nan if v is None else v for v in turn["inverse"]])
    forward = np.array([np.nan if v is None else v for v in turn["forward"]])
    live = ~np.isnan(inverse)
    assert live.sum() == len(angles) - 1  # no correction at the bind pose
    np.testing.assert_allclose(inverse[live], angles[-1] - angles[live], atol=ANGLE_ATOL)
    np.testing.assert_allclose(forward[live], 0.0, atol=ANGLE_ATOL)
    # the figure's reference lines: the joint's own turn, and the correction it carries (perpendicular to z)
    np.testing.assert_allclose(turn["joint_turn"], angles[-1] - angles, atol=1e-5)
    np.testing.assert_allclose(turn["carried_turn"], angles[-1] - angles, atol=1e-5)


def test_report_dir_that_is_a_file_is_refused(run, tmp_path):
    target = tmp_path / "report.txt"
    target.write_text("not a folder")
    code, _, err = run("compare", ASSET, EXAMPLES, "--anim", ANIM, "-o", target)
    assert code == 6
    assert err.startswith("psdbake: error: ") and len(err.strip().splitlines()) == 1
    assert "not a folder" in err
    assert target.read_text() == "not a folder"


def test_foreign_folder_is_refused_and_untouched(run, tmp_path):
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.txt").write_text("keep me")
    code, _, err = run("compare", ASSET, EXAMPLES, "--anim", ANIM, "-o", folder)
    assert code == 6 and "not written by psdbake compare" in err
    assert sorted(os.listdir(folder)) == ["notes.txt"]


@pytest.mark.parametrize(("args", "message"), [
    (("--views", "999"), "not a compared frame"),
    (("--views", "a,b"), "--views"),
    (("--vertex", "0"), "has no corrective"),
])
def test_bad_options_are_input_errors(run, tmp_path, args, message):
    code, _, err = run("compare", ASSET, EXAMPLES, "--anim", ANIM, "-o", tmp_path / "r", *args)
    assert code == 3 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()


def test_helpers():
    assert report.parse_views("12, 30,41") == (12.0, 30.0, 41.0)
    assert report.parse_views(None) is None
    assert [report.frame_token(t) for t in (12.0, 12.5, -3.0)] == ["12", "12.5", "-3"]


@pytest.mark.slow
def test_failed_rerun_leaves_the_previous_report_whole(run, tmp_path, monkeypatch):
    """The folder's files are one commit (atomic.Transaction): a run that fails after some
    files are drawn changes none of the previous report's files and leaves no temporaries."""
    from psdbake.report import figures

    asset, examples, anim = _single_joint_rig(tmp_path)
    out = tmp_path / "report"
    assert run("compare", asset, examples, "--anim", anim, "-o", out, "--views", "2,6")[0] == 0
    before = {name: (out / name).read_bytes() for name in os.listdir(out)}
    draw, drawn = figures.draw_views, []

    def fail_on_second_view(*args):
        drawn.append(args[-1])
        if len(drawn) == 2:
            raise report.ReportError("drawing failed")
        draw(*args)

    monkeypatch.setattr(figures, "draw_views", fail_on_second_view)
    code, _, err = run("compare", asset, examples, "--anim", anim, "-o", out, "--views", "6,11")
    assert code == 1 and "drawing failed" in err and len(drawn) == 2
    assert {name: (out / name).read_bytes() for name in os.listdir(out)} == before


def test_leftovers_of_a_killed_run_do_not_make_a_folder_foreign(tmp_path):
    """SIGKILL before the commit leaves only ``.psdbake-*.tmp*`` files: the folder is still ours."""
    from psdbake.errors import OutputError

    folder = tmp_path / "report"
    folder.mkdir()
    (folder / ".psdbake-abcd1234.tmp.png").write_bytes(b"partial")
    report.check_report_dir(str(folder))
    (folder / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="not written by psdbake compare"):
        report.check_report_dir(str(folder))
