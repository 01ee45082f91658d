"""`aret-pipe submit slurm --submit` on a real Slurm: a single-node cluster started for this module
by tools/slurm-local (munged, slurmctld and slurmd, all state in a temporary folder), never a
mock.

A four-patient phantom cohort (one patient in each of four shards) runs as a four-task array and
the gather after it; every file the cohort writes is then the file one local `aret-pipe run`
writes. Then two tasks are stopped while they train, one cancelled through Slurm and one
SIGKILLed: the gather after the array fails naming their patients, and those tasks submitted
again, then the gather, complete the cohort.

Skipped where slurm-wlm and munge are not installed, except when CI=true (CI installs them).
"""
import importlib.util
import json
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from test_train_safetensors import BIN

REPO = Path(__file__).resolve().parents[2]
SLURM_LOCAL = REPO / "tools" / "slurm-local"
# The daemons live in sbin, which a normal user's PATH may lack (tools/slurm-local adds it too).
SEARCH = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/sbin"])
MISSING = [p for p in ("munged", "slurmctld", "slurmd", "sbatch") if shutil.which(p, path=SEARCH) is None]
NOT_INSTALLED = f"Slurm is not installed here ({', '.join(MISSING)} missing): apt-get install slurm-wlm munge"
# CI set, as stages/engine/progress.rs reads it: there the cluster's fixture fails instead.
IN_CI = os.environ.get("CI", "") not in ("", "false")
if MISSING and not IN_CI:
    pytest.skip(NOT_INSTALLED, allow_module_level=True)

# One patient in each of four shards (blake3 of the ID, modulo 4): `cohort_shards` checks it.
PATIENTS = ["P1", "P3", "P7", "P11"]
SHARDS = 4
# How long any wait on the scheduler may take: each step here takes seconds.
TIMEOUT = 120
# The tiny training of tests/cli.rs, with enough iterations that a patient trains for seconds
# (about 3 s here): long enough to kill a task while it trains, short enough for CI.
CONFIG = """[pipeline]
name = "slurm"
[dataset]
kind = "phantom"
cohort = "{cohort}"
[drr]
width_px = 32
height_px = 32
[train]
model = "vm"
grid = 8
log_every = 1000
[train.vm]
iterations = 10000
rank = 2
batch_rays = 64
[sweep]
score = "density"
region = "box"
[select]
localize = "none"
sizing = "candidates"
"""


def sphere_cohort():
    spec = importlib.util.spec_from_file_location("sphere_cohort", REPO / "lab" / "scripts" / "sphere_cohort.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    """Four phantom patients of 64 × 64 × 40 voxels (the real cohort's 512² scans take a minute
    each to generate), each with one sphere drawn by four readers, written by the calibration
    cohort's own writers (lab/scripts/sphere_cohort.py) so every patient is scored."""
    spheres = sphere_cohort()
    folder = tmp_path_factory.mktemp("cohort")
    for n, patient in enumerate(PATIENTS):
        series = spheres.uid(patient, "series")
        zvals = [-200.0 + 5.0 * k for k in range(40)]
        scan = {
            "format": "aret-pipe sphere cohort/1", "note": "tests/py/test_slurm.py", "patient_id": patient,
            "study_instance_uid": spheres.uid(patient, "study"), "series_instance_uid": series,
            "pixel_spacing_mm": 5.5, "slice_thickness_mm": 5.0, "rows": 64, "cols": 64, "zvals_mm": zvals,
            "sop_uids": [spheres.uid(series, k) for k in range(len(zvals))],
        }
        centre, diameter = [(-1) ** n * 80.0, 10.0 * n, -100.0 + 5.0 * n], 20.0 + 4.0 * n
        scan["sphere"] = {"centre_mm": centre, "diameter_mm": diameter}
        (folder / f"{patient}.scan.json").write_text(json.dumps(scan, indent=1))
        (folder / f"{patient}.xml").write_text(spheres.lidc_xml(scan, spheres.sphere_contours(scan, centre, diameter)))
    return folder


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """The environment in which sbatch, squeue, scontrol and scancel reach the module's cluster,
    and the cluster's folder. The cluster is stopped after the module, whatever happened. The
    jobs inherit this environment (sbatch exports it), without CI: off a terminal and outside CI
    a run logs a line per stage it computes, as a user's jobs do."""
    if MISSING:
        pytest.fail(f"{NOT_INSTALLED}; CI must install them (.ci/run does)", pytrace=False)
    state = tmp_path_factory.mktemp("slurm")
    try:
        up = subprocess.run([SLURM_LOCAL, "up", state], capture_output=True, text=True, timeout=180)
        assert up.returncode == 0, f"tools/slurm-local up failed:\n{up.stdout}\n{up.stderr}"
        conf = re.search(r"^export SLURM_CONF=(\S+)$", up.stdout, re.M)
        assert conf, up.stdout
        env = {k: v for k, v in os.environ.items() if k != "CI"}
        yield {**env, "SLURM_CONF": conf[1]}, state
    finally:
        down = subprocess.run([SLURM_LOCAL, "down", state], capture_output=True, text=True, timeout=120)
        assert down.returncode == 0, f"tools/slurm-local down failed:\n{down.stdout}\n{down.stderr}"


def run(args, cwd, env, ok=True):
    done = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=TIMEOUT)
    if ok:
        assert done.returncode == 0, f"{' '.join(map(str, args))}:\n{done.stdout}\n{done.stderr}"
    return done


def project(root: Path, cohort: Path) -> Path:
    (root / "p.toml").write_text(CONFIG.format(cohort=cohort))
    return root


def cohort_shards(folder, env):
    """shard index -> its patient, as `submit slurm --dry-run` splits them."""
    shown = run([BIN, "submit", "slurm", "p.toml", "--array", SHARDS, "--dry-run"], folder, env).stdout
    split = dict(re.findall(r"^shard (\d+)/\d+: 1 patients: (\S+)$", shown, re.M))
    assert sorted(split.values()) == sorted(PATIENTS), f"not one patient a shard:\n{shown}"
    return {int(k): p for k, p in split.items()}


def submit(folder, env):
    """`aret-pipe submit slurm --submit`: the array's and the gather's job ids, as it prints them."""
    shown = run([BIN, "submit", "slurm", "p.toml", "--array", SHARDS, "--submit"], folder, env).stdout
    ids = re.search(r"^submitted: the shards as job (\d+), the gather as job (\d+) \(afterany:\1\)$", shown, re.M)
    assert ids, shown
    return ids[1], ids[2]


def sbatch(args, folder, env):
    return run(["sbatch", "--parsable", *args], folder, env).stdout.strip().split(";")[0]


def wait_for_empty_queue(env):
    """Waits until no job is queued or running on the cluster (it runs only this module's)."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        if not run(["squeue", "-h", "-o", "%i"], None, env).stdout.strip():
            return
        time.sleep(0.2)
    queue = run(["squeue"], None, env).stdout
    pytest.fail(f"jobs still queued after {TIMEOUT} s:\n{queue}")


def job_states(job, env):
    """{array task index or None: (JobState, ExitCode)} of a job (all tasks of an array), as
    slurmctld keeps them for a while after they end (there is no accounting database here)."""
    lines = run(["scontrol", "-o", "show", "job", job], None, env).stdout.splitlines()
    states = {}
    for line in lines:
        fields = dict(f.split("=", 1) for f in line.split() if "=" in f)
        task = fields.get("ArrayTaskId")
        states[int(task) if task and task.isdigit() else None] = (fields["JobState"], fields["ExitCode"])
    return states


def assert_same_outputs(ours: Path, theirs: Path):
    """Every file under two out dirs is the same bytes (no artifact holds a wall time), but
    run_report.json, the run's own record of what it computed or found cached and how long each
    stage took: it must list the same stages of the same patients."""
    files = sorted(p.relative_to(ours) for p in ours.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(theirs) for p in theirs.rglob("*") if p.is_file())
    assert Path("results.csv") in files and len(files) > 30, files
    for rel in files:
        a, b = (ours / rel).read_bytes(), (theirs / rel).read_bytes()
        if rel.name == "run_report.json":
            stages = [{(r["unit"], r["stage"]) for r in json.loads(x)["records"]} for x in (a, b)]
            assert stages[0] == stages[1] and len(stages[0]) > 4 * 7, stages
        else:
            assert a == b, f"{rel} differs"


@pytest.fixture(scope="module")
def local_run(cohort, tmp_path_factory):
    """The reference: one local `aret-pipe run` of the configuration, no scheduler."""
    folder = project(tmp_path_factory.mktemp("local"), cohort)
    run([BIN, "run", "p.toml"], folder, {**os.environ, "CI": "true"})
    return folder / "out"


@pytest.fixture(scope="module")
def array_run(cohort, cluster, tmp_path_factory):
    """The cohort as a four-task array and the gather after it, submitted by aret-pipe itself:
    the folder, the job ids and the seconds from submission to an empty queue."""
    env, _ = cluster
    folder = project(tmp_path_factory.mktemp("array"), cohort)
    assert len(cohort_shards(folder, env)) == SHARDS
    start = time.monotonic()
    array, gather = submit(folder, env)
    wait_for_empty_queue(env)
    return folder, array, gather, time.monotonic() - start


def test_the_array_and_its_gather_write_what_one_local_run_writes(array_run, local_run, cluster):
    folder, array, gather, seconds = array_run
    env, _ = cluster
    logs = folder / "submit" / "logs"
    tasks = job_states(array, env)
    assert tasks == {k: ("COMPLETED", "0:0") for k in range(SHARDS)}, tasks
    assert job_states(gather, env) == {None: ("COMPLETED", "0:0")}, (logs / f"gather-{gather}.out").read_text()
    for k, patient in cohort_shards(folder, env).items():
        log = (logs / f"shard-{array}_{k}.out").read_text()
        assert f"select {patient}: computed" in log, log
    print(f"the 4-task array and its gather ran in {seconds:.1f} s from submission")
    assert_same_outputs(folder / "out", local_run)


def task_fields(task, env):
    """`scontrol show job` of one array task (JOB_K) as {field: value}."""
    shown = run(["scontrol", "-o", "show", "job", task], None, env).stdout
    return dict(f.split("=", 1) for f in shown.split() if "=" in f)


def kill_processes(job_id, env):
    """SIGKILL every process of a running job (its own JobId), as `scontrol listpids` lists them."""
    listed = run(["scontrol", "listpids", job_id], None, env).stdout
    pids = re.findall(rf"^(\d+)\s+{job_id}\s", listed, re.M)
    assert pids, f"no processes of job {job_id}:\n{listed}"
    for pid in pids:
        os.kill(int(pid), 9)


def table(log: str, patient: str):
    """A patient's row of the table a run ends with: {stage: its outcome or seconds}."""
    header, row = (re.search(rf"^{name}\s.*$", log, re.M)[0].split() for name in ("patient", patient))
    return dict(zip(header[1:], row[1:]))


def test_tasks_stopped_mid_run_fail_the_gather_until_submitted_again(array_run, cohort, cluster, tmp_path):
    """Tasks 0 and 1 (the first two to run) each stop while their patient trains. Task 0 is
    cancelled: `scancel --signal=KILL` is a cancel to Slurm, which sends SIGTERM and SIGKILL only
    after KillWait (30 s), so aret-pipe finishes the stage in progress and stops. Task 1's
    process is killed outright (SIGKILL, as the kernel's OOM killer would), mid-stage."""
    env, _ = cluster
    folder = project(tmp_path, cohort)
    patients = cohort_shards(folder, env)
    array, gather = submit(folder, env)
    logs = folder / "submit" / "logs"
    log = {k: logs / f"shard-{array}_{k}.out" for k in (0, 1)}

    # Each task is stopped once it has rendered its DRRs, so while it trains (seconds): mid-run.
    deadline, stopped = time.monotonic() + TIMEOUT, set()
    while stopped != {0, 1}:
        assert time.monotonic() < deadline, f"tasks {set(log) - stopped} of {array} did not reach training"
        for k in {0, 1} - stopped:
            if f"drr {patients[k]}: computed" not in (log[k].read_text() if log[k].exists() else ""):
                continue
            fields = task_fields(f"{array}_{k}", env)
            assert fields["JobState"] == "RUNNING", fields
            if k == 0:
                run(["scancel", "--signal=KILL", "--full", f"{array}_{k}"], None, env)
            else:
                kill_processes(fields["JobId"], env)
            stopped.add(k)
        time.sleep(0.05)
    wait_for_empty_queue(env)
    killed_logs = {k: log[k].read_text() for k in (0, 1)}
    tasks = job_states(array, env)
    assert tasks[0][0] == "CANCELLED" and "stopping: the stages in progress finish" in killed_logs[0], (
        tasks, killed_logs[0])
    assert tasks[1] == ("FAILED", "0:9"), tasks
    assert f"train {patients[1]}: computed" not in killed_logs[1], f"task 1 finished training:\n{killed_logs[1]}"
    for k in (0, 1):
        assert f"select {patients[k]}: computed" not in killed_logs[k], f"task {k} ended before it was stopped"
    assert tasks[2] == tasks[3] == ("COMPLETED", "0:0"), tasks

    # The gather ran after the array (afterany) and failed, naming the two tasks' patients and
    # only them, with the command that computes them.
    gathered = (logs / f"gather-{gather}.out").read_text()
    assert job_states(gather, env)[None][0] == "FAILED", gathered
    lost = sorted(patients[k] for k in (0, 1))
    assert f"2 of 4 patients are not computed yet: {', '.join(lost)}. " in gathered, gathered
    assert f"--patients {','.join(lost)} " in gathered, gathered
    resubmit = "sbatch --array=0,1 submit/aret-shards.sbatch"
    assert f"their shards of 4: 0, 1 (a Slurm array: `{resubmit}`)" in gathered, gathered
    assert not (folder / "out" / "results.csv").exists()

    # Those two tasks again as the gather said, one array of two (whose SLURM_ARRAY_TASK_COUNT is
    # 2: the script names the shard count itself), then the gather: the cohort is complete.
    again = sbatch(resubmit.split()[1:], folder, env)
    gather_again = sbatch([f"--dependency=afterok:{again}", "submit/aret-gather.sbatch"], folder, env)
    wait_for_empty_queue(env)
    assert job_states(again, env) == {0: ("COMPLETED", "0:0"), 1: ("COMPLETED", "0:0")}
    for k in (0, 1):
        rerun = (logs / f"shard-{again}_{k}.out").read_text()
        assert re.findall(r"^(\S+)\s+(?:cached|stopped|[0-9.]+s)\s", rerun, re.M) == [patients[k]], rerun
        # What the stopped task had finished is cached; the rest is computed.
        outcome = table(rerun, patients[k])
        assert [outcome[s] for s in ("phantom", "ingest", "hu", "drr")] == ["cached"] * 4, rerun
        assert f"select {patients[k]}: computed" in rerun, rerun
        assert log[k].read_text() == killed_logs[k], "the stopped task's log is kept"
    assert f"train {patients[1]}: computed" in (logs / f"shard-{again}_1.out").read_text()
    gathered = (logs / f"gather-{gather_again}.out").read_text()
    assert job_states(gather_again, env) == {None: ("COMPLETED", "0:0")}, gathered
    results = [(f / "out" / "results.csv").read_bytes() for f in (folder, array_run[0])]
    assert results[0] == results[1] and len(results[0].splitlines()) == 1 + len(PATIENTS), results
    assert_same_outputs(folder / "out", array_run[0] / "out")
