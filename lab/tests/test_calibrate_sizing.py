"""lab/scripts/calibrate_sizing.py runs its preset at each fraction with `--set`: the key it sets is
the one the preset's sizing reads, and each fraction gets its own out dir."""
import subprocess
from pathlib import Path

import pytest

from lab_scripts import BIN, ROOT, load

calibrate = load("calibrate_sizing")
PRESET = ROOT / "lab" / "presets" / "calibration_spheres.toml"


def test_each_fraction_runs_the_preset_into_its_own_out_dir():
    sets, out = calibrate.run_at(str(PRESET), 0.275)
    assert out == str(ROOT / "out-calibration-spheres-f0.275")
    assert sets[::2] == ["--set"] * 3
    assert sets[1] == "select.half_max.fraction=0.275"
    assert sets[3] == f'pipeline.out_dir="{out}"'


def test_a_preset_that_reads_no_fraction_is_refused():
    with pytest.raises(SystemExit, match="candidates"):
        calibrate.run_at(str(ROOT / "presets" / "paper.toml"), 0.4)
    assert calibrate.run_at(str(ROOT / "pipeline.toml"), 0.4)[1] == str(ROOT / "out-f0.400")  # sized by its shadows


@pytest.mark.skipif(not Path(BIN).exists(), reason=f"no aret-pipe binary at {BIN} (set ARET_PIPE_BIN)")
def test_aret_pipe_accepts_the_settings():
    def status(*sets):
        return subprocess.run([BIN, "status", str(PRESET), *sets], capture_output=True, text=True, cwd=ROOT)

    proc = status(*calibrate.run_at(str(PRESET), 0.4)[0])
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # --set is checked as a file edit: a key the preset does not read is refused.
    assert status("--set", "select.half_max.nonsense=1").returncode != 0
