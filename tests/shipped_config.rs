//! The shipped `pipeline.toml` and presets parse, and every key in them carries a comment.

use aret_pipe::config::Config;
use std::path::Path;

fn check_commented(path: &Path) {
    let text = std::fs::read_to_string(path).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    for (n, line) in lines.iter().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with('[') {
            continue;
        }
        let previous = lines[..n].iter().rev().map(|l| l.trim()).find(|l| !l.is_empty()).unwrap_or("");
        assert!(previous.starts_with('#'), "{}:{}: `{line}` has no comment above it", path.display(), n + 1);
    }
}

#[test]
fn shipped_pipeline_parses_and_documents_every_key() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("pipeline.toml");
    let config = Config::load(&path).unwrap();
    assert_eq!(config.pipeline.name, "default");
    check_commented(&path);
}

#[test]
fn presets_parse_and_document_every_key() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("presets");
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            Config::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
            check_commented(&path);
        }
    }
}
