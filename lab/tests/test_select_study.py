"""lab/scripts/select_study.py writes each set's config: the shipped configuration with the set's
phantom, views or fit, the shipped select, the variant.

A study compares select variants on fits other runs cached, so its configs must reach the
same cache and cohort as the runs that fitted them and change nothing upstream of select.
"""
import json
import subprocess
import tomllib
from pathlib import Path

import pytest

from lab_scripts import BIN, ROOT, load

import preset_config  # noqa: E402  (lab_scripts puts lab/scripts on the path)

study = load("select_study")
UPSTREAM = ("ingest", "hu", "drr", "train", "grid", "sweep")
VARIANT = "blob.rival_ratio = 0.5; half_max.fraction = 0.4; primary = \"blind_persistent\""


def write(folder, name, overrides, variant="", perfect_field=False):
    """The set's config, written where select_study.py writes it; its path."""
    out = folder / "out-study" / "v" / name
    out.mkdir(parents=True, exist_ok=True)
    config = study.study_config(overrides, study.parse_variant(variant), str(out), perfect_field)
    (out / "config.toml").write_text(preset_config.toml_text(config))
    return out / "config.toml"


def shipped_with(overrides):
    """pipeline.toml as read, with `overrides` (paths relative to the repository) on top."""
    config = preset_config.load_absolute(ROOT / "pipeline.toml")
    for dotted, keys in study.absolute(overrides).items():
        t = config
        for part in dotted.split("."):
            t = t.setdefault(part, {})
        t.update(keys)
    return config


def test_every_set_extends_the_shipped_configuration_with_its_overrides_and_the_variant_on_select(tmp_path):
    shipped = tomllib.loads((ROOT / "pipeline.toml").read_text())["select"]
    for name, overrides in study.SETS + study.HELD_OUT:
        path = write(tmp_path, name, overrides, VARIANT)
        written = tomllib.loads(path.read_text())
        assert written["extends"] == str(ROOT / "pipeline.toml"), name
        assert written["pipeline"] == {"out_dir": str(path.parent)}, name
        assert written["select"] == {"primary": "blind_persistent", "blob": {"rival_ratio": 0.5},
                                     "half_max": {"fraction": 0.4}}, name
        config, expected = preset_config.load_absolute(path), shipped_with(overrides)
        assert Path(config["pipeline"]["cache_dir"]) == ROOT / "cache", name
        assert Path(config["dataset"]["cohort"]).is_dir(), name
        # Upstream of select, the shipped configuration, but for the set's overrides.
        for table in UPSTREAM:
            assert config.get(table, {}) == expected.get(table, {}), (name, table)
        assert config["dataset"] == expected["dataset"], name
        # The shipped select, the variant's keys on top.
        blob, half_max = {**shipped["blob"], "rival_ratio": 0.5}, {**shipped["half_max"], "fraction": 0.4}
        assert config["select"] == {**shipped, "primary": "blind_persistent", "blob": blob, "half_max": half_max}


def test_the_spheres_sets_fit_what_the_calibration_preset_fits(tmp_path):
    spheres = preset_config.load_absolute(write(tmp_path, "spheres-1", dict(study.SETS)["spheres-1"]))
    preset = preset_config.load_absolute(ROOT / "lab" / "presets" / "calibration_spheres.toml")
    for table in ("dataset", *UPSTREAM):
        assert spheres.get(table, {}) == preset.get(table, {}), table
    assert preset["pipeline"]["cache_dir"] == spheres["pipeline"]["cache_dir"]


def test_the_second_anatomies_differ_from_the_first_only_in_the_phantom_seed(tmp_path):
    sets = dict(study.SETS + study.HELD_OUT)
    for first, second, seed in [("spheres-1", "spheres-2", 2), ("union-1", "union-2", 2),
                                ("consensus-1", "consensus-2", 2), ("consensus-1", "consensus-9", 9)]:
        one = preset_config.load_absolute(write(tmp_path, "same", sets[first]))
        two = preset_config.load_absolute(write(tmp_path, "same", sets[second]))
        assert two["dataset"]["phantom"].pop("seed") == seed
        one["dataset"]["phantom"].pop("seed", None)
        assert one == two, (first, second)


def test_the_perfect_field_replaces_only_the_fit(tmp_path):
    config = preset_config.load_absolute(write(tmp_path, "consensus-3", {"dataset.phantom": {"seed": 3}},
                                               perfect_field=True))
    expected = shipped_with({"dataset.phantom": {"seed": 3}})
    # Picking the truth drops the dense fit's table, as aret-pipe drops it.
    assert config["train"] == {**{k: v for k, v in expected["train"].items() if k != "dense_tv"}, "model": "truth"}
    for table in ("dataset", "drr", "sweep", "select"):
        assert config[table] == expected[table], table


def test_a_key_spelt_before_the_variant_tables_is_refused_with_its_new_spelling():
    for old, new in [("rival_ratio = 0.5", "[select.blob] rival_ratio"),
                     ("half_max_fraction = 0.4", "[select.half_max] fraction"),
                     ("blob_scales_mm = [6.0]", "[select.blob] scales_mm")]:
        with pytest.raises(SystemExit, match=new.replace("[", r"\[").replace("]", r"\]")):
            study.parse_variant(old)
    with pytest.raises(SystemExit, match="lab-v1"):
        study.parse_variant("guided_scale_ratios = [0.71, 1.0]")
    with pytest.raises(SystemExit, match=r"blob\.score_top has left the code: it runs only at tag lab-v2"):
        study.parse_variant("blob.score_top = 3")
    assert study.parse_variant("") == {}


def status(config, *sets, patients=None):
    """`aret-pipe status --json`: it reads and checks the configuration, runs nothing."""
    args = [BIN, "status", str(config), "--json", *(a for s in sets for a in ("--set", s))]
    if patients:
        args += ["--patients", patients]
    proc = subprocess.run(args, capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads(proc.stdout)


def phantom_key(plan):
    return next(r["key"] for r in plan["rows"] if r["stage"] == "phantom")


@pytest.mark.skipif(not Path(BIN).exists(), reason=f"no aret-pipe binary at {BIN} (set ARET_PIPE_BIN)")
def test_aret_pipe_accepts_every_sets_config_and_reads_the_phantom_the_set_names(tmp_path):
    one = "LIDC-IDRI-0001"
    for name, overrides in study.SETS + study.HELD_OUT:
        patients = None if "cohort" in overrides.get("dataset", {}) else one
        for perfect_field in (False, True):
            status(write(tmp_path, name, overrides, VARIANT, perfect_field), patients=patients)
    # The phantom of a seeded set is pipeline.toml's with --set, and the spheres' the calibration
    # preset's.
    seeded = phantom_key(status(write(tmp_path, "consensus-2", {"dataset.phantom": {"seed": 2}}), patients=one))
    assert seeded == phantom_key(status(ROOT / "pipeline.toml", "dataset.phantom.seed=2", patients=one))
    assert seeded != phantom_key(status(ROOT / "pipeline.toml", patients=one))
    spheres = phantom_key(status(write(tmp_path, "spheres-2", dict(study.SETS)["spheres-2"])))
    preset = ROOT / "lab" / "presets" / "calibration_spheres.toml"
    assert spheres == phantom_key(status(preset, "dataset.phantom.seed=2"))


def test_preset_configs_toml_text_writes_extends_nested_and_empty_tables_and_lists_back_as_read():
    config = {
        "extends": "../pipeline.toml",
        "pipeline": {"name": 'a "quoted" name', "stage_workers": {}, "workers": 2},
        "dataset": {"kind": "phantom", "phantom": {"seed": 3, "lung_hu": -850.0}},
        "select": {"primary": "guided", "blob": {"scales_mm": [6.0, 9.0, 13.0], "guided_fallback": True}},
    }
    assert tomllib.loads(preset_config.toml_text(config)) == config


def test_load_absolute_layers_what_a_configuration_extends_as_aret_pipe_does(tmp_path):
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "base.toml").write_text(
        '[pipeline]\nname = "base"\nout_dir = "../out-base"\n[dataset]\nkind = "phantom"\ncohort = "cohort"\n'
        '[train]\nmodel = "vm"\ngrid = 64\n[train.vm]\nrank = 8\n'
        '[select]\nsizing = "half_max"\n[select.half_max]\nfraction = 0.4\n'
    )
    (tmp_path / "top.toml").write_text(
        'extends = "base/base.toml"\n[pipeline]\nname = "top"\n'
        '[train]\nmodel = "dense_tv"\n[train.dense_tv]\nlambda = 0.1\n[select]\nsizing = "shadows"\n'
    )
    config = preset_config.load_absolute(tmp_path / "top.toml")
    assert config["pipeline"] == {"name": "top", "out_dir": str(tmp_path / "out-base"),
                                  "cache_dir": str(tmp_path / "cache")}
    assert config["dataset"] == {"kind": "phantom", "cohort": str(tmp_path / "base" / "cohort")}
    # Picking the dense model drops [train.vm]; shadows reads [select.half_max] as half_max did.
    assert config["train"] == {"model": "dense_tv", "grid": 64, "dense_tv": {"lambda": 0.1}}
    assert config["select"] == {"sizing": "shadows", "half_max": {"fraction": 0.4}}
