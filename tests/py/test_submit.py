"""`aret-pipe submit`: the Kubernetes manifests read with PyYAML as the Indexed Job of the
shards and the gather Job, and the Slurm scripts checked by bash's own parser, each running the
shard the scheduler hands it. tests/py/test_slurm.py submits them to a real single-node Slurm
cluster (tools/slurm-local)."""
import os
import subprocess
from pathlib import Path

import yaml

from test_train_safetensors import BIN

REPO = Path(__file__).resolve().parents[2]
CONFIG = f'[pipeline]\nname = "submit"\n[dataset]\nkind = "phantom"\ncohort = "{REPO / "tools" / "cohorts" / "paper19"}"\n'


def aret(*args, cwd):
    done = subprocess.run([BIN, *args], cwd=cwd, capture_output=True, text=True, env={**os.environ, "CI": "true"})
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


def test_kubernetes_gets_an_indexed_job_of_shards_and_a_gather_job(tmp_path):
    (tmp_path / "cohort.toml").write_text(CONFIG)
    shown = aret("submit", "k8s", "cohort.toml", "--array", "3", "--image", "registry.example/aret-pipe:1",
                 "--cache-pvc", "lidc", "--dry-run", cwd=tmp_path)
    counts = [int(line.split(": ")[1].split()[0]) for line in shown.splitlines() if line.startswith("shard ")]
    assert len(counts) == 3 and sum(counts) == 19, shown
    assert not (tmp_path / "submit").exists(), "a dry run writes nothing"
    aret("submit", "k8s", "cohort.toml", "--array", "3", "--max-running", "2", "--image",
         "registry.example/aret-pipe:1", "--cache-pvc", "lidc", cwd=tmp_path)
    shards, gather = yaml.safe_load_all((tmp_path / "submit" / "aret-pipe-jobs.yaml").read_text())
    assert shards["kind"] == gather["kind"] == "Job" and shards["apiVersion"] == "batch/v1"
    assert (shards["spec"]["completionMode"], shards["spec"]["completions"], shards["spec"]["parallelism"]) == (
        "Indexed", 3, 2)
    pod = shards["spec"]["template"]["spec"]
    container = pod["containers"][0]
    assert container["image"] == "registry.example/aret-pipe:1" and container["command"] == ["aret-pipe"]
    assert container["args"] == ["run", "cohort.toml", "--shard-from-env", "--shard-count", "3"]
    assert container["workingDir"] == container["volumeMounts"][0]["mountPath"] == "/work"
    assert pod["volumes"][0]["persistentVolumeClaim"]["claimName"] == "lidc" and pod["restartPolicy"] == "Never"
    assert gather["spec"]["template"]["spec"]["containers"][0]["args"] == ["run", "cohort.toml", "--gather", "--shard-count", "3"]


def test_slurm_gets_an_array_script_and_a_gather_script_that_bash_accepts(tmp_path):
    (tmp_path / "cohort.toml").write_text(CONFIG)
    shown = aret("submit", "slurm", "cohort.toml", "--array", "4", "--partition", "short", "--time", "02:00:00",
                 "--mem", "8G", cwd=tmp_path)
    assert "sbatch --dependency=afterany:$jid" in shown, shown
    shards = (tmp_path / "submit" / "aret-shards.sbatch").read_text()
    gather = (tmp_path / "submit" / "aret-gather.sbatch").read_text()
    for script in (shards, gather):
        subprocess.run(["bash", "-n"], input=script, text=True, check=True)
        assert "#SBATCH --partition=short\n#SBATCH --time=02:00:00\n#SBATCH --mem=8G\n" in script
    assert "#SBATCH --array=0-3\n" in shards and "--array" not in gather
    assert f"run {tmp_path / 'cohort.toml'} --shard-from-env --shard-count 4" in shards
    assert shards.splitlines()[-1].startswith("exec /"), "the tasks run this aret-pipe, named absolutely"
    assert gather.rstrip().endswith("--gather --shard-count 4"), "a refused gather names the shards to run again"
