//! The cache's checks through the command line, on a small CT series up to `hu`: `run --copy`
//! against the default read-only links, `gc` removing what killed runs left in the out dir, and
//! a run that has to wait for a gc (on another host) to finish.

mod support;

use std::path::Path;
use std::process::Output;
use std::time::Duration;
use support::dicom_writer::{default_name, series, write_series};
use support::leases::pretend_lease;
use support::toy_stages::ended_pid;

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");

/// One patient with a 3-slice series, and a configuration caching in `cache`, publishing in `out`.
fn project() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let series_dir = dir.path().join("data/P1/series");
    std::fs::create_dir_all(&series_dir).unwrap();
    write_series(&series_dir, &series(3), default_name);
    let config = "[pipeline]\nname = \"test\"\ncache_dir = \"cache\"\nout_dir = \"out\"\n\
                  [dataset]\nkind = \"dicom\"\nroot = \"data\"\n";
    std::fs::write(dir.path().join("pipeline.toml"), config).unwrap();
    dir
}

/// `aret-pipe ARGS` in `dir`, quiet as in CI; fails the test unless it succeeds.
fn aret(dir: &Path, args: &[&str]) -> (String, String) {
    let out: Output = std::process::Command::new(BIN).args(args).current_dir(dir).env("CI", "true").output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "aret-pipe {args:?} failed:\n{stdout}\n{stderr}");
    (stdout.into_owned(), stderr.into_owned())
}

fn run_until_hu(dir: &Path, extra: &[&str]) -> (String, String) {
    let mut args = vec!["run", "pipeline.toml", "--until", "hu"];
    args.extend_from_slice(extra);
    aret(dir, &args)
}

#[cfg(unix)]
fn mode_and_links(path: &Path) -> (u32, u64) {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    let meta = std::fs::metadata(path).unwrap();
    (meta.permissions().mode() & 0o777, meta.nlink())
}

#[cfg(unix)]
#[test]
fn run_publishes_read_only_links_and_with_copy_writable_copies() {
    let dir = project();
    run_until_hu(dir.path(), &[]);
    let published = dir.path().join("out/P1/ct_unit.raw");
    let (mode, links) = mode_and_links(&published);
    assert!(mode == 0o444 && links >= 2, "a read-only link into the cache: {mode:o}, {links} links");
    let (stdout, _) = run_until_hu(dir.path(), &["--copy"]);
    assert!(stdout.contains("0 computed"), "{stdout}");
    assert_eq!(mode_and_links(&published), (0o644, 1), "an independent, writable copy");
    run_until_hu(dir.path(), &[]);
    assert_eq!(mode_and_links(&published).0, 0o444, "links again");
}

#[test]
fn gc_and_a_run_remove_the_temporary_files_killed_runs_left_in_the_out_dir() {
    let dir = project();
    run_until_hu(dir.path(), &[]);
    let dead = ended_pid();
    // A kill while publishing: a hard link to a blob under a temporary name; and a lone file.
    let link = dir.path().join(format!("out/P1/.tmp-{}-{dead}-0-1", aret_pipe::engine::files::this_host()));
    std::fs::hard_link(dir.path().join("out/P1/ct_unit.raw"), &link).unwrap();
    let lone = dir.path().join(format!("out/.tmp-{dead}-1-1"));
    std::fs::write(&lone, vec![0u8; 3 << 20]).unwrap();

    let (stdout, _) = aret(dir.path(), &["gc", "pipeline.toml", "--dry-run"]);
    assert!(stdout.contains("would remove 2 stale .tmp-* file(s)"), "{stdout}");
    assert!(stdout.contains("freeing 3.0 MiB"), "{stdout}");
    assert!(link.exists() && lone.exists());
    let (stdout, _) = aret(dir.path(), &["gc", "pipeline.toml"]);
    assert!(stdout.contains("removed 2 stale .tmp-* file(s)") && stdout.contains("freeing 3.0 MiB"), "{stdout}");
    assert!(stdout.contains("more were links to blobs that stay"), "{stdout}");
    assert!(!link.exists() && !lone.exists());
    let (stdout, _) = run_until_hu(dir.path(), &[]);
    assert!(stdout.contains("0 computed"), "gc removed nothing a run needs: {stdout}");

    // A run removes them too: from the patient's folder it publishes into, and from out_dir
    // itself, where it writes run_report.json (a run up to hu publishes nothing else there).
    std::fs::hard_link(dir.path().join("out/P1/ct_unit.raw"), &link).unwrap();
    std::fs::write(&lone, "x").unwrap();
    let (stdout, stderr) = run_until_hu(dir.path(), &[]);
    assert!(!link.exists() && !lone.exists(), "{stdout}");
    assert_eq!(stderr.matches("removed 1 stale .tmp-* file(s)").count(), 2, "{stderr}");
}

#[test]
fn a_run_waiting_for_a_gc_says_so_and_its_time_includes_the_wait() {
    let dir = project();
    run_until_hu(dir.path(), &[]);
    // A gc on another host holds the cache, and deletes its lease when it ends.
    let gc = pretend_lease(&dir.path().join("cache"), "node_2", 4242, "aret-pipe gc", 60);
    let holder = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(1800));
        std::fs::remove_file(gc).unwrap();
    });
    let (stdout, stderr) = run_until_hu(dir.path(), &[]);
    holder.join().unwrap();
    let waiting: Vec<&str> = stderr.lines().filter(|l| l.contains("waiting for")).collect();
    assert_eq!(waiting.len(), 1, "{stderr}");
    assert!(waiting[0].contains("waiting for aret-pipe gc on node_2 (pid 4242), alive until"), "{stderr}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("out/run_report.json")).unwrap()).unwrap();
    let waited = report["gc_wait_seconds"].as_f64().unwrap();
    assert!(waited >= 1.0 && report["wall_seconds"].as_f64().unwrap() >= waited, "{report}");
    assert!(stdout.contains("s of it waiting for gc"), "{stdout}");
}
