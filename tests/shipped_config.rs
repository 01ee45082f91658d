//! The shipped `pipeline.toml` is the built-in defaults, documented key by key; the product
//! presets extend it with their difference; `--set` is an edit of the file; a key of a variant
//! the configuration does not pick is an error.

use aret_pipe::config::Config;
use aret_pipe::pipeline;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Each stage's cache key but for its inputs' hashes: name, version, inputs and parameters.
fn stage_keys(config: &Config) -> Vec<(String, u32, Vec<String>, serde_json::Value)> {
    let graph = pipeline::graph(config).unwrap();
    graph
        .stages()
        .iter()
        .map(|s| (s.name().to_string(), s.version(), s.inputs().iter().map(|i| i.to_string()).collect(), s.params()))
        .collect()
}

/// Comment lines that hold a measurement, a date or an issue number (product files say what a
/// key does; measurements live in docs/results.md and lab/).
fn is_log(comment: &str) -> bool {
    let has_percent = comment.split('%').count() > 1 && comment.chars().any(|c| c.is_ascii_digit());
    let has_date = comment.as_bytes().windows(5).any(|w| w[0] == b'2' && w[1] == b'0' && w[4] == b'-');
    let lower = comment.to_lowercase();
    let has_issue = ["issue ", "stop "]
        .iter()
        .any(|w| lower.match_indices(w).any(|(i, m)| lower[i + m.len()..].starts_with(|c: char| c.is_ascii_digit())));
    has_percent || has_date || has_issue
}

#[test]
fn the_shipped_pipeline_documents_every_key_in_at_most_three_lines_and_logs_nothing() {
    let path = root().join("pipeline.toml");
    let config = Config::load(&path).unwrap();
    assert_eq!(config.pipeline.name, "default");
    let text = std::fs::read_to_string(&path).unwrap();
    let lines: Vec<&str> = text.lines().map(str::trim).collect();
    for (n, line) in lines.iter().enumerate() {
        if line.starts_with('#') {
            assert!(!is_log(line), "pipeline.toml:{}: `{line}` is a measurement, a date or an issue", n + 1);
        }
        if line.is_empty() || line.starts_with('#') || line.starts_with('[') {
            continue;
        }
        let comments = lines[..n].iter().rev().take_while(|l| l.starts_with('#')).count();
        assert!((1..=3).contains(&comments), "pipeline.toml:{}: `{line}` has {comments} comment lines", n + 1);
    }
}

#[test]
fn a_config_of_only_its_name_and_dataset_runs_exactly_what_pipeline_toml_runs() {
    let shipped = Config::load(&root().join("pipeline.toml")).unwrap();
    let minimal = Config::parse(
        "[pipeline]\nname = \"default\"\n[dataset]\nkind = \"phantom\"\ncohort = \"tools/cohorts/paper19\"\n",
    )
    .unwrap();
    let (a, b) = (stage_keys(&shipped), stage_keys(&minimal));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x, y, "stage `{}`", x.0);
    }
}

/// The product presets: a one-line description first, `extends`, and their difference in at
/// most 15 keys, each group of keys under a comment.
#[test]
fn presets_extend_the_shipped_method_with_their_difference() {
    for dir in [root().join("presets"), root().join("lab/presets")] {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_none_or(|e| e != "toml") {
                continue;
            }
            let config = Config::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            assert_ne!(config.pipeline.name, "default", "{}", path.display());
            let text = std::fs::read_to_string(&path).unwrap();
            let lines: Vec<&str> = text.lines().map(str::trim).collect();
            assert!(lines[0].starts_with("# ") && lines[0].len() > 10, "{}: no description first", path.display());
            assert!(lines[1].starts_with("extends = "), "{}: the second line extends", path.display());
            let keys: Vec<(usize, &str)> = lines
                .iter()
                .enumerate()
                .filter(|(_, l)| !l.is_empty() && !l.starts_with('#') && !l.starts_with('['))
                .map(|(n, l)| (n, *l))
                .collect();
            assert!(keys.len() <= 15, "{}: {} keys", path.display(), keys.len());
            for (n, line) in keys.into_iter().skip(1) {
                let above = lines[..n].iter().rev().find(|l| !l.is_empty()).unwrap();
                let documented = above.starts_with('#') || !(above.starts_with('[') || above.is_empty());
                assert!(documented, "{}:{}: `{line}` has no comment over its group", path.display(), n + 1);
                assert!(!is_log(above), "{}:{}: a measurement in a comment", path.display(), n);
            }
        }
    }
}

/// Paths in a preset are its own folder's; what it extends gives them from its folder.
#[test]
fn a_preset_takes_each_path_from_the_file_that_gives_it() {
    let config = Config::load(&root().join("presets/paper.toml")).unwrap();
    let cache = std::path::absolute(root().join("cache")).unwrap();
    assert_eq!(config.cache_dir(), cache);
    assert_eq!(config.out_dir(), root().join("presets").join("../out-paper"));
    let cohort = std::path::absolute(root().join("tools/cohorts/paper19")).unwrap();
    assert_eq!(config.dataset_root(), cohort);
}

#[test]
fn a_set_is_the_edited_file() {
    let dir = tempfile::tempdir().unwrap();
    let shipped = std::fs::read_to_string(root().join("pipeline.toml")).unwrap();
    let edited =
        shipped.replace("grid = 128\n", "grid = 64\n").replace("sizing = \"shadows\"", "sizing = \"half_max\"");
    assert_ne!(edited, shipped);
    std::fs::write(dir.path().join("edited.toml"), edited).unwrap();
    std::fs::write(dir.path().join("pipeline.toml"), &shipped).unwrap();
    let by_file = Config::load(&dir.path().join("edited.toml")).unwrap();
    let sets = ["train.grid=64".to_string(), "select.sizing=half_max".to_string()];
    let by_set = Config::load_with(&dir.path().join("pipeline.toml"), &sets).unwrap();
    assert_eq!(stage_keys(&by_file), stage_keys(&by_set));
    assert_ne!(stage_keys(&by_set), stage_keys(&Config::load(&dir.path().join("pipeline.toml")).unwrap()));
    // Typed and checked like the file: a wrong type names the key; a missing `=` says how.
    let path = dir.path().join("pipeline.toml");
    let e = format!("{:#}", Config::load_with(&path, &["train.grid=many words".into()]).unwrap_err());
    assert!(e.contains("train.grid"), "{e}");
    let e = format!("{:#}", Config::load_with(&path, &["train.grid=fine".into()]).unwrap_err());
    assert!(e.contains("--set train.grid=fine") && e.contains("grid"), "{e}");
    let e = format!("{:#}", Config::load_with(&path, &["train.grid".into()]).unwrap_err());
    assert!(e.contains("section.key=value"), "{e}");
    let e = format!("{:#}", Config::load_with(&path, &["train.gird=3".into()]).unwrap_err());
    assert!(e.contains("--set train.gird=3") && e.contains("gird"), "{e}");
}

#[test]
fn a_key_of_a_variant_not_picked_is_an_error_naming_it_and_its_variant() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let base = "[pipeline]\nname = \"t\"\n[dataset]\nkind = \"dicom\"\nroot = \"data\"\n";
    let vm = write("vm.toml", &format!("{base}[train]\nmodel = \"dense_tv\"\n[train.vm]\nrank = 8\n"));
    let e = format!("{:#}", Config::load(&vm).unwrap_err());
    assert!(e.contains("line 8") && e.contains("[train.vm]") && e.contains("model = \"vm\""), "{e}");
    assert!(e.contains("model = \"dense_tv\""), "{e}");
    // The built-in model is the dense one: the VM's table alone is an error too.
    let alone = write("alone.toml", &format!("{base}[train.vm]\nrank = 8\n"));
    assert!(format!("{:#}", Config::load(&alone).unwrap_err()).contains("[train.vm]"));
    let half =
        write("half.toml", &format!("{base}[select]\nsizing = \"candidates\"\n[select.half_max]\nfraction = 0.4\n"));
    let e = format!("{:#}", Config::load(&half).unwrap_err());
    assert!(e.contains("[select.half_max]") && e.contains("\"half_max\" or \"shadows\""), "{e}");
    let tiles = write("tiles.toml", &format!("{base}[drr.tiles]\ncounts = [1, 1, 1]\n"));
    let e = format!("{:#}", Config::load(&tiles).unwrap_err());
    assert!(e.contains("[drr.tiles]") && e.contains("roi_center = \"tiles\""), "{e}");
    let at = write("at.toml", &format!("{base}[drr]\nroi_center = [1.0, 2.0, 3.0]\n[drr.tiles]\ncounts = [1, 1, 1]\n"));
    let e = format!("{:#}", Config::load(&at).unwrap_err());
    assert!(e.contains("[drr.tiles]") && e.contains("a position in mm"), "{e}");
    // A configuration that extends another and picks another variant drops what only the old
    // one read: the shipped [train.dense_tv] does not trouble a VM preset.
    let tensorf = Config::load(&root().join("presets/tensorf.toml")).unwrap();
    assert!(tensorf.train.model.is_vm());
    // A wrong type or an unknown key in an extended file names that file and line.
    let parent = write("parent.toml", &format!("{base}[hu]\nhu_maxx = 3\n"));
    let child = write("child.toml", "extends = \"parent.toml\"\n[pipeline]\nname = \"c\"\n");
    let e = format!("{:#}", Config::load(&child).unwrap_err());
    assert!(e.contains(&parent.display().to_string()) && e.contains("line 7") && e.contains("hu_maxx"), "{e}");
    let circle = write("circle.toml", "extends = \"circle.toml\"\n");
    assert!(format!("{:#}", Config::load(&circle).unwrap_err()).contains("circle"));
}

#[test]
fn the_lab_keeps_its_instruments_outside_the_product_presets() {
    let perfect = Config::load(Path::new(&root().join("lab/presets/perfect_field.toml"))).unwrap();
    assert_eq!(perfect.train.model.name(), "truth");
    assert!(!root().join("presets/perfect_field.toml").exists());
}
