"""psdbake batch: jobs file parsing, chunk expansion, ordering from files, and runs on the local
pool and on a real dask.distributed LocalCluster (byte-identical outputs, a worker killed mid-job)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import fixture, run_cli

from psdbake import farm
from psdbake.cli import cli
from psdbake.errors import InputError, PsdError

pytestmark = pytest.mark.slow  # make test-fast leaves this module out (make test runs it)


ASSET, EXAMPLES = fixture("arm_lbs.usda"), fixture("arm_lbs_examples.usda")
POSES, ANIM = fixture("arm_poses.usda"), fixture("arm_anim.usda")
UNSCULPTED = fixture("bad", "examples_unsculpted.usda")
HUMANOID, HUMANOID_EXAMPLES = fixture("humanoid", "humanoid.usda"), fixture("humanoid", "humanoid_examples.usda")
HUMANOID_ANIM = fixture("humanoid", "humanoid_anim.usda")

# pose (independent) | two correctives groups fitted into one layer (read-modify-write, in file order)
# -> eval cut into 3 chunk tasks (the shot's 100 frames and a points cache: the slowest tasks) -> stack
PIPELINE = f"""
[defaults]
asset = "{HUMANOID}"

[[pose]]
anim = "{HUMANOID_EXAMPLES}"
output = "out/to_sculpt.usda"

[[fit]]
examples = ["{HUMANOID_EXAMPLES}"]
group = "L_Elbow"
driver = ["L_Elbow"]
output = "out/correctives.usda"

[[fit]]
examples = ["{HUMANOID_EXAMPLES}"]
group = "R_Elbow"
driver = ["R_Elbow"]
output = "out/correctives.usda"

[[eval]]
correctives = "out/correctives.usda"
anim = "{HUMANOID_ANIM}"
frames = "1:100"
chunk_size = 34
output = "out/weights.usda"
points_cache = "out/cache.usda"

[[stack]]
output = "out/shot.usda"
layers = ["{HUMANOID}", "out/correctives.usda", "{HUMANOID_ANIM}", "out/weights.usda"]
"""
OUTPUTS = (
    "to_sculpt.usda", "correctives.usda", "shot.usda",
    *(f"{name}{part}.usda" for name in ("weights", "cache")
      for part in ("", ".clipmanifest", ".f0001-0034", ".f0035-0068", ".f0069-0100")),
)
TASKS = 7  # pose, 2 fits, 3 eval chunks, stack
COMMANDS = {name: cli.commands[name] for name in farm.COMMANDS}  # what psdbake batch passes: the CLI is the schema


def load_jobs(path: str, allow_deformers: bool = False) -> farm.Batch:
    return farm.load_jobs(path, COMMANDS, allow_deformers=allow_deformers)


def jobs_file(folder: Path, text: str) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "jobs.toml"
    path.write_text(text)
    return str(path)


def outputs(folder: Path) -> dict[str, bytes]:
    return {name: (folder / "out" / name).read_bytes() for name in OUTPUTS}


def no_temps(folder: Path) -> None:
    left = [f for f in os.listdir(folder) if ".tmp" in f]
    assert not left, f"temporary files left behind: {left}"


# --- parse, expand, order ------------------------------------------------------------------------


def test_keys_become_the_command_line_checked_by_click(tmp_path):
    path = jobs_file(tmp_path, """
[defaults]
asset = "rig/asset.usda"
kernel = "cubic"        # fit takes it, eval does not: not given to eval
deformer = ["d.py:f"]

[[fit]]
examples = ["-odd name.usda", "b.usda"]
output = "out/c.usda"
driver = "Elbow"
twist-axis = [1, 0, -1.5]
pose_space = "swingTwist"
no_rest_example = true
clamp_weights = false
degree = -1
sigma = 0.25

[[eval]]
correctives = "out/c.usda"
anim = "shot.usda"
output = "out/w.usda"
""")
    jobs = load_jobs(path, allow_deformers=True)
    fit, ev = jobs.tasks
    assert fit.args == (
        "--output=out/c.usda", "--driver=Elbow", "--kernel=cubic", "--sigma=0.25", "--degree=-1", "--no-rest-example",
        "--pose-space=swingTwist", "--twist-axis", "1", "0", "-1.5", "--deformer=d.py:f",
        "--", "rig/asset.usda", "-odd name.usda", "b.usda",  # a positional starting with '-' goes after '--'
    )
    assert ev.args == ("rig/asset.usda", "out/c.usda", "--anim=shot.usda", "--output=out/w.usda", "--deformer=d.py:f")
    assert fit.cwd == ev.cwd == str(tmp_path)  # paths stay as written; jobs run in the jobs file's folder
    assert fit.outputs == ("out/c.usda",) and fit.writes == (str(tmp_path / "out" / "c.usda"),)
    assert ev.needs == (fit.key,) and fit.needs == ()
    # click parses each command line to the values the TOML gave
    ctx = cli.commands["fit"].make_context("fit", list(fit.args))
    assert ctx.params["twist_axis"] == (1.0, 0.0, -1.5) and ctx.params["examples"] == ("-odd name.usda", "b.usda")
    assert ctx.params["no_rest_example"] is True and ctx.params["degree"] == -1


def test_order_comes_from_the_files(tmp_path):
    path = jobs_file(tmp_path, """
[[stack]]                  # listed first, reads what every other job writes
output = "view.usda"
layers = ["a.usda", "c.usda", "anim.usda", "w.usda"]

[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "anim.usda"
output = "w.usda"

[[fit]]
asset = "a.usda"
examples = ["ex.usda"]
output = "c.usda"

[[fit]]                    # the same CORRECTIVES layer again: after the first, but not skipped if it fails
asset = "a.usda"
examples = ["ex2.usda"]
output = "c.usda"

[[pose]]                   # writes what the first fit reads
asset = "a.usda"
anim = "poses.usda"
output = "ex.usda"

[[pose]]                   # independent of everything
asset = "a.usda"
anim = "poses.usda"
output = "other.usda"
""")
    tasks = load_jobs(path).tasks
    labels = [t.label for t in tasks]
    assert labels == ["[[pose]] #1", "[[fit]] #1", "[[fit]] #2", "[[eval]] #1", "[[stack]] #1", "[[pose]] #2"]
    key = {t.label: t.key for t in tasks}
    by = {t.label: t for t in tasks}
    assert by["[[fit]] #1"].needs == (key["[[pose]] #1"],)
    assert by["[[fit]] #2"].needs == () and by["[[fit]] #2"].after == (key["[[fit]] #1"],)
    assert by["[[eval]] #1"].needs == (key["[[fit]] #2"],)  # the last writer of c.usda, after the first
    assert by["[[stack]] #1"].needs == (key["[[fit]] #2"], key["[[eval]] #1"])
    assert by["[[pose]] #2"].needs == by["[[pose]] #2"].after == ()
    assert len(set(key.values())) == len(tasks)
    assert [t.key for t in load_jobs(path).tasks] == [t.key for t in tasks]  # deterministic keys


def test_pose_jobs_sharing_an_obj_dir_run_one_after_the_other(tmp_path):
    """--obj-dir is an output (a folder): two pose jobs writing one never run at once."""
    path = jobs_file(tmp_path, """
[[pose]]
asset = "a.usda"
anim = "poses.usda"
output = "ex1.usda"
obj_dir = "sculpt"

[[pose]]
asset = "a.usda"
anim = "poses.usda"
output = "ex2.usda"
obj_dir = "sculpt"
""")
    first, second = load_jobs(path).tasks
    assert second.after == (first.key,) and str(tmp_path / "sculpt") in first.writes


def test_a_missing_input_or_a_job_reading_its_own_output_is_refused_before_anything_runs(tmp_path):
    """A typo in a path failed that job (and skipped its readers) hours into a farm run, and a
    dry run printed it as fine: now both refuse it first (exit 3, naming the job and the file)."""
    (tmp_path / "a.usda").write_text("#usda 1.0\n")
    path = jobs_file(tmp_path, """
[[fit]]
asset = "a.usda"
examples = ["sculpted.usda"]
output = "c.usda"

[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "shto.usda"
output = "w.usda"
""")
    for extra in ([], ["--dry-run"]):
        code, _, err = run_cli("batch", path, *extra)
        assert code == 3 and err.count("psdbake: error:") == 1, err
        assert "[[fit]] #1: reads sculpted.usda, which is not there and no job writes" in err, err
    (tmp_path / "sculpted.usda").write_text("#usda 1.0\n")
    code, _, err = run_cli("batch", path, "--dry-run")
    assert code == 3 and "[[eval]] #1: reads shto.usda" in err, err  # c.usda is written by the fit: fine
    (tmp_path / "shto.usda").write_text("#usda 1.0\n")
    assert run_cli("batch", path, "--dry-run")[0] == 0
    own = jobs_file(tmp_path / "own", """
[[eval]]
asset = "../a.usda"
correctives = "w.usda"
anim = "../shto.usda"
output = "w.usda"
""")
    code, _, err = run_cli("batch", own, "--dry-run")
    assert code == 3 and "reads w.usda, which it also writes" in err, err


def test_two_jobs_writing_one_file_are_refused_unless_chunks_of_a_shot(tmp_path):
    """Two evals into one WEIGHTS layer ran one after the other and the later silently replaced
    the earlier's work: refused when the jobs file is read (exit 3, naming both jobs). The
    chunks of one shot, written as separate jobs (chunk = K), share its manifests by design."""
    two = """
[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "shot1.usda"
output = "w.usda"

[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "shot2.usda"
output = "w.usda"
"""
    with pytest.raises(InputError, match=r"\[\[eval\]\] #2: writes w.usda, as \[\[eval\]\] #1 does: the later would "
                                         r"replace"):
        load_jobs(jobs_file(tmp_path / "two", two))
    chunks = "".join(f"""
[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "shot.usda"
frames = "1:10"
chunk_size = 5
chunk = {k}
output = "w.usda"
""" for k in (1, 2))
    first, second = load_jobs(jobs_file(tmp_path / "chunks", chunks)).tasks
    assert second.after == (first.key,)


MANIFESTS = ("out/w.usda", "out/w.clipmanifest.usda", "out/p.usdc", "out/p.clipmanifest.usdc")


def test_eval_chunks_are_cut_as_eval_cuts_them():
    parts = farm.eval_chunks("out/w.usda", "out/p.usdc", "1:10", 4)
    assert parts == [
        (1, ("out/w.f0001-0004.usda", "out/p.f0001-0004.usdc", *MANIFESTS)),
        (2, ("out/w.f0005-0008.usda", "out/p.f0005-0008.usdc", *MANIFESTS)),
        (3, ("out/w.f0009-0010.usda", "out/p.f0009-0010.usdc", *MANIFESTS)),
    ]
    assert [k for k, _ in farm.eval_chunks("w.usda", None, "0.5:1000.5", 100)] == list(range(1, 11))
    assert farm.eval_chunks("w.usda", None, "-5:4", 5)[0][1] == ("w.fm0005-m0001.usda", "w.usda", "w.clipmanifest.usda")
    with pytest.raises(PsdError, match="no whole frame"):
        farm.eval_chunks("w.usda", None, "1.2:1.8", 10)


def test_a_chunked_eval_is_one_task_per_chunk(tmp_path):
    path = jobs_file(tmp_path, """
[[eval]]
asset = "a.usda"
correctives = "c.usda"
anim = "shot.usda"
output = "w.usda"
frames = "1:250"
chunk_size = 100

[[stack]]
output = "view.usda"
layers = ["a.usda", "c.usda", "shot.usda", "w.usda"]
""")
    tasks = load_jobs(path).tasks
    chunks = tasks[:3]
    assert [t.label for t in chunks] == ["[[eval]] #1 chunk 1/3", "[[eval]] #1 chunk 2/3", "[[eval]] #1 chunk 3/3"]
    for k, t in enumerate(chunks, start=1):
        assert t.args[-3:] == ("--frames=1:250", "--chunk-size=100", f"--chunk={k}")
        assert t.needs == t.after == ()  # the chunks run in parallel (each writes the same manifest)
        ctx = cli.commands["eval"].make_context("eval", list(t.args))
        assert ctx.params["chunk"] == k and ctx.params["chunk_size"] == 100
    assert chunks[2].outputs == ("w.f0201-0250.usda", "w.usda", "w.clipmanifest.usda")
    assert tasks[3].needs == tuple(t.key for t in chunks)  # the reader waits for every chunk
    head = '[[eval]]\nasset = "a.usda"\ncorrectives = "c.usda"\nanim = "s.usda"\noutput = "w.usda"\n'
    for extra, message in [("chunk_size = 10", "chunk_size needs frames"), ('frames = "1:5"\nchunk_size = 0', "at least 1")]:
        with pytest.raises(InputError, match=r"jobs.toml \[\[eval\]\] #1: .*" + message):
            load_jobs(jobs_file(tmp_path / "bad", head + extra))


GOOD_FIT = '[[fit]]\nasset = "a.usda"\nexamples = ["e.usda"]\noutput = "out/c.usda"\n'


def good_fit_jobs(folder: Path) -> str:
    """GOOD_FIT as a jobs file beside stand-ins for its inputs (batch refuses missing ones first)."""
    path = jobs_file(folder, GOOD_FIT)
    for name in ("a.usda", "e.usda"):
        (folder / name).write_text("#usda 1.0\n")
    return path


@pytest.mark.parametrize("text, message", [
    ("[[fitt]]\nasset = 'a'\n", r"jobs.toml: unknown table \[fitt\]"),
    (GOOD_FIT + "[fit2]\n", r"unknown table \[fit2\]"),
    ("[fit]\nasset = 'a.usda'\n", r"jobs.toml \[fit\]: jobs are an array of tables: write \[\[fit\]\]"),
    (GOOD_FIT * 2 + "kernal = 'cubic'\n", r"jobs.toml \[\[fit\]\] #2: unknown key 'kernal' for psdbake fit"),
    (GOOD_FIT + "quiet = true\n", r"\[\[fit\]\] #1: unknown key 'quiet' for psdbake fit \(psdbake batch sets it\)"),
    (GOOD_FIT * 2 + '[[fit]]\nasset = "a.usda"\noutput = "o.usda"\n', r"\[\[fit\]\] #3: missing required key 'examples'"),
    (GOOD_FIT + "sigma = 'wide'\n", r"\[\[fit\]\] #1: sigma must be a number, got 'wide'"),
    (GOOD_FIT + "jobs = 1.5\n", r"\[\[fit\]\] #1: jobs must be an integer"),
    (GOOD_FIT + "strict = 'yes'\n", r"\[\[fit\]\] #1: strict must be true or false"),
    (GOOD_FIT + "twist_axis = [1, 0]\n", r"\[\[fit\]\] #1: twist_axis must be a list of 3 values"),
    (GOOD_FIT + "kernel = 'gauss'\n", r"\[\[fit\]\] #1: Invalid value for '--kernel': 'gauss' is not one of"),
    (GOOD_FIT + "jobs = 0\n", r"\[\[fit\]\] #1: Invalid value for '--jobs' / '-j': 0 is not in the range"),
    ("[defaults]\nkernal = 'cubic'\n" + GOOD_FIT, r"jobs.toml \[defaults\]: unknown key 'kernal'"),
    ("[[fit]]\nasset = \n", r"jobs.toml: not valid TOML: "),
    (GOOD_FIT + '[[eval]]\nasset = "a.usda"\ncorrectives = "c.usda"\nanim = "s.usda"\noutput = "out/c.usda"\n',
     r"\[\[eval\]\] #1: writes out/c.usda, as \[\[fit\]\] #1 does"),
    ('[[pose]]\nasset = "a.usda"\nanim = "p.usda"\noutput = "out/x.usda"\n'  # x <- y <- x
     '[[pose]]\nasset = "a.usda"\nanim = "out/x.usda"\noutput = "out/y.usda"\n'
     '[[fit]]\nasset = "a.usda"\nexamples = ["out/y.usda"]\noutput = "out/p.usda"\n'
     '[[eval]]\nasset = "a.usda"\ncorrectives = "out/p.usda"\nanim = "out/p.usda"\noutput = "p.usda"\n',
     r"read each other's outputs in a cycle: \[\[eval\]\] #1, \[\[fit\]\] #1, \[\[pose\]\] #1, \[\[pose\]\] #2"),
])
def test_bad_jobs_file_is_one_line_exit_3_and_nothing_runs(run, tmp_path, text, message):
    path = jobs_file(tmp_path, text)
    code, out, err = run("batch", path)
    assert code == 3 and out == "", err
    assert err.count("\n") == 1 and err.startswith(f"psdbake: error: {tmp_path}/") and "Traceback" not in err
    assert re.search(message, err), err
    assert not (tmp_path / "out").exists()  # nothing ran, no folder made


def test_missing_jobs_file(run, tmp_path):
    code, _, err = run("batch", tmp_path / "nope.toml")
    assert code == 3 and err.startswith("psdbake: error: ") and "nope.toml: cannot read" in err


# --- local runs ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def local_run(tmp_path_factory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("batch") / "local"
    path = jobs_file(folder, PIPELINE)
    summary = farm.run_batch(load_jobs(path), workers=2).summary()
    return folder, summary


def test_local_batch_equals_the_commands_run_directly(local_run, run, tmp_path, monkeypatch):
    folder, summary = local_run
    assert (summary["ok"], summary["failed"], summary["skipped"], summary["lost"]) == (TASKS, 0, 0, 0)
    direct = tmp_path / "direct"  # the same depth as the batch folder: stack's relative paths agree
    (direct / "out").mkdir(parents=True)
    monkeypatch.chdir(direct)
    for job in summary["jobs"]:  # exactly the command lines the batch ran, typed in its folder
        code, _, err = run(*shlex.split(job["command"])[1:])
        assert code == 0, err
    assert outputs(direct) == outputs(folder)
    no_temps(folder / "out")


def test_failed_job_skips_its_dependents_and_names_itself(run, tmp_path):
    path = jobs_file(tmp_path, f"""
[defaults]
asset = "{ASSET}"

[[fit]]                     # nothing sculpted: psdbake fit exits 4
asset = "{fixture("bad", "good_asset.usda")}"
examples = ["{UNSCULPTED}"]
output = "out/c.usda"

[[eval]]
correctives = "out/c.usda"
anim = "{ANIM}"
output = "out/w.usda"

[[pose]]                    # independent: still runs
anim = "{POSES}"
output = "out/to_sculpt.usda"
""")
    code, out, err = run("batch", path, "--json")
    assert code == 4, err
    lines = err.strip().splitlines()
    assert any(ln.startswith(f"psdbake: error: {path} [[fit]] #1 failed (exit 4): ")
               and "no example differs from plain skinning" in ln for ln in lines), err
    assert lines[-1] == f"psdbake: error: {path}: 1 job(s) failed: [[fit]] #1; 1 skipped"
    summary = json.loads(out)
    status = {j["job"]: (j["status"], j["exit_code"]) for j in summary["jobs"]}
    assert status == {"[[fit]] #1": ("failed", 4), "[[eval]] #1": ("skipped", None), "[[pose]] #1": ("ok", 0)}
    assert (tmp_path / "out" / "to_sculpt.usda").exists()
    assert not (tmp_path / "out" / "c.usda").exists() and not (tmp_path / "out" / "w.usda").exists()


def test_a_failed_earlier_writer_still_skips_the_readers(run, tmp_path):
    """A reader needs only the last job writing a file (edges linear in the jobs), yet is skipped
    when an earlier writer of that file failed: the failure travels along the writers' chain."""
    path = jobs_file(tmp_path, f"""
[[fit]]                     # nothing sculpted: psdbake fit exits 4
asset = "{fixture("bad", "good_asset.usda")}"
examples = ["{UNSCULPTED}"]
group = "first"
output = "out/c.usda"

[[fit]]                     # the same layer, then: runs after #1, and succeeds
asset = "{ASSET}"
examples = ["{EXAMPLES}"]
group = "second"
output = "out/c.usda"

[[eval]]
asset = "{ASSET}"
correctives = "out/c.usda"
anim = "{ANIM}"
output = "out/w.usda"
""")
    by = {t.label: t for t in load_jobs(path).tasks}
    assert by["[[eval]] #1"].needs == (by["[[fit]] #2"].key,)
    code, out, err = run("batch", path, "--json")
    assert code == 4, err
    status = {j["job"]: (j["status"], j["error"]) for j in json.loads(out)["jobs"]}
    assert status["[[fit]] #2"] == ("ok", None)
    assert status["[[eval]] #1"] == ("skipped", "needs [[fit]] #1, which did not succeed")
    assert not (tmp_path / "out" / "w.usda").exists()


def test_a_dry_run_of_25000_jobs_is_linear_and_small(tmp_path):
    """25,000 jobs writing one file (a 614 kB jobs file): every job waited for every earlier one,
    312 million pairs (19.6 GB); now a chain. Peak memory of the whole ``batch --dry-run``,
    measured in a fresh process: under 500 MB."""
    path = tmp_path / "jobs.toml"
    for name in ("a.usda", "e.usda"):  # the inputs must be there (batch checks before a dry run too)
        (tmp_path / name).write_text("#usda 1.0\n")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write('[defaults]\nasset = "a.usda"\nexamples = ["e.usda"]\noutput = "c.usda"\n')
        fh.writelines(f'[[fit]]\ngroup = "g{i}"\n' for i in range(25_000))
    script = ("import resource, subprocess, sys\n"
              "done = subprocess.run([sys.argv[1], 'batch', sys.argv[2], '--dry-run', '--json'], capture_output=True)\n"
              "tasks = __import__('json').loads(done.stdout)\n"
              "print(done.returncode, len(tasks), max(len(t['after']) + len(t['needs']) for t in tasks),"
              " resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    psdbake = os.path.join(os.path.dirname(sys.executable), "psdbake")
    done = subprocess.run([sys.executable, "-c", script, psdbake, str(path)], capture_output=True, text=True, check=True)
    code, jobs, most_edges, peak_kib = map(int, done.stdout.split())
    assert (code, jobs, most_edges) == (0, 25_000, 1)
    assert peak_kib < 500 * 1024, f"peak RSS {peak_kib / 1024:.0f} MiB"


def _children(pid: int) -> list[int]:
    """Child processes of pid, started by any of its threads (jobs start from pool threads)."""
    found = []
    for tid in os.listdir(f"/proc/{pid}/task") if os.path.exists(f"/proc/{pid}/task") else ():
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as fh:
                found += [int(c) for c in fh.read().split()]
        except FileNotFoundError:
            continue
    return found


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read().replace(b"\0", b" ").decode()
    except FileNotFoundError:
        return ""


def _kill_first_job(parents, what: str, sig: int, found: dict, stop: threading.Event) -> None:
    """Poll until a job process running `what` appears under one of `parents`; kill the parent
    (or, when the parent is ourselves, the job) with sig; record both pids."""
    while not stop.is_set():
        for parent in parents():
            for child in _children(parent):
                line = _cmdline(child)
                if "psdbake.farm.job" in line and f" {what} " in line:
                    found.update(parent=parent, job=child, chunk=int(re.search(r"--chunk=(\d+)", line).group(1)))
                    os.kill(child if parent == os.getpid() else parent, sig)
                    return
        time.sleep(0.01)


def _wait_gone(pid: int) -> None:
    for _ in range(3000):  # a killed worker's job unwinds on SIGTERM; bounded so a survivor fails the test
        if not os.path.exists(f"/proc/{pid}") or "psdbake.farm.job" not in _cmdline(pid):
            return
        time.sleep(0.01)
    raise AssertionError(f"job process {pid} outlived its killed worker")


def test_local_job_killed_by_a_signal_is_rerun(local_run, tmp_path):
    folder = tmp_path / "killed_local"
    jobs = load_jobs(jobs_file(folder, PIPELINE))
    found, stop = {}, threading.Event()
    killer = threading.Thread(target=_kill_first_job, args=(lambda: [os.getpid()], "eval", signal.SIGKILL, found, stop))
    killer.start()
    try:
        result = farm.run_batch(jobs, workers=2)
    finally:
        stop.set()
        killer.join()
    assert found, "the eval job was never seen running"
    assert [r.status for r in result.results] == ["ok"] * TASKS
    assert [r.label for r in result.results if r.attempts > 1] == [f"[[eval]] #1 chunk {found['chunk']}/3"]  # run again
    assert outputs(folder) == outputs(local_run[0])
    no_temps(folder / "out")


# --- Dask ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as c, distributed.Client(c, set_as_default=False) as client:
        yield c, client


def test_dask_cluster_gives_the_local_outputs_byte_for_byte(cluster, local_run, run, tmp_path):
    c, client = cluster
    path = jobs_file(tmp_path / "dask", PIPELINE)
    code, out, err = run("batch", path, "--scheduler", c.scheduler_address, "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["scheduler"] == c.scheduler_address and summary["workers"] == 2
    assert [j["status"] for j in summary["jobs"]] == ["ok"] * TASKS
    worker_pids = set(client.run(os.getpid).values())
    assert {int(j["worker"].rsplit(":", 1)[1]) for j in summary["jobs"]} <= worker_pids  # ran on the cluster
    assert outputs(tmp_path / "dask") == outputs(local_run[0])
    no_temps(tmp_path / "dask" / "out")


def test_dask_batch_survives_a_worker_killed_mid_job(cluster, local_run, tmp_path):
    c, client = cluster
    folder = tmp_path / "dask_killed"
    jobs = load_jobs(jobs_file(folder, PIPELINE))
    pids = set(client.run(os.getpid).values())
    found, stop = {}, threading.Event()
    killer = threading.Thread(target=_kill_first_job, args=(lambda: sorted(pids), "eval", signal.SIGKILL, found, stop))
    killer.start()
    try:
        result = farm.run_batch(jobs, scheduler=c.scheduler_address)
    finally:
        stop.set()
        killer.join()
    assert found, "the eval job was never seen running on a worker"
    by = {r.label: r for r in result.results}
    assert [r.status for r in result.results] == ["ok"] * TASKS, result.results
    assert int(by[f"[[eval]] #1 chunk {found['chunk']}/3"].worker.rsplit(":", 1)[1]) != found["parent"]  # rerun elsewhere
    _wait_gone(found["job"])  # the killed worker's job died with it (it would race its rerun)
    assert outputs(folder) == outputs(local_run[0])
    no_temps(folder / "out")
    client.wait_for_workers(2, timeout=60)  # the nanny restarted the killed worker


def test_scheduler_without_dask_is_a_usage_error(run, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    path = good_fit_jobs(tmp_path)
    code, _, err = run("batch", path, "--scheduler", "tcp://127.0.0.1:8786")
    assert code == 2
    assert err == "psdbake: error: --scheduler needs dask.distributed: pip install 'psdbake[dask]'\n"
    code, _, err = run("batch", path, "--scheduler", "tcp://127.0.0.1:8786", "--workers", "2")
    assert code == 2 and "--workers sizes the local pool" in err


def test_bad_scheduler_address_is_one_line(run, tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    from psdbake.farm.backends import dask as dask_backend

    path = good_fit_jobs(tmp_path)
    code, _, err = run("batch", path, "--scheduler", "udp://127.0.0.1:8786")
    assert code == 2 and err.startswith("psdbake: error: --scheduler udp://127.0.0.1:8786: unknown address scheme 'udp'")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    monkeypatch.setattr(dask_backend, "CONNECT_TIMEOUT", 1.0)
    code, _, err = run("batch", path, "--scheduler", f"tcp://127.0.0.1:{port}")
    assert code == 3 and err.startswith(f"psdbake: error: --scheduler tcp://127.0.0.1:{port}: cannot connect (")
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()  # nothing ran, no folder made


def test_scheduler_that_speaks_http_is_one_line(run, tmp_path):
    """``--scheduler`` at an HTTP server (the dashboard's port, a proxy) that answers Dask's
    handshake with ``HTTP/1.1 400``: distributed read those bytes as a frame length and asked for
    3.07 EiB (an internal MemoryError); now one line, exit 3, nothing run."""
    pytest.importorskip("distributed")
    path = good_fit_jobs(tmp_path)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]

        def answer() -> None:  # every connection, as a web server does (psdbake connects twice)
            with contextlib.suppress(OSError):
                while True:
                    conn, _ = server.accept()
                    with conn:
                        if conn.recv(65536):
                            conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        code, _, err = run("batch", path, "--scheduler", f"tcp://127.0.0.1:{port}")
        with contextlib.suppress(OSError):
            server.shutdown(socket.SHUT_RDWR)  # wakes the accept (Linux)
        thread.join(timeout=60)
    assert code == 3, err
    assert err.count("\n") == 1 and err.startswith(f"psdbake: error: --scheduler tcp://127.0.0.1:{port}: not a Dask "
                                                   "scheduler: it answers in another protocol (an HTTP server?")
    assert "MemoryError" not in err and not (tmp_path / "out").exists()


# --- no code from a data folder -------------------------------------------------------------------

#: Modules a shared asset folder might hold beside a jobs file, shadowing what a job imports: each
#: leaves a marker in the folder when imported (and would break the job).
PLANTED = ("click.py", "numpy.py", "json.py", "site.py", "sitecustomize.py", "pxr/__init__.py", "psdbake/__init__.py")
_PLANT = 'import os\nopen(os.path.join({folder!r}, "IMPORTED-" + __name__), "w").close()\n'

DATA_JOBS = f"""
[defaults]
asset = "{ASSET}"

[[fit]]
examples = ["{EXAMPLES}"]
output = "out/correctives.usda"

[[eval]]
correctives = "out/correctives.usda"
anim = "{ANIM}"
output = "out/weights.usda"
points_cache = "out/cache.usda"

[[stack]]
output = "out/shot.usda"
layers = ["{ASSET}", "out/correctives.usda", "{ANIM}", "out/weights.usda"]
"""


def _planted_folder(folder: Path) -> str:
    path = jobs_file(folder, DATA_JOBS)
    for name in PLANTED:
        (folder / name).parent.mkdir(exist_ok=True)
        (folder / name).write_text(_PLANT.format(folder=str(folder)))
    return path


@pytest.mark.parametrize("where", ["local", "dask"])
def test_modules_beside_the_jobs_file_are_never_imported(where, run, tmp_path, request):
    """``python -m`` put the jobs file's folder first on the job's sys.path, so a click.py (or
    numpy.py, json.py, pxr/) left there ran inside every job. Jobs now start isolated (``-I``)
    with this process's own import path: the batch succeeds and no planted module is imported,
    on the local pool and on a Dask cluster."""
    folder = tmp_path / "shared_assets"
    path = _planted_folder(folder)
    scheduler = []
    if where == "dask":
        c, _ = request.getfixturevalue("cluster")
        scheduler = ["--scheduler", c.scheduler_address]
    code, _, err = run("batch", path, *scheduler, "-q")
    assert code == 0, err
    assert sorted(p.name for p in folder.iterdir() if p.name.startswith("IMPORTED-")) == []
    assert all((folder / "out" / name).is_file() for name in ("correctives.usda", "weights.usda", "cache.usda"))


IDENTITY_DEFORMER = "def make(stage, mesh, time):\n    return lambda points: points\n"


@pytest.mark.parametrize("where", ["local", "dask"])
@pytest.mark.parametrize("table", ["job", "defaults"])
def test_a_deformer_named_in_a_jobs_file_needs_the_flag(where, table, run, tmp_path, request):
    """A deformer is code: named in a jobs file (its own folder's deformer.py, say), it is refused in
    one line before anything runs, on every back end, unless batch is given
    --allow-deformers-from-jobs."""
    (tmp_path / "deformer.py").write_text(IDENTITY_DEFORMER)
    spec = 'deformer = ["deformer.py:make"]\n'
    fit = f'[[fit]]\nasset = "{ASSET}"\nexamples = ["{EXAMPLES}"]\noutput = "out/c.usda"\n'
    path = jobs_file(tmp_path, "[defaults]\n" + spec + fit if table == "defaults" else fit + spec)
    scheduler = []
    if where == "dask":
        c, _ = request.getfixturevalue("cluster")
        scheduler = ["--scheduler", c.scheduler_address]
    code, _, err = run("batch", path, *scheduler)
    named = f"{path} [defaults]" if table == "defaults" else f"{path} [[fit]] #1"
    assert code == 3 and err == (f"psdbake: error: {named}: deformer 'deformer.py:make' would run code named by the "
                                 "jobs file: deformers are taken from the command line only, unless batch is given "
                                 "--allow-deformers-from-jobs\n")
    assert not (tmp_path / "out").exists()
    if where == "local" and table == "job":
        code, _, err = run("batch", path, "--allow-deformers-from-jobs", "-q")
        assert code == 0, err
        assert (tmp_path / "out" / "c.usda").is_file()


def test_jobs_is_the_flag_and_workers_its_older_name(run, tmp_path):
    """batch takes -j/--jobs as fit and eval do; -w/--workers still works; both, disagreeing, is a usage error."""
    path = jobs_file(tmp_path, f'[[pose]]\nasset = "{ASSET}"\nanim = "{POSES}"\noutput = "out/p.usda"\n')
    for flags in (["-j", "2"], ["--jobs", "1"], ["-w", "2"], ["--workers", "2", "--jobs", "2"]):
        code, out, err = run("batch", path, *flags, "--dry-run")
        assert code == 0 and "[[pose]] #1" in out, (flags, err)
    code, _, err = run("batch", path, "-j", "1", "-w", "2", "--dry-run")
    assert code == 2 and "--jobs 1 and --workers 2" in err
