//! `roi_center = "tiles"` through the command line on one phantom patient: each box is its own
//! drr → train → grid → sweep chain under `<patient>/tileNN/`, select keeps per rule the box
//! whose centre scores most, and the cohort report is written for it.

use serde_json::Value;
use std::path::Path;
use std::process::Command;

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");
const PATIENT: &str = "LIDC-IDRI-0003";

/// The default's method at toy size (48² views, a 32³ dense field, 60 steps) in 2 × 2 boxes.
fn write_config(dir: &Path, select_extra: &str) {
    let cohort = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/cohorts/paper19");
    let text = format!(
        "[pipeline]\nname = \"tiles\"\ncache_dir = \"cache\"\nout_dir = \"out\"\nworkers = 2\n\
         [dataset]\nkind = \"phantom\"\ncohort = \"{}\"\n[dataset.phantom]\nnodule_extent = \"consensus\"\n\
         [drr]\nwidth_px = 48\nheight_px = 48\nroi_center = \"tiles\"\n[drr.tiles]\ncounts = [1, 2, 2]\n\
         [train]\ngrid = 32\n[train.dense_tv]\niterations = 60\n\
         [select]\nprimary = \"blind_persistent\"\nsizing = \"half_max\"\n\
         [select.blob]\ntie_break = \"response\"\nblind_tie_break = \"response\"\nguided_fallback = false\n{select_extra}",
        cohort.display()
    );
    std::fs::write(dir.join("t.toml"), text).unwrap();
}

fn run(dir: &Path) -> Value {
    let out = Command::new(BIN)
        .args(["run", "t.toml", "--patients", PATIENT])
        .current_dir(dir)
        .env("CI", "true")
        .output()
        .unwrap();
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));
    read_json(&dir.join("out/run_report.json"))
}

fn read_json(path: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// The units whose `stage` record had `outcome`.
fn units(report: &Value, stage: &str, outcome: &str) -> Vec<String> {
    let records = report["records"].as_array().unwrap();
    let matching = records.iter().filter(|r| r["stage"] == stage && r["outcome"] == outcome);
    matching.map(|r| r["unit"].as_str().unwrap().to_string()).collect()
}

#[test]
fn each_box_is_its_own_chain_and_select_keeps_the_best_scoring_box_per_rule() {
    let dir = tempfile::tempdir().unwrap();
    write_config(dir.path(), "");
    let report = run(dir.path());
    let boxes: Vec<String> = (0..4).map(|t| format!("{PATIENT}/tile{t:02}")).collect();
    for stage in ["drr", "train", "grid", "sweep"] {
        assert_eq!(units(&report, stage, "computed"), boxes, "{stage}");
    }
    assert_eq!(units(&report, "select", "computed"), [PATIENT]);

    // The boxes lie 74 mm apart in y and 120 mm in z around one centre, the same in x.
    let patient = dir.path().join("out").join(PATIENT);
    let origin = |t: usize| {
        let cameras = read_json(&patient.join(format!("tile{t:02}/cameras.json")));
        assert_eq!(cameras["roi_center_mode"], format!("tile{t:02}"));
        let c = &cameras["frame"]["roi_center_mm"];
        [0, 1, 2].map(|a| c[a].as_f64().unwrap())
    };
    let step = |a: usize, b: usize| [0, 1, 2].map(|i| ((origin(b)[i] - origin(a)[i]) * 1e6).round() / 1e6);
    assert_eq!(step(0, 1), [0.0, 0.0, 120.0]);
    assert_eq!(step(0, 2), [0.0, 74.0, 0.0]);

    // Each rule's selection comes from the box whose centre scores most.
    let result = read_json(&patient.join("result.json"));
    let tiles = result["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), 4);
    let top = |key: &str| {
        let scores = tiles.iter().map(|t| t[key].as_f64().unwrap_or(f64::NEG_INFINITY));
        let best = scores.enumerate().fold((0, f64::NEG_INFINITY), |b, (i, s)| if s > b.1 { (i, s) } else { b });
        tiles[best.0]["tile"].clone()
    };
    assert_eq!(result["blind_persistent"]["tile"], top("blind_score"));
    assert_eq!(result["guided"]["tile"], top("guided_score"));
    assert!(result["verdict"].is_string() && patient.join("nodule.obj").exists());

    // The target's readers rated it 4 of 5 on average (ingest's ground truth): a solid nodule.
    let summary = read_json(&dir.path().join("out/summary.json"));
    let n = |group: &str| summary["groups"][group]["n"].as_u64();
    assert_eq!((n("solid"), n("subsolid"), n("ge10mm_solid")), (Some(1), Some(0), Some(1)));
    // The lung encloses it (ingest's target_site.json): none of it is outside the lung field.
    let site = read_json(&patient.join("target_site.json"));
    assert_eq!((site["outside_lung_fraction"].as_f64(), site["attached"].as_bool()), (Some(0.0), Some(false)));
    assert_eq!((n("ge10mm_solid_enclosed"), n("ge10mm_solid_attached")), (Some(1), Some(0)));

    // A second run serves every box from the cache; a select edit reruns select alone.
    let again = run(dir.path());
    assert_eq!(units(&again, "train", "cached"), boxes);
    assert_eq!(units(&again, "select", "cached"), [PATIENT]);
    write_config(dir.path(), "inside_mm = 6.0\n");
    let edited = run(dir.path());
    assert_eq!(units(&edited, "sweep", "cached"), boxes);
    assert_eq!(units(&edited, "select", "computed"), [PATIENT]);
}
