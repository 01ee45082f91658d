"""lab/scripts/select_study.py writes each set's config: the preset's fits, the shipped select,
the variant.

A study compares select variants on fits other runs cached, so its configs must reach the
same cache and cohort as the presets do and change nothing upstream of select.
"""
import importlib.util
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = ROOT / "lab" / "scripts"
sys.path.insert(0, str(SCRIPTS))  # the scripts import their shared preset_config
import preset_config  # noqa: E402

spec = importlib.util.spec_from_file_location("select_study", SCRIPTS / "select_study.py")
study = importlib.util.module_from_spec(spec)
spec.loader.exec_module(study)


def written(preset, overrides, variant, out="/tmp/study-out"):
    return tomllib.loads(preset_config.toml_text(study.study_config(preset, overrides, variant, out)))


def test_every_set_reads_its_presets_fits_through_the_shipped_select_with_the_variant_on_top():
    shipped = tomllib.loads((ROOT / "pipeline.toml").read_text())["select"]
    for name, preset, overrides in study.SETS + study.HELD_OUT:
        config = written(preset, overrides, "rival_ratio = 0.5\nguided_scale_ratios = [0.71, 1.0]")
        original = tomllib.loads((ROOT / preset).read_text())
        assert config["pipeline"]["out_dir"] == "/tmp/study-out", name
        assert Path(config["pipeline"]["cache_dir"]) == ROOT / "cache", name
        assert Path(config["dataset"]["cohort"]).is_dir(), name
        # Upstream of select, the preset as it is, but for the set's overrides.
        for table in ("drr", "train", "sweep"):
            assert config.get(table, {}) == original.get(table, {}), (name, table)
        phantom = {**original["dataset"].get("phantom", {}), **overrides.get("dataset.phantom", {})}
        assert config["dataset"].get("phantom", {}) == phantom, name
        assert config["select"] == {**shipped, "rival_ratio": 0.5, "guided_scale_ratios": [0.71, 1.0]}, name


def test_the_second_anatomies_differ_from_the_first_only_in_the_phantom_seed():
    one = written("presets/calibration_spheres.toml", {}, "")
    two = written("presets/calibration_spheres.toml", {"dataset.phantom": {"seed": 2}}, "")
    assert two["dataset"]["phantom"] == {"seed": 2}
    del two["dataset"]["phantom"]
    assert one == two


def test_preset_configs_toml_text_writes_nested_and_empty_tables_and_lists_back_as_read():
    config = {
        "pipeline": {"name": 'a "quoted" name', "stage_workers": {}, "workers": 2},
        "dataset": {"kind": "phantom", "phantom": {"seed": 3, "lung_hu": -850.0}},
        "select": {"blob_scales_mm": [6.0, 9.0, 13.0], "primary": "guided", "strict": True},
    }
    assert tomllib.loads(preset_config.toml_text(config)) == config
