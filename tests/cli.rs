//! The pipeline through its command line, on small CT series written by the tests: caching and
//! invalidation per stage, dry-run reasons, concurrent runs, SIGKILL and SIGTERM mid-run, failure
//! isolation, no identifying tags in any artifact.

mod support;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use support::dicom_writer::{default_name, series, write_series, SliceSpec};

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");

struct Project {
    dir: tempfile::TempDir,
}

impl Project {
    /// A dataset of `patients` folders with a small CT series each.
    fn new(patients: &[&str], slices: usize) -> Project {
        let p = Project { dir: tempfile::tempdir().unwrap() };
        for (n, id) in patients.iter().enumerate() {
            let mut specs = series(slices);
            for s in &mut specs {
                s.intercept = Some(-1024.0 + n as f64);
            }
            p.write_patient(id, &specs);
        }
        p.write_config("pipeline.toml", "cache", "out", "");
        p
    }

    fn write_patient(&self, id: &str, specs: &[SliceSpec]) {
        let dir = self.path(&format!("data/{id}/series"));
        std::fs::create_dir_all(&dir).unwrap();
        write_series(&dir, specs, default_name);
    }

    /// A tiny run (a VM field on an 8³ lattice, 3 iterations): the engine is under test, so it
    /// uses the paper's sweep and selection, which need no lung field in the density.
    fn write_config(&self, name: &str, cache: &str, out: &str, extra: &str) {
        let text = format!(
            "[pipeline]\nname = \"test\"\ncache_dir = \"{cache}\"\nout_dir = \"{out}\"\nworkers = 2\n\
             [dataset]\nkind = \"dicom\"\nroot = \"data\"\n\
             [drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n\
             [train]\nmodel = \"vm\"\ngrid = 8\nlog_every = 1\n\
             [train.vm]\niterations = 3\nrank = 2\nbatch_rays = 64\n\
             [sweep]\nscore = \"density\"\nregion = \"box\"\n[select]\nlocalize = \"none\"\nsizing = \"candidates\"\n{extra}"
        );
        std::fs::write(self.path(name), text).unwrap();
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }

    /// `aret-pipe ARGS` in the project's folder, quiet as in CI.
    fn command(&self, args: &[&str]) -> Command {
        let mut command = Command::new(BIN);
        command.args(args).current_dir(self.dir.path()).env("CI", "true");
        command
    }

    fn aret(&self, args: &[&str]) -> Output {
        self.command(args).output().unwrap()
    }

    fn run(&self, args: &[&str]) -> Value {
        let mut all = vec!["run", "pipeline.toml"];
        all.extend_from_slice(args);
        let out = self.aret(&all);
        assert!(out.status.success(), "run failed:\n{}\n{}", text(&out.stdout), text(&out.stderr));
        self.report("out")
    }

    fn report(&self, out_dir: &str) -> Value {
        serde_json::from_slice(&std::fs::read(self.path(&format!("{out_dir}/run_report.json"))).unwrap()).unwrap()
    }
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// How many (patient, stage) records of `stage` had `outcome`.
fn count(report: &Value, stage: &str, outcome: &str) -> usize {
    report["records"].as_array().unwrap().iter().filter(|r| r["stage"] == stage && r["outcome"] == outcome).count()
}

#[test]
fn editing_hu_recomputes_hu_only_and_forced_runs_cut_off_early() {
    let p = Project::new(&["P1", "P2"], 4);
    let r = p.run(&[]);
    assert_eq!((count(&r, "ingest", "computed"), count(&r, "hu", "computed")), (2, 2));
    assert!(p.path("out/P1/ct_hu.mhd").exists() && p.path("out/P2/ct_unit.raw").exists());

    let r = p.run(&[]);
    assert_eq!((count(&r, "ingest", "cached"), count(&r, "hu", "cached")), (2, 2), "unchanged config: nothing runs");

    p.write_config("pipeline.toml", "cache", "out", "[hu]\nhu_max = 500.0\n");
    let dry = p.aret(&["run", "pipeline.toml", "--dry-run"]);
    let dry_text = text(&dry.stdout);
    assert!(dry_text.contains("parameter `hu_max` changed: 400.0 → 500.0"), "{dry_text}");
    assert!(dry_text.lines().filter(|l| l.contains("ingest")).all(|l| l.contains("cached")), "{dry_text}");
    let r = p.run(&[]);
    assert_eq!((count(&r, "ingest", "cached"), count(&r, "hu", "computed")), (2, 2));

    let r = p.run(&["--force", "hu"]);
    assert_eq!((count(&r, "ingest", "cached"), count(&r, "hu", "computed")), (2, 2));

    // Early cutoff: ingest recomputes (its parameter changed) to identical bytes; hu stays cached.
    p.write_config("pipeline.toml", "cache", "out", "[hu]\nhu_max = 500.0\n[ingest]\nslice_gap_tolerance = 0.02\n");
    let r = p.run(&[]);
    assert_eq!((count(&r, "ingest", "computed"), count(&r, "hu", "cached")), (2, 2));

    let status = text(&p.aret(&["status", "pipeline.toml"]).stdout);
    let rows: Vec<&str> = status.lines().filter(|l| l.starts_with('P')).collect();
    // Per-patient stages all cached; the cohort stage's column is "·" on patient rows.
    let cached = |l: &&str| l.split_whitespace().skip(1).all(|c| c == "cached" || c == "·");
    assert!(rows.len() == 2 && rows.iter().all(cached), "{status}");
}

#[test]
fn force_all_recomputes_every_stage_and_a_misspelt_stage_is_an_error_listing_them() {
    let p = Project::new(&["P1"], 2);
    p.run(&[]);
    let dry = text(&p.aret(&["run", "pipeline.toml", "--dry-run", "--force", "all"]).stdout);
    assert!(dry.lines().count() > 2 && dry.lines().all(|l| l.contains("forced with --force")), "{dry}");
    let r = p.run(&["--force", "all"]);
    let records = r["records"].as_array().unwrap();
    assert!(records.len() > 2 && records.iter().all(|r| r["outcome"] == "computed"), "{r}");
    // `all` is every stage --until keeps.
    let r = p.run(&["--force", "all", "--until", "hu"]);
    let stages: Vec<&str> = r["records"].as_array().unwrap().iter().map(|r| r["stage"].as_str().unwrap()).collect();
    assert_eq!(stages, ["ingest", "hu"]);
    assert_eq!((count(&r, "ingest", "computed"), count(&r, "hu", "computed")), (1, 1));

    for force in ["hue", "all,hue"] {
        let out = p.aret(&["run", "pipeline.toml", "--force", force]);
        let stderr = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{stderr}");
        assert!(stderr.contains("--force hue: no such stage") && stderr.contains("ingest, hu, drr"), "{stderr}");
    }
}

/// `status --json` and `run --dry-run --json` parsed, and checked fact by fact against the
/// status table and the dry run's lines.
#[test]
fn status_and_dry_run_json_say_what_their_text_says() {
    let p = Project::new(&["P1", "P2"], 3);
    p.run(&[]);
    p.write_config("pipeline.toml", "cache", "out", "[hu]\nhu_max = 500.0\n");
    let json = |args: &[&str]| -> Value {
        let out = p.aret(args);
        assert!(out.status.success(), "{}", text(&out.stderr));
        serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("stdout is not one JSON document ({e}):\n{}", text(&out.stdout)))
    };
    let status = json(&["status", "pipeline.toml", "--json"]);
    let dry = json(&["run", "pipeline.toml", "--dry-run", "--json"]);
    assert_eq!((&status["command"], &dry["command"]), (&Value::from("status"), &Value::from("dry-run")));
    assert_eq!(status["config"], "pipeline.toml");
    assert_eq!(status["rows"], dry["rows"], "one plan, two views");
    let rows = status["rows"].as_array().unwrap();
    let stages: Vec<&str> = status["stages"].as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect();
    let row = |unit: &str, stage: &str| rows.iter().find(|r| r["unit"] == unit && r["stage"] == stage).unwrap();

    // The facts of this plan: ingest cached, hu stale with the key it will have, what follows
    // pending after it, and the cohort after the first patient's hu.
    for unit in ["P1", "P2"] {
        let ingest = row(unit, "ingest");
        assert_eq!(
            (&ingest["status"], &ingest["cached"], &ingest["would_run"]),
            (&"cached".into(), &true.into(), &false.into())
        );
        let key = ingest["key"].as_str().unwrap();
        assert!(p.path(&format!("cache/manifests/ingest/{key}.json")).exists(), "{ingest}");
        let hu = row(unit, "hu");
        assert_eq!((&hu["status"], &hu["cached"], &hu["would_run"]), (&"stale".into(), &false.into(), &true.into()));
        assert_eq!(hu["reasons"], serde_json::json!(["parameter `hu_max` changed: 400.0 → 500.0"]));
        assert_eq!(hu["key"].as_str().map(str::len), Some(64), "{hu}");
        let drr = row(unit, "drr");
        assert_eq!(
            (&drr["status"], &drr["after"], &drr["would_run"]),
            (&"pending".into(), &"hu".into(), &false.into())
        );
        assert!(drr["key"].is_null() && drr["reasons"] == serde_json::json!([]), "{drr}");
    }
    assert_eq!(row("cohort", "metrics")["after"], "P1/hu");

    // The status table: its header, one grid row per unit, then the notes.
    let table = text(&p.aret(&["status", "pipeline.toml"]).stdout);
    let mut lines = table.lines();
    let header: Vec<&str> = lines.next().unwrap().split_whitespace().collect();
    assert_eq!(header[1..], stages[..], "{table}");
    let mut units: Vec<&str> = rows.iter().map(|r| r["unit"].as_str().unwrap()).collect();
    units.dedup();
    let mut cells = 0;
    for unit in &units {
        let line: Vec<&str> = lines.next().unwrap().split_whitespace().collect();
        assert_eq!(line[0], *unit, "{table}");
        for (stage, cell) in stages.iter().zip(&line[1..]) {
            if *cell != "·" {
                assert_eq!(row(unit, stage)["status"], *cell, "{unit} · {stage}:\n{table}");
                cells += 1;
            }
        }
    }
    assert_eq!(cells, rows.len(), "{table}");
    let notes: Vec<&str> = lines.collect();
    for r in rows {
        let why = match r["status"].as_str().unwrap() {
            "stale" | "blocked" => {
                r["reasons"].as_array().unwrap().iter().map(|w| w.as_str().unwrap()).collect::<Vec<_>>().join("; ")
            }
            "pending" => format!("after `{}`", r["after"].as_str().unwrap()),
            _ => continue,
        };
        let note = format!("{} · {}: {why}", r["unit"].as_str().unwrap(), r["stage"].as_str().unwrap());
        assert!(notes.contains(&note.as_str()), "{note}:\n{table}");
    }

    // The dry run's lines, one per row in the same order.
    let lines = text(&p.aret(&["run", "pipeline.toml", "--dry-run"]).stdout);
    assert_eq!(lines.lines().count(), rows.len(), "{lines}");
    for (line, r) in lines.lines().zip(rows) {
        let words: Vec<&str> = line.split_whitespace().collect();
        assert_eq!((words[0], words[1]), (r["unit"].as_str().unwrap(), r["stage"].as_str().unwrap()), "{line}");
        let reasons: Vec<&str> = r["reasons"].as_array().unwrap().iter().map(|w| w.as_str().unwrap()).collect();
        if r["cached"] == true {
            assert!(line.ends_with(" cached"), "{line}");
        } else if r["would_run"] == true {
            assert!(line.contains(&format!("would run: {}", reasons.join("; "))), "{line}");
        } else {
            assert!(line.contains(&format!("would run after `{}`", r["after"].as_str().unwrap())), "{line}");
        }
    }

    // The key the plan gave hu is the key hu is cached under once it has run.
    p.run(&[]);
    let after = json(&["status", "pipeline.toml", "--json"]);
    for unit in ["P1", "P2"] {
        let hu = after["rows"].as_array().unwrap().iter().find(|r| r["unit"] == unit && r["stage"] == "hu").unwrap();
        assert_eq!((&hu["status"], &hu["key"]), (&"cached".into(), &row(unit, "hu")["key"]));
    }

    let refused = p.aret(&["run", "pipeline.toml", "--json"]);
    assert!(!refused.status.success() && text(&refused.stderr).contains("--json goes with --dry-run"));
}

#[test]
fn presets_lists_each_with_its_first_comment_line_sorted_by_name() {
    let p = Project::new(&[], 0);
    let missing = p.aret(&["presets"]);
    assert!(!missing.status.success() && text(&missing.stderr).contains("presets: no such presets directory"));
    let dir = p.path("presets");
    std::fs::create_dir_all(dir.join("old")).unwrap();
    std::fs::write(dir.join("tiles.toml"), "# Blind, by tiling the lungs.\n# More words.\n[drr]\n").unwrap();
    std::fs::write(dir.join("blind.toml"), "#Assistance level C\r\n[select]\n").unwrap();
    std::fs::write(dir.join("bare.toml"), "[train]\n# a comment, but not on the first line\n").unwrap();
    std::fs::write(dir.join("README.md"), "# not a preset\n").unwrap();
    std::fs::write(dir.join("old/gone.toml"), "# in a subfolder: not listed\n").unwrap();
    let out = p.aret(&["presets"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(
        text(&out.stdout),
        "bare   (no description: its first line should be a `# ...` comment)\n\
         blind  Assistance level C\n\
         tiles  Blind, by tiling the lungs.\n"
    );
    let elsewhere = p.aret(&["presets", "lab/presets"]);
    assert!(
        !elsewhere.status.success() && text(&elsewhere.stderr).contains("lab/presets"),
        "{}",
        text(&elsewhere.stderr)
    );

    // The shipped presets all say what they are.
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("presets");
    let out = Command::new(BIN).arg("presets").arg(&shipped).output().unwrap();
    let list = text(&out.stdout);
    let files =
        std::fs::read_dir(&shipped).unwrap().flatten().filter(|e| e.path().extension().is_some_and(|x| x == "toml"));
    assert_eq!(list.lines().count(), files.count(), "{list}");
    assert!(!list.contains("(no description"), "{list}");
}

#[test]
fn completions_name_the_subcommands_for_each_shell() {
    for shell in ["bash", "zsh", "fish"] {
        let out = Command::new(BIN).args(["completions", shell]).output().unwrap();
        assert!(out.status.success(), "{shell}: {}", text(&out.stderr));
        let script = text(&out.stdout);
        // Subcommands, and flags (fish names them without their dashes).
        for word in ["run", "status", "gc", "presets", "completions", "dry-run", "patients"] {
            assert!(script.contains(word), "{shell}'s script does not mention {word}");
        }
    }
    let out = Command::new(BIN).args(["completions", "tcsh"]).output().unwrap();
    assert!(!out.status.success());
}

#[test]
fn dry_run_explains_new_and_changed_inputs() {
    let p = Project::new(&["P1"], 3);
    let dry = text(&p.aret(&["run", "pipeline.toml", "--dry-run"]).stdout);
    assert!(dry.contains("ingest   would run: never run"), "{dry}");
    assert!(!p.path("out").exists(), "a dry run writes no results");
    p.run(&[]);
    let mut specs = series(3);
    specs[1].intercept = Some(-1000.0);
    p.write_patient("P1", &specs);
    let dry = text(&p.aret(&["run", "pipeline.toml", "--dry-run"]).stdout);
    assert!(dry.contains("input changed: source/series/slice_1.dcm"), "{dry}");
    assert!(dry.contains("would run after `ingest`"), "{dry}");
}

#[test]
fn hu_output_matches_the_window_formula() {
    let p = Project::new(&["P1"], 3);
    p.run(&[]);
    let hu = std::fs::read(p.path("out/P1/ct_hu.raw")).unwrap();
    let unit = std::fs::read(p.path("out/P1/ct_unit.raw")).unwrap();
    assert_eq!(unit.len(), hu.len() * 2);
    for (h, u) in hu.chunks_exact(2).zip(unit.chunks_exact(4)) {
        let h = f64::from(i16::from_le_bytes([h[0], h[1]]));
        let u = f32::from_le_bytes([u[0], u[1], u[2], u[3]]);
        let expected = ((h.clamp(-1000.0, 400.0) + 1000.0) / 1400.0) as f32;
        assert_eq!(u, expected);
    }
}

#[test]
fn a_bad_patient_fails_alone_with_a_clear_message() {
    let p = Project::new(&["P1", "P2"], 3);
    let mut specs = series(3);
    specs[2].ipp[2] = specs[1].ipp[2]; // duplicate slice position
    p.write_patient("P2", &specs);
    let out = p.aret(&["run", "pipeline.toml"]);
    assert_eq!(out.status.code(), Some(1));
    let stdout = text(&out.stdout);
    assert!(stdout.contains("failed: P2 · ingest:"), "{stdout}");
    assert!(stdout.to_lowercase().contains("duplicate"), "{stdout}");
    let r = p.report("out");
    assert_eq!(count(&r, "hu", "computed"), 1);
    assert_eq!(count(&r, "hu", "skipped"), 1);
    // The cohort metrics still run: the failed patient reported and counted, the patient
    // without annotations listed as unscored, nothing scored.
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(p.path("out/summary.json")).unwrap()).unwrap();
    assert_eq!(summary["failed"], serde_json::json!(["P2"]));
    assert_eq!(summary["unscored"], serde_json::json!(["P1"]));
    assert_eq!(summary["scored"], 0);
    assert_eq!(std::fs::read_to_string(p.path("out/results.csv")).unwrap().lines().count(), 1, "header only");
}

#[test]
fn no_identifying_tag_reaches_any_artifact() {
    let p = Project::new(&["P1"], 2);
    let mut specs = series(2);
    for s in &mut specs {
        s.patient = Some(("SECRET^NAME".into(), "SECRETID42".into()));
    }
    p.write_patient("P1", &specs);
    let out = p.aret(&["run", "pipeline.toml"]);
    assert!(out.status.success());
    for entry in walkdir::WalkDir::new(p.path("out")).into_iter().chain(walkdir::WalkDir::new(p.path("cache"))) {
        let entry = entry.unwrap();
        if entry.file_type().is_file() {
            let bytes = std::fs::read(entry.path()).unwrap();
            let body = String::from_utf8_lossy(&bytes);
            assert!(!body.contains("SECRET"), "{} leaks a patient tag", entry.path().display());
        }
    }
    assert!(!text(&out.stdout).contains("SECRET") && !text(&out.stderr).contains("SECRET"));
}

#[test]
fn config_errors_name_key_and_line_and_bad_patients_are_listed() {
    let p = Project::new(&["P1"], 2);
    p.write_config("pipeline.toml", "cache", "out", "[hu]\nhu_mx = 3\n");
    let out = p.aret(&["run", "pipeline.toml"]);
    assert_eq!(out.status.code(), Some(2));
    let err = text(&out.stderr);
    assert!(err.contains("pipeline.toml") && err.contains("line 28") && err.contains("hu_mx"), "{err}");

    p.write_config("pipeline.toml", "cache", "out", "");
    let err = text(&p.aret(&["run", "pipeline.toml", "--patients", "P1,P7"]).stderr);
    assert!(err.contains("`P7`") && err.contains("it has: P1"), "{err}");
    let err = text(&p.aret(&["run", "pipeline.toml", "--until", "hx"]).stderr);
    assert!(err.contains("--until hx"), "{err}");
    let err = text(&p.aret(&["run", "pipeline.toml", "--force", "hux"]).stderr);
    assert!(err.contains("--force hux"), "{err}");
}

#[test]
fn until_and_patients_narrow_the_run() {
    let p = Project::new(&["P1", "P2"], 2);
    let r = p.run(&["--until", "ingest", "--patients", "P2"]);
    assert_eq!(count(&r, "ingest", "computed"), 1);
    assert_eq!(count(&r, "hu", "computed") + count(&r, "hu", "cached"), 0);
    assert!(p.path("out/P2/ct_hu.mhd").exists() && !p.path("out/P1").exists());
}

#[test]
fn four_processes_on_one_cache_at_once_compute_each_result_once_and_agree_with_one_run() {
    let ids = ["P1", "P2", "P3", "P4", "P5", "P6"];
    let p = Project::new(&ids, 4);
    let start = || {
        let mut command = p.command(&["run", "pipeline.toml"]);
        command.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().unwrap()
    };
    let children: Vec<_> = (0..4).map(|_| start()).collect();
    // "N computed, M cached, F failed, S skipped in …" ends each process's table.
    let totals = |stdout: &str| -> [usize; 4] {
        let line = stdout.lines().find(|l| l.contains(" computed, ")).unwrap_or_else(|| panic!("{stdout}"));
        let n: Vec<usize> = line.split(", ").map(|part| part.split(' ').next().unwrap().parse().unwrap()).collect();
        [n[0], n[1], n[2], n[3]]
    };
    let mut computed = 0;
    for child in children {
        let run = child.wait_with_output().unwrap();
        let (stdout, stderr) = (text(&run.stdout), text(&run.stderr));
        assert!(run.status.success() && !stderr.contains("warning"), "{stdout}\n{stderr}");
        let [done, _, failed, skipped] = totals(&stdout);
        assert_eq!((failed, skipped), (0, 0), "{stdout}");
        computed += done;
    }
    // One process alone on a fresh cache: what it computes, the four computed once between them.
    p.write_config("whole.toml", "cache-whole", "out-whole", "");
    let alone = p.aret(&["run", "whole.toml"]);
    assert!(alone.status.success());
    assert_eq!(computed, totals(&text(&alone.stdout))[0], "each result computed once");
    let files = |dir: &str| -> Vec<PathBuf> {
        let mut files: Vec<PathBuf> = walkdir::WalkDir::new(p.path(dir))
            .into_iter()
            .map(|e| e.unwrap())
            .filter(|e| e.file_type().is_file())
            .map(|e| e.path().strip_prefix(p.path(dir)).unwrap().to_path_buf())
            .collect();
        files.sort();
        files
    };
    let temporary = |f: &PathBuf| f.file_name().unwrap().to_string_lossy().starts_with(".tmp-");
    assert!(!files("cache").iter().chain(&files("out")).any(temporary), "no temporary file is left");
    assert!(files("cache/leases").is_empty(), "every process gave its lease back");
    // The same bytes in the same files; run_report.json holds each run's own times.
    let published: Vec<PathBuf> = files("out").into_iter().filter(|f| f.as_os_str() != "run_report.json").collect();
    assert!(published.len() > ids.len() * 5, "{published:?}");
    assert_eq!(
        published,
        files("out-whole").into_iter().filter(|f| f.as_os_str() != "run_report.json").collect::<Vec<_>>()
    );
    let read = |dir: &str, file: &PathBuf| std::fs::read(p.path(dir).join(file)).unwrap();
    let differ: Vec<&PathBuf> = published.iter().filter(|f| read("out", f) != read("out-whole", f)).collect();
    assert!(differ.is_empty(), "{differ:?}");
}

/// Bigger slices so that a run lasts long enough to be killed in the middle of it.
fn big_series(n: usize) -> Vec<SliceSpec> {
    (0..n)
        .map(|k| {
            let mut s = SliceSpec::ct(k);
            s.rows = 384;
            s.cols = 384;
            s.stored = (0..384 * 384).map(|i| ((i * 7 + k * 13) % 2000) as i32).collect();
            s
        })
        .collect()
}

#[test]
fn a_run_killed_at_any_moment_leaves_nothing_a_later_run_trusts() {
    let p = Project::new(&[], 0);
    for id in ["P1", "P2", "P3"] {
        p.write_patient(id, &big_series(24));
    }
    p.write_config("reference.toml", "ref_cache", "ref_out", "");
    let out = p.aret(&["run", "reference.toml"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    for delay_ms in [5u64, 30, 60, 100, 150, 250, 400] {
        let mut child = p
            .command(&["run", "pipeline.toml", "--force", "ingest,hu"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(delay_ms));
        unsafe_kill(child.id());
        let _ = child.wait();
        // Its lease names a process that has ended on this host: gc need not wait for it.
        let gc = p.aret(&["gc", "pipeline.toml"]);
        assert!(gc.status.success(), "gc after kill at {delay_ms} ms: {}", text(&gc.stderr));
        // Whatever the kill left, a normal run completes and gives the reference bytes.
        let out = p.aret(&["run", "pipeline.toml"]);
        assert!(out.status.success(), "after kill at {delay_ms} ms: {}", text(&out.stderr));
        assert_same_results(&p.path("out"), &p.path("ref_out"));
        let r = p.run(&["--verify"]);
        assert_eq!(count(&r, "ingest", "computed") + count(&r, "hu", "computed"), 0, "verify finds nothing corrupt");
    }
}

/// `aret-pipe ARGS` in the project's folder as a process on another host: in a UTS namespace of
/// its own named `host` (`unshare --uts`, which needs root); `None` where namespaces are refused.
fn on_other_host(p: &Project, host: &str, args: &str) -> Option<std::process::Child> {
    let probe = Command::new("unshare").args(["--uts", "true"]).output();
    if !probe.is_ok_and(|o| o.status.success()) {
        eprintln!("skipped: `unshare --uts` is not allowed here (it needs root)");
        return None;
    }
    let script = format!("hostname {host} && exec {BIN} {args}");
    let child = Command::new("unshare")
        .args(["--uts", "sh", "-c", &script])
        .current_dir(p.path(""))
        .env("CI", "true")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    Some(child)
}

#[test]
fn a_run_killed_on_another_host_holds_gc_off_until_its_lease_expires() {
    let p = Project::new(&[], 0);
    for id in ["P1", "P2", "P3"] {
        p.write_patient(id, &big_series(24));
    }
    let Some(mut child) = on_other_host(&p, "node-b", "run pipeline.toml") else { return };
    // unshare and sh exec: the run keeps the child's pid. It names its lease after its host.
    let lease = p.path(&format!("cache/leases/node_b-{}-0.json", child.id()));
    let started = std::time::Instant::now();
    while !lease.exists() && started.elapsed() < std::time::Duration::from_secs(20) {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    assert!(lease.exists(), "no lease of node-b's run in {:?}", p.path("cache/leases"));
    std::thread::sleep(std::time::Duration::from_millis(200));
    unsafe_kill(child.id());
    let _ = child.wait();
    let killed = child.id();

    // Here its pid means nothing: only its lease's expiry ends it. gc refuses, naming it.
    let gc = p.aret(&["gc", "pipeline.toml"]);
    assert!(!gc.status.success(), "{}", text(&gc.stdout));
    assert!(text(&gc.stderr).contains(&format!("aret-pipe run on node_b (pid {killed})")), "{}", text(&gc.stderr));
    // A run here goes on beside it, and leaves a temporary file of node-b alone, one of a
    // process that ended here not.
    std::fs::create_dir_all(p.path("out/P1")).unwrap();
    let theirs = p.path(&format!("out/P1/.tmp-node_b-{killed}-0-1"));
    let ours = p.path(&format!(
        "out/P1/.tmp-{}-{}-0-1",
        aret_pipe::engine::files::this_host(),
        support::toy_stages::ended_pid()
    ));
    for file in [&theirs, &ours] {
        std::fs::write(file, "half").unwrap();
    }
    p.run(&[]);
    assert!(theirs.exists() && !ours.exists());
    // Its leases expire (as 120 s without renewal would have them): then gc goes on, and takes
    // node-b's leftovers and its leases.
    let leases: Vec<PathBuf> = std::fs::read_dir(p.path("cache/leases")).unwrap().map(|e| e.unwrap().path()).collect();
    assert!(leases.contains(&lease) && leases.iter().all(|l| l.to_string_lossy().contains("/node_b-")), "{leases:?}");
    for path in &leases {
        let mut record: Value = serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap();
        record["expires_unix"] = Value::from(aret_pipe::engine::lease::unix_now() - 1);
        std::fs::write(path, serde_json::to_vec(&record).unwrap()).unwrap();
    }
    let gc = p.aret(&["gc", "pipeline.toml"]);
    assert!(gc.status.success(), "{}", text(&gc.stderr));
    assert!(!theirs.exists() && std::fs::read_dir(p.path("cache/leases")).unwrap().next().is_none());
}

#[test]
fn sigterm_lets_the_stages_in_progress_finish_and_the_next_run_goes_on() {
    let p = Project::new(&[], 0);
    for id in ["P1", "P2", "P3", "P4", "P5", "P6"] {
        p.write_patient(id, &big_series(24));
    }
    let child = p
        .command(&["run", "pipeline.toml"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Signal once the first stage has been cached: the handler is in place by then, and the
    // run has most of its stages ahead of it.
    let started = std::time::Instant::now();
    while !has_a_manifest(&p.path("cache")) {
        assert!(started.elapsed().as_secs() < 60, "the run cached nothing in a minute");
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    let status = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(130), "{}\n{}", text(&out.stdout), text(&out.stderr));
    assert!(text(&out.stderr).contains("stopping"), "{}", text(&out.stderr));
    assert!(text(&out.stdout).contains("run the same command again"), "{}", text(&out.stdout));
    let first = p.report("out");
    let records = first["records"].as_array().unwrap();
    let stopped = records.iter().filter(|r| r["outcome"] == "interrupted").count();
    let done: Vec<(String, String)> = records
        .iter()
        .filter(|r| r["outcome"] == "computed")
        .map(|r| (r["unit"].as_str().unwrap().into(), r["stage"].as_str().unwrap().into()))
        .collect();
    assert!(stopped > 0 && !done.is_empty(), "{first}");
    assert!(records.iter().all(|r| r["outcome"] == "computed" || r["outcome"] == "interrupted"), "{first}");
    // The next run serves what finished from the cache and does the rest.
    let second = p.run(&[]);
    for r in second["records"].as_array().unwrap() {
        let key = (r["unit"].as_str().unwrap().to_string(), r["stage"].as_str().unwrap().to_string());
        let want = if done.contains(&key) { "cached" } else { "computed" };
        assert_eq!(r["outcome"], want, "{key:?}");
    }
}

/// Whether the cache `dir` holds any stage's manifest yet.
fn has_a_manifest(dir: &Path) -> bool {
    walkdir::WalkDir::new(dir.join("manifests")).into_iter().flatten().any(|e| e.file_type().is_file())
}

fn unsafe_kill(pid: u32) {
    let status = Command::new("kill").args(["-KILL", &pid.to_string()]).status().unwrap();
    assert!(status.success() || status.code() == Some(1));
}

fn assert_same_results(out: &Path, reference: &Path) {
    for id in ["P1", "P2", "P3"] {
        for f in ["ct_hu.mhd", "ct_hu.raw", "ct_unit.mhd", "ct_unit.raw", "ct_series.json"] {
            let a = std::fs::read(out.join(id).join(f)).unwrap();
            let b = std::fs::read(reference.join(id).join(f)).unwrap();
            assert!(a == b, "{id}/{f} differs from the reference run");
        }
    }
}

#[test]
fn gc_deletes_orphan_blobs_and_reports_what_it_frees() {
    let p = Project::new(&["P1"], 2);
    p.run(&[]);
    // A killed run can leave a blob whose manifest was never written.
    let hash = blake3::hash(b"orphan").to_hex().to_string();
    let orphan = p.path(&format!("cache/blobs/{}/{hash}", &hash[..2]));
    std::fs::create_dir_all(orphan.parent().unwrap()).unwrap();
    std::fs::write(&orphan, vec![7u8; 4096]).unwrap();
    let out = p.aret(&["gc", "pipeline.toml"]);
    assert!(out.status.success());
    let line = text(&out.stdout);
    assert!(line.starts_with("gc: deleted") && line.contains("MiB"), "{line}");
    assert!(!orphan.exists());
    let r = p.run(&[]);
    assert_eq!(count(&r, "hu", "cached"), 1, "gc keeps what manifests reference");
}

#[test]
fn gc_prune_and_forget_drop_only_what_they_name_and_a_dry_run_deletes_nothing() {
    let p = Project::new(&["P1"], 2);
    p.run(&[]);
    // Another configuration on the same cache: a different bootstrap, so its own metrics.
    p.write_config("other.toml", "cache", "out-other", "[metrics]\nbootstrap_resamples = 200\n");
    assert!(p.aret(&["run", "other.toml"]).status.success());
    let manifests = || walkdir::WalkDir::new(p.path("cache/manifests")).min_depth(2).into_iter().count();
    let before = manifests();

    let dry = p.aret(&["gc", "pipeline.toml", "--prune", "--dry-run"]);
    let line = text(&dry.stdout);
    assert!(dry.status.success() && line.starts_with("gc --dry-run: would forget 1 stage result(s)"), "{line}");
    assert_eq!(manifests(), before, "a dry run deletes nothing");

    let both = p.aret(&["gc", "pipeline.toml", "other.toml", "--prune"]);
    assert!(text(&both.stdout).starts_with("gc: forgot 0 stage result(s)"), "{}", text(&both.stdout));

    let pruned = p.aret(&["gc", "pipeline.toml", "--prune"]);
    assert!(text(&pruned.stdout).starts_with("gc: forgot 1 stage result(s)"), "{}", text(&pruned.stdout));
    assert_eq!(manifests(), before - 1);
    let r = p.run(&[]);
    assert_eq!(count(&r, "metrics", "cached"), 1, "what pipeline.toml uses stays");
    assert!(p.aret(&["run", "other.toml"]).status.success());
    assert_eq!(count(&p.report("out-other"), "metrics", "computed"), 1, "the other's metrics went");

    // The CT volumes go, and come back in seconds; nothing after them recomputes.
    let forgot = p.aret(&["gc", "pipeline.toml", "--forget", "hu"]);
    assert!(text(&forgot.stdout).starts_with("gc: forgot 1 stage result(s) of hu"), "{}", text(&forgot.stdout));
    let r = p.run(&[]);
    assert_eq!((count(&r, "hu", "computed"), count(&r, "drr", "cached"), count(&r, "train", "cached")), (1, 1, 1));
    let unknown = p.aret(&["gc", "pipeline.toml", "--forget", "hue"]);
    assert!(!unknown.status.success() && text(&unknown.stderr).contains("--forget hue: no such stage"));

    p.write_config("elsewhere.toml", "cache-elsewhere", "out-elsewhere", "");
    let refused = p.aret(&["gc", "pipeline.toml", "elsewhere.toml", "--prune"]);
    assert!(!refused.status.success());
    assert!(text(&refused.stderr).contains("prune one cache at a time"), "{}", text(&refused.stderr));
}

#[test]
fn gc_deletes_nothing_while_a_run_holds_the_cache_but_a_dry_run_may_look() {
    let p = Project::new(&["P1"], 2);
    p.run(&[]);
    // A run in progress on another host holds a live lease on the cache.
    let running = support::leases::pretend_lease(&p.path("cache"), "node_5", 77, "aret-pipe run", 60);
    let refused = p.aret(&["gc", "pipeline.toml", "--forget", "hu"]);
    assert!(!refused.status.success());
    let said = text(&refused.stderr);
    assert!(said.contains("is in use by aret-pipe run on node_5 (pid 77), alive until"), "{said}");
    assert!(!p.path("cache/leases/gc.json").exists(), "the refused gc leaves no lease");
    let dry = p.aret(&["gc", "pipeline.toml", "--forget", "hu", "--dry-run"]);
    assert!(
        dry.status.success() && text(&dry.stdout).contains("would forget 1 stage result(s) of hu"),
        "{}",
        text(&dry.stdout)
    );
    std::fs::remove_file(running).unwrap();
    let r = p.run(&[]);
    assert_eq!(count(&r, "hu", "cached"), 1, "neither deleted anything");
    // A lease that expired (its process was killed on its host) no longer holds gc back, and
    // goes with the garbage.
    let expired = support::leases::pretend_lease(&p.path("cache"), "node_5", 77, "aret-pipe run", -1);
    let gc = p.aret(&["gc", "pipeline.toml"]);
    assert!(gc.status.success() && !expired.exists(), "{}", text(&gc.stderr));
}

/// A one-reader LIDC XML with one nodule: a square contour on the slice at `z_mm`.
fn lidc_xml(z_mm: f64) -> String {
    let points: String = [
        (1, 1),
        (2, 1),
        (3, 1),
        (4, 1),
        (5, 1),
        (5, 2),
        (5, 3),
        (5, 4),
        (4, 4),
        (3, 4),
        (2, 4),
        (1, 4),
        (1, 3),
        (1, 2),
    ]
    .iter()
    .map(|(x, y)| format!("<edgeMap><xCoord>{x}</xCoord><yCoord>{y}</yCoord></edgeMap>"))
    .collect();
    let ratings = "<subtlety>5</subtlety><internalStructure>1</internalStructure><calcification>6</calcification>\
        <sphericity>4</sphericity><margin>4</margin><lobulation>1</lobulation><spiculation>1</spiculation>\
        <texture>5</texture><malignancy>3</malignancy>";
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<LidcReadMessage xmlns="http://www.nih.gov" uid="1.2.3">
  <ResponseHeader><SeriesInstanceUid>{series}</SeriesInstanceUid></ResponseHeader>
  <readingSession>
    <servicingRadiologistID>anon1</servicingRadiologistID>
    <unblindedReadNodule>
      <noduleID>Nodule 001</noduleID>
      <characteristics>{ratings}</characteristics>
      <roi><imageZposition>{z_mm}</imageZposition><imageSOP_UID>1.2.3.4</imageSOP_UID><inclusion>TRUE</inclusion>{points}</roi>
    </unblindedReadNodule>
    <nonNodule><nonNoduleID>n1</nonNoduleID><imageZposition>{z_mm}</imageZposition><locus><xCoord>7</xCoord><yCoord>5</yCoord></locus></nonNodule>
  </readingSession>
</LidcReadMessage>
"#,
        series = support::dicom_writer::SERIES_UID
    )
}

#[test]
fn lidc_layout_reads_series_and_annotations_into_ground_truth() {
    let p = Project::new(&[], 0);
    // TCIA layout: LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/*.dcm + the XML beside them.
    let series = p.path("data/LIDC-IDRI/LIDC-IDRI-0042/1.2.840.1/1.2.840.1.7");
    std::fs::create_dir_all(&series).unwrap();
    let specs = series_of(4);
    write_series(&series, &specs, default_name);
    std::fs::write(series.join("069.xml"), lidc_xml(specs[2].ipp[2])).unwrap();
    std::fs::write(p.path("data/LIDC-IDRI/metadata.csv"), "not a patient\n").unwrap();
    std::fs::create_dir_all(p.path("data/LIDC-IDRI/notes")).unwrap();
    p.write_config("pipeline.toml", "cache", "out", "");
    let text = std::fs::read_to_string(p.path("pipeline.toml")).unwrap().replace("kind = \"dicom\"", "kind = \"lidc\"");
    std::fs::write(p.path("pipeline.toml"), text).unwrap();
    let r = p.run(&[]);
    assert_eq!(count(&r, "ingest", "computed"), 1, "one patient: LIDC-IDRI-0042");

    let truth: Value =
        serde_json::from_slice(&std::fs::read(p.path("out/LIDC-IDRI-0042/ground_truth.json")).unwrap()).unwrap();
    assert_eq!(truth["annotations_file"], "1.2.840.1/1.2.840.1.7/069.xml");
    assert_eq!(truth["non_nodule_marks"], 1);
    assert_eq!(truth["target"], 0);
    let nodule = &truth["nodules"][0];
    // matplotlib's test on pixel centres, contour points removed: the 3 × 2 interior (x 2..4, y 2..3).
    assert_eq!(nodule["consensus_voxels"], 6);
    assert!((nodule["volume_mm3"].as_f64().unwrap() - 6.0 * 0.7 * 0.7 * 2.5).abs() < 1e-9);
    let mask = std::fs::read(p.path("out/LIDC-IDRI-0042/gt_mask.raw")).unwrap();
    let on: Vec<usize> = mask.iter().enumerate().filter(|(_, &v)| v == 1).map(|(i, _)| i).collect();
    let (cols, rows) = (8, 6);
    let expected: Vec<usize> = (2..4).flat_map(|y| (2..5).map(move |x| x + cols * (y + rows * 2))).collect();
    assert_eq!(on, expected);
    assert!(p.path("out/LIDC-IDRI-0042/gt_mask.mhd").exists());
}

/// `n` slices with square pixels (LIDC annotations assume them).
fn series_of(n: usize) -> Vec<SliceSpec> {
    let mut specs = series(n);
    for s in &mut specs {
        s.pixel_spacing = [0.7, 0.7];
    }
    specs
}

#[test]
fn stages_rerun_only_for_the_outputs_they_read() {
    let p = Project::new(&[], 0);
    let series = p.path("data/P1/series");
    std::fs::create_dir_all(&series).unwrap();
    let specs = series_of(4);
    write_series(&series, &specs, default_name);
    std::fs::write(series.join("reads.xml"), lidc_xml(specs[2].ipp[2])).unwrap();
    p.run(&[]);
    // A new consensus level changes ground_truth.json only: hu (which reads ct_hu) and drr (whose
    // ROI centre is explicit in these tests) stay cached.
    p.write_config("pipeline.toml", "cache", "out", "[ingest]\nclevel = 1.0\n");
    let r = p.run(&[]);
    assert_eq!(count(&r, "ingest", "computed"), 1);
    assert_eq!((count(&r, "hu", "cached"), count(&r, "drr", "cached"), count(&r, "train", "cached")), (1, 1, 1));
}

/// `[train] model = "truth"` through the engine: the CT on the lattice, one log row, and a key
/// that the fits' own keys do not reach (`--set` picks the model over the file's, whose VM table
/// it then drops; a new `log_every` keeps the ceiling cached).
#[test]
fn the_perfect_field_runs_through_the_engine_and_ignores_the_fits_keys() {
    let p = Project::new(&["P1"], 6);
    // The box around the small CT (the other tests' box at the origin misses it: their fits
    // fit empty views, and the ceiling would be zero everywhere).
    let config = std::fs::read_to_string(p.path("pipeline.toml")).unwrap();
    let config = config.replacen("roi_center = [0.0, 0.0, 0.0]", "roi_center = [-97.6, -78.3, 16.25]", 1);
    std::fs::write(p.path("pipeline.toml"), config).unwrap();
    let r = p.run(&["--set", "train.model=truth"]);
    assert_eq!((count(&r, "train", "computed"), count(&r, "grid", "computed")), (1, 1));
    let log = std::fs::read_to_string(p.path("out/P1/train_log.csv")).unwrap();
    assert_eq!(log.lines().count(), 2, "a header and one row: {log}");
    let model = std::fs::read(p.path("out/P1/model.safetensors")).unwrap();
    assert!(String::from_utf8_lossy(&model[..400.min(model.len())]).contains(r#"\"model\":\"truth\""#));
    let r = p.run(&["--set", "train.model=truth", "--set", "train.log_every=5"]);
    assert_eq!(count(&r, "train", "cached"), 1, "log_every is not the ceiling's key");
    // The file's own VM table under model = "truth" is an error naming it.
    let out = p.aret(&["run", "pipeline.toml", "--set", "train.model=truth", "--set", "train.vm.rank=3"]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success() && stderr.contains("[train.vm]") && stderr.contains("model = \"vm\""), "{stderr}");
}

#[test]
fn shards_compute_their_patients_and_the_gather_the_cohort_as_one_run_would() {
    let ids = ["P1", "P2", "P3", "P4"];
    let p = Project::new(&ids, 4);
    // Where each patient falls among two shards: the same rule as the tool's.
    let shard_of = |id: &str| aret_pipe::shard::shard_of(id, 2);
    let gather = p.aret(&["run", "pipeline.toml", "--gather"]);
    let refused = text(&gather.stderr);
    assert!(!gather.status.success() && refused.contains("4 of 4 patients are not computed yet"), "{refused}");
    assert!(refused.contains("--patients P1,P2,P3,P4"), "{refused}");

    let first = p.run(&["--shard", "0/2"]);
    let in_first: Vec<&str> = ids.iter().copied().filter(|id| shard_of(id) == 0).collect();
    assert_eq!(count(&first, "select", "computed"), in_first.len());
    assert_eq!(count(&first, "metrics", "computed") + count(&first, "metrics", "cached"), 0, "no cohort stage");
    let left: Vec<&str> = ids.iter().copied().filter(|id| shard_of(id) == 1).collect();
    if !left.is_empty() {
        let gather = p.aret(&["run", "pipeline.toml", "--gather", "--shard-count", "2"]);
        let refused = text(&gather.stderr);
        assert!(!gather.status.success() && refused.contains(&left.join(", ")), "{refused}");
        assert!(refused.contains("their shards of 2: 1 (a Slurm array: `sbatch --array=1 "), "{refused}");
    }
    let alone = p.aret(&["run", "pipeline.toml", "--shard-count", "2"]);
    assert!(text(&alone.stderr).contains("--shard-count goes with --shard-from-env or --gather"));
    // The second shard as a Slurm array task would run it.
    let second = p
        .command(&["run", "pipeline.toml", "--shard-from-env"])
        .env("SLURM_ARRAY_TASK_ID", "1")
        .env("SLURM_ARRAY_TASK_COUNT", "2")
        .output()
        .unwrap();
    assert!(second.status.success(), "{}", text(&second.stderr));
    let gathered = p.run(&["--gather"]);
    assert_eq!(count(&gathered, "select", "cached"), 4);
    assert_eq!(count(&gathered, "metrics", "computed"), 1);
    // One run over the whole cohort on a fresh cache writes the same per-patient results and
    // the same cohort summary (these patients have no annotations: all four are unscored).
    p.write_config("whole.toml", "cache-whole", "out-whole", "");
    assert!(p.aret(&["run", "whole.toml"]).status.success());
    let read = |path: String| std::fs::read(p.path(&path)).unwrap();
    for id in ids {
        for file in ["result.json", "density.raw", "nodule_mask.raw"] {
            assert_eq!(read(format!("out/{id}/{file}")), read(format!("out-whole/{id}/{file}")), "{id} {file}");
        }
    }
    let summary: Value = serde_json::from_slice(&read("out/summary.json".into())).unwrap();
    assert_eq!(summary["unscored"].as_array().map(Vec::len), Some(4), "{summary}");
    assert_eq!(read("out/summary.json".into()), read("out-whole/summary.json".into()));

    // A gather checks the sizes of the per-patient blobs it serves; what the cohort stages read
    // is hashed as they read it, and --verify hashes the rest. A byte changed in P1's ct_unit
    // (read by no cohort stage), through its published link to the blob:
    let blob = p.path("out/P1/ct_unit.raw");
    let mut bytes = std::fs::read(&blob).unwrap();
    bytes[7] ^= 0x5a;
    std::fs::set_permissions(&blob, std::os::unix::fs::PermissionsExt::from_mode(0o644)).unwrap();
    std::fs::write(&blob, &bytes).unwrap();
    let gathered = p.run(&["--gather"]);
    assert_eq!((count(&gathered, "hu", "cached"), count(&gathered, "metrics", "cached")), (4, 1));
    let verified = p.aret(&["run", "pipeline.toml", "--gather", "--verify"]);
    let refused = text(&verified.stderr);
    assert!(!verified.status.success() && refused.contains("1 of 4 patients are not computed yet: P1."), "{refused}");
    let mended = p.run(&[]);
    assert_eq!(count(&mended, "hu", "computed"), 1, "a plain run hashes every hit");
    assert!(p.run(&["--gather", "--verify"])["notices"].as_array().unwrap().is_empty());
}
