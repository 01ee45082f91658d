//! Hostile dataset layouts through the command line and `dataset`: patient IDs that are not one
//! plain path component, names that are not UTF-8 or that collide, file names that could carry
//! a patient's name, and annotation files built to exhaust the parser. Each must be refused with
//! a message naming the file or folder — never write outside `out_dir`, drop a patient, copy a
//! name into an artifact, or bring down the run for the other patients.

mod support;

use aret_pipe::dataset::{narrow, patient_id, phantom_cohort};
use aret_pipe::engine::run::Unit;
use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::process::Output;
use support::dicom_writer::{default_name, series, write_series, write_slice, SliceSpec};

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");
const PAPER_COHORT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/cohorts/paper19");

fn aret(dir: &Path, args: &[&str]) -> Output {
    std::process::Command::new(BIN).args(args).current_dir(dir).env("CI", "true").output().unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A dataset of `kind` at `dir/<folder>`, results to `dir/work/out`, cache in `dir/work/cache`.
fn write_config(dir: &Path, kind: &str, folder: &str) {
    let key = if kind == "phantom" { "cohort" } else { "root" };
    let config = format!(
        "[pipeline]\nname = \"t\"\ncache_dir = \"work/cache\"\nout_dir = \"work/out\"\nworkers = 2\n\
         [dataset]\nkind = \"{kind}\"\n{key} = \"{folder}\"\n"
    );
    std::fs::write(dir.join("pipeline.toml"), config).unwrap();
}

fn write_patient(dir: &Path, folder: &OsStr) -> PathBuf {
    let series_dir = dir.join("data").join(folder).join("series");
    std::fs::create_dir_all(&series_dir).unwrap();
    write_series(&series_dir, &series(3), default_name);
    series_dir
}

/// Every file under `dir`, as paths relative to it.
fn files_under(dir: &Path) -> Vec<PathBuf> {
    walkdir::WalkDir::new(dir)
        .into_iter()
        .map(|e| e.unwrap())
        .filter(|e| e.file_type().is_file())
        .map(|e| e.path().strip_prefix(dir).unwrap().to_path_buf())
        .collect()
}

#[test]
fn names_that_are_not_one_plain_path_component_are_refused_naming_them() {
    let entry = Path::new("/data/cohort/entry");
    let refused: [(&[u8], &str); 13] = [
        (b"", "empty"),
        (b".", "names a folder itself"),
        (b"..", "would write outside out_dir"),
        (b".hidden", "hidden"),
        (b"-rf", "option"),
        (b" P1", "whitespace"),
        (b"P1\t", "whitespace"),
        (b"a/b", "path separator"),
        (b"a\\b", "path separator"),
        (b"a\0b", "control character"),
        (b"a\x1bb", "control character"),
        (b"p\xff", "not valid UTF-8"),
        (&[b'x'; 201], "more than 200"),
    ];
    for (name, why) in refused {
        let err = patient_id(OsStr::from_bytes(name), entry).unwrap_err().to_string();
        assert!(err.contains("/data/cohort/entry") && err.contains(why), "{name:?}: {err}");
    }
    for accepted in ["LIDC-IDRI-0001", "P 1", "patient.7", "Ünïcode_患者", "a-b_c"] {
        assert_eq!(patient_id(OsStr::new(accepted), entry).unwrap(), accepted);
    }
}

#[test]
fn ids_that_collide_exactly_or_but_for_case_are_refused() {
    let unit = |id: &str, dir: &str| Unit::folder(id, PathBuf::from(dir));
    let root = Path::new("/data");
    let err = narrow(vec![unit("P1", "/data/a"), unit("P2", "/data/c"), unit("P1", "/data/b")], None, root)
        .unwrap_err()
        .to_string();
    assert!(err.contains("`P1` (from /data/a)") && err.contains("`P1` (from /data/b)"), "{err}");
    let err = narrow(vec![unit("p1", "/data/x"), unit("P1", "/data/y")], None, root).unwrap_err().to_string();
    assert!(err.contains("but for letter case"), "{err}");
    assert_eq!(narrow(vec![unit("P2", "/d/2"), unit("P1", "/d/1")], None, root).unwrap().len(), 2);
}

#[test]
fn cohort_files_that_make_no_valid_id_are_refused_naming_the_file() {
    for stem in ["..", ".", "", "-x", ".hidden", "a\\b", "a\u{7}b", " p"] {
        let cohort = tempfile::tempdir().unwrap();
        std::fs::write(cohort.path().join(format!("{stem}.scan.json")), "{}").unwrap();
        std::fs::write(cohort.path().join(format!("{stem}.xml")), "<LidcReadMessage/>").unwrap();
        let err = phantom_cohort(cohort.path()).unwrap_err().to_string();
        assert!(err.contains(".scan.json") && err.contains("cannot be a patient ID"), "{stem:?}: {err}");
    }
    let cohort = tempfile::tempdir().unwrap();
    let name = [b"p\xfe".as_slice(), b".scan.json"].concat();
    std::fs::write(cohort.path().join(OsStr::from_bytes(&name)), "{}").unwrap();
    let err = phantom_cohort(cohort.path()).unwrap_err().to_string();
    assert!(err.contains("p\u{fffd}.scan.json") && err.contains("not valid UTF-8"), "{err}");
}

/// `...scan.json` + `...xml` once gave the ID `..`: `phantom --out D` wrote `D/../series/`,
/// and `run` wrote `ct_hu.raw` and more into the folder above `out_dir`.
#[test]
fn a_dot_dot_patient_writes_nothing_outside_the_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let cohort = dir.path().join("cohort");
    std::fs::create_dir_all(&cohort).unwrap();
    std::fs::create_dir_all(dir.path().join("work")).unwrap();
    for (from, to) in [("LIDC-IDRI-0001.scan.json", "...scan.json"), ("LIDC-IDRI-0001.xml", "...xml")] {
        std::fs::copy(Path::new(PAPER_COHORT).join(from), cohort.join(to)).unwrap();
    }
    let out = aret(dir.path(), &["phantom", "--cohort", "cohort", "--out", "work/out"]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("...scan.json") && err.contains("`..` cannot be a patient ID"), "{err}");

    write_config(dir.path(), "phantom", "cohort");
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("`..` cannot be a patient ID"), "{}", text(&out.stderr));
    assert_eq!(files_under(&dir.path().join("work")), Vec::<PathBuf>::new(), "nothing written at all");
}

/// `p\xff` and `p\xfe` once both became `p�`: one patient vanished and the run still exited 0.
#[test]
fn patient_folders_whose_names_are_not_utf8_are_refused_not_merged() {
    let dir = tempfile::tempdir().unwrap();
    for name in [b"p\xff".as_slice(), b"p\xfe", b"p3"] {
        write_patient(dir.path(), OsStr::from_bytes(name));
    }
    write_config(dir.path(), "dicom", "data");
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("data/p\u{fffd}") && err.contains("not valid UTF-8"), "{err}");
}

/// In the TCIA layout only `LIDC-IDRI-*` folders are patients: other names are passed over
/// whatever they are, a patient folder's name must still make a valid ID.
#[test]
fn lidc_roots_check_the_patient_folders_and_pass_over_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    write_patient(dir.path(), OsStr::new("LIDC-IDRI/LIDC-IDRI-0042"));
    std::fs::create_dir_all(dir.path().join("data/LIDC-IDRI/-old notes ")).unwrap();
    std::fs::create_dir_all(dir.path().join(OsStr::from_bytes(b"data/LIDC-IDRI/backup\xff"))).unwrap();
    write_config(dir.path(), "lidc", "data");
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(dir.path().join("work/out/LIDC-IDRI-0042/ct_hu.mhd").exists());

    write_patient(dir.path(), OsStr::new("LIDC-IDRI/LIDC-IDRI-0043\t"));
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("`LIDC-IDRI-0043\\t` cannot be a patient ID") && err.contains("whitespace"), "{err}");
}

#[test]
fn skipped_files_are_counted_in_ct_series_json_never_named() {
    let dir = tempfile::tempdir().unwrap();
    let series_dir = write_patient(dir.path(), OsStr::new("P1"));
    std::fs::write(series_dir.join("Jane Doe referral letter.txt"), "Referral for Jane Doe, born 1960\n").unwrap();
    std::fs::write(series_dir.join("DOE_JANE.pdf"), vec![b'%'; 400]).unwrap();
    let mut scout = SliceSpec::ct(9);
    scout.modality = "CR".into();
    scout.sop_class_uid = "1.2.840.10008.5.1.4.1.1.1".into();
    scout.series_uid = "1.2.3.4".into();
    write_slice(&series_dir.join("scout of Jane Doe.dcm"), &scout);
    write_config(dir.path(), "dicom", "data");
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let info: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("work/out/P1/ct_series.json")).unwrap()).unwrap();
    assert_eq!(info["skipped_files"], serde_json::json!({"not_dicom": 2, "dicom_not_ct": 1}));
    // The published results and every stored output. (The cache's own index of input files,
    // `sources/` and `latest/`, lists the patient's files by name to fingerprint them.)
    let published = files_under(&dir.path().join("work/out")).into_iter().map(|f| Path::new("out").join(f));
    let stored =
        files_under(&dir.path().join("work/cache/blobs")).into_iter().map(|f| Path::new("cache/blobs").join(f));
    let artifacts: Vec<PathBuf> = published.chain(stored).collect();
    assert!(artifacts.len() > 5, "{artifacts:?}");
    for file in artifacts {
        let body = std::fs::read(dir.path().join("work").join(&file)).unwrap();
        let body = String::from_utf8_lossy(&body).to_lowercase();
        assert!(!body.contains("doe") && !body.contains("referral"), "{} names a skipped file", file.display());
    }
}

/// An annotation file nested 5,000 deep once overflowed the parser's stack and aborted the
/// whole run; one over the size limit is refused unread. Each fails its own patient only.
#[test]
fn hostile_annotation_files_fail_their_patient_alone() {
    let dir = tempfile::tempdir().unwrap();
    write_patient(dir.path(), OsStr::new("P1"));
    let deep = write_patient(dir.path(), OsStr::new("P2"));
    let nesting = format!("<LidcReadMessage>{}{}</LidcReadMessage>", "<a>".repeat(5000), "</a>".repeat(5000));
    std::fs::write(deep.join("069.xml"), nesting).unwrap();
    let big = write_patient(dir.path(), OsStr::new("P3"));
    let padding = " ".repeat(17 << 20);
    std::fs::write(big.join("070.xml"), format!("<LidcReadMessage>{padding}</LidcReadMessage>")).unwrap();
    write_config(dir.path(), "dicom", "data");
    let out = aret(dir.path(), &["run", "pipeline.toml", "--until", "ingest"]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    let stdout = text(&out.stdout);
    assert!(stdout.contains("failed: P2 · ingest:") && stdout.contains("069.xml"), "{stdout}");
    assert!(stdout.contains("deeper than the limit of 64 levels"), "{stdout}");
    assert!(stdout.contains("failed: P3 · ingest:") && stdout.contains("070.xml"), "{stdout}");
    assert!(stdout.contains("exceeds the limit of 16777216 bytes"), "{stdout}");
    assert!(dir.path().join("work/out/P1/ct_hu.mhd").exists(), "P1 still ingested");
}
