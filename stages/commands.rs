//! The commands behind the CLI: run, status, gc (each loads the configuration, builds the stage
//! graph, and hands it to the engine), and the standalone presets, completions, phantom and
//! convert.

use crate::config::Config;
use crate::engine::files::write_atomic;
use crate::engine::lease::{self, Lease};
use crate::engine::leftovers;
use crate::engine::preview::{self, Row, State};
use crate::engine::progress::{self, Progress};
use crate::engine::remote::RemoteCache;
use crate::engine::run::{self, Publish, RunOptions, RunSummary, StopRequest, Unit};
use crate::engine::store::{Doomed, Store};
use crate::engine::{Hash, StageGraph};
use crate::formats::vdb::{self, FloatGrid, GridClass};
use crate::volume::Volume;
use crate::{dataset, pipeline};
use anyhow::{bail, Context as _};
use serde::Serialize;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

#[derive(Debug, Default, Clone)]
pub struct RunArgs {
    /// `section.key=value` over the configuration ([`Config::load_with`]).
    pub sets: Vec<String>,
    pub patients: Option<Vec<String>>,
    pub until: Option<String>,
    /// Stage names to recompute even when cached, or [`FORCE_ALL`] for every stage.
    pub force: Vec<String>,
    pub dry_run: bool,
    /// With `dry_run`: print the plan as JSON ([`plan_json`]) instead of the text lines.
    pub json: bool,
    pub verify: bool,
    /// Publish independent copies instead of read-only hard links into the cache.
    pub copy: bool,
    /// Only the per-patient stages of this shard's patients ([`crate::shard`]).
    pub shard: Option<crate::shard::Shard>,
    /// Only the cohort stages, once every patient's results are cached.
    pub gather: Option<Gather>,
}

/// `run --gather`: the cohort stages over what the shards cached.
#[derive(Debug, Default, Clone)]
pub struct Gather {
    /// How many shards computed the patients, so that a refusal names the shards to run again.
    pub shard_count: Option<u64>,
}

/// What `aret-pipe status` shows.
#[derive(Debug, Default, Clone)]
pub struct StatusArgs {
    /// `section.key=value` over the configuration ([`Config::load_with`]).
    pub sets: Vec<String>,
    pub patients: Option<Vec<String>>,
    pub verify: bool,
    /// Print the plan as JSON ([`plan_json`]) instead of the table.
    pub json: bool,
}

/// `--force all`: every stage of the graph.
pub const FORCE_ALL: &str = "all";

struct Prepared {
    config: Config,
    graph: StageGraph,
    units: Vec<Unit>,
    store: Store,
}

fn prepare(
    config_path: &Path,
    sets: &[String],
    patients: Option<&[String]>,
    until: Option<&str>,
) -> anyhow::Result<Prepared> {
    let config = Config::load_with(config_path, sets)?;
    let mut graph = pipeline::graph(&config)?;
    if let Some(last) = until {
        graph = graph.until(last)?;
    }
    let units = dataset::units(&config, patients)?;
    let mut store = Store::open(&config.cache_dir())?;
    if let Some(url) = config.cache_remote() {
        store = store.with_remote(open_remote(url, config_path)?);
    }
    Ok(Prepared { config, graph, units, store })
}

/// Prints the remote cache's warnings (a run prints its own as it goes).
fn say_remote_notices(store: &Store) {
    for line in store.remote().map(|r| r.take_notices()).unwrap_or_default() {
        eprintln!("aret-pipe: {line}");
    }
}

/// The remote cache at `url`, checked reachable (see [`RemoteCache::probe`] for why a run stops
/// when it is not).
fn open_remote(url: &str, config_path: &Path) -> anyhow::Result<std::sync::Arc<RemoteCache>> {
    let remote = RemoteCache::open(url)?;
    remote.probe().with_context(|| {
        format!(
            "[pipeline] cache_remote of {}: check the URL and the AWS_* / GOOGLE_* / AZURE_* variables, \
             or run without it (--set pipeline.cache_remote='')",
            config_path.display()
        )
    })?;
    Ok(std::sync::Arc::new(remote))
}

/// `run --gather`: an error listing the patients whose per-patient results are not all cached,
/// with the command that computes them, so the cohort stages never compute them themselves.
fn refuse_missing_patients(config_path: &Path, p: &Prepared, args: &RunArgs) -> anyhow::Result<()> {
    let per_patient: Vec<&str> = p.graph.per_patient().iter().map(|s| s.name()).collect();
    let rows = preview::preview(&p.graph, &p.store, &p.units, args.verify, &[]);
    let mut missing: Vec<&str> = rows
        .iter()
        .filter(|r| per_patient.contains(&r.stage.as_str()) && !matches!(r.state, State::Cached { .. }))
        .map(|r| r.unit.split('/').next().unwrap_or(&r.unit))
        .collect();
    missing.sort_unstable();
    missing.dedup();
    if !missing.is_empty() {
        let shards = match args.gather.as_ref().and_then(|g| g.shard_count) {
            Some(n) => {
                let mut shards: Vec<u64> = missing.iter().map(|id| crate::shard::shard_of(id, n)).collect();
                shards.sort_unstable();
                shards.dedup();
                let list: Vec<String> = shards.iter().map(u64::to_string).collect();
                format!(
                    "their shards of {n}: {} (a Slurm array: `sbatch --array={} {}/{}`), or ",
                    list.join(", "),
                    list.join(","),
                    crate::submit::SUBMIT_DIR,
                    crate::submit::SLURM_SHARDS_SCRIPT
                )
            }
            None => "their shards, or ".into(),
        };
        bail!(
            "--gather: {} of {} patients are not computed yet: {}. Compute them first ({shards}\
             `aret-pipe run {} --patients {} --until {}`), then gather again",
            missing.len(),
            p.units.len(),
            missing.join(", "),
            config_path.display(),
            missing.join(","),
            per_patient.last().copied().unwrap_or("select"),
        );
    }
    Ok(())
}

/// `aret-pipe run`. Returns the process exit code: 0 when every stage of every patient succeeded.
pub fn run(config_path: &Path, args: &RunArgs) -> anyhow::Result<i32> {
    let stop = StopRequest::default();
    stop_on_signals(&stop);
    if args.json && !args.dry_run {
        bail!(
            "--json goes with --dry-run: a run prints its progress and end table, and records every \
             outcome in out_dir/run_report.json"
        );
    }
    let mut p = prepare(config_path, &args.sets, args.patients.as_deref(), args.until.as_deref())?;
    crate::resources::check_memory(&p.config)?;
    if let Some(shard) = args.shard {
        p.units.retain(|u| shard.holds(&u.id));
        p.graph = p.graph.without_cohort();
    }
    let force = forced_stages(&p.graph, &args.force)?;
    // Held until run_report.json is written: its temporary file is this process's too.
    let _alive = Lease::take(p.store.root(), "aret-pipe run")?;
    let mut waited_for = Vec::new();
    let cache_wait = lease::wait_while_gc(p.store.root(), &mut |line| {
        eprintln!("aret-pipe: {line}");
        waited_for.push(line);
    });
    if args.gather.is_some() {
        if !args.verify {
            p.store.check_sizes_only();
        }
        refuse_missing_patients(config_path, &p, args)?;
    }
    if args.dry_run {
        let rows = preview::preview(&p.graph, &p.store, &p.units, args.verify, &force);
        say_remote_notices(&p.store);
        if args.json {
            print!("{}", plan_json("dry-run", config_path, &p.graph, &rows)?);
        } else {
            print!("{}", preview::describe(&rows));
        }
        return Ok(0);
    }
    let options = RunOptions {
        verify: args.verify,
        force,
        workers: p.config.pipeline.stage_workers.clone().into_iter().collect(),
        default_workers: p.config.pipeline.workers,
        out_dir: p.config.out_dir(),
        publish: if args.copy { Publish::Copies } else { Publish::Links },
        stop,
    };
    let progress = Progress::auto(&p.graph.runs_per_stage(p.units.len()));
    let mut summary = run::run(&p.graph, &p.store, &p.units, &options, &progress);
    drop(progress);
    summary.wall_seconds += cache_wait.as_secs_f64();
    summary.gc_wait_seconds = cache_wait.as_secs_f64();
    summary.notices.splice(0..0, waited_for);
    write_report(&p.store, &options.out_dir, &mut summary)?;
    print!("{}", progress::table(&summary, &p.graph.names()));
    let metrics_done = summary.records.iter().any(|r| {
        r.stage == crate::artifacts::SUMMARY.stage
            && matches!(
                r.outcome,
                run::Outcome::Cached { .. } | run::Outcome::Fetched { .. } | run::Outcome::Computed { .. }
            )
    });
    if metrics_done {
        if let Ok(json) = std::fs::read(options.out_dir.join(crate::artifacts::SUMMARY.file)) {
            print!("{}", crate::stage::metrics::summary::headline(&json)?);
        }
    }
    Ok(if summary.failures().next().is_some() {
        1
    } else if summary.interrupted() {
        INTERRUPTED_EXIT
    } else {
        0
    })
}

/// The cache's `gc` lease, once no other process holds a live lease on it (on any host):
/// otherwise an error naming each holder.
fn take_gc_lease(store: &Store) -> anyhow::Result<Lease> {
    let root = store.root();
    let lease = match Lease::take_gc(root, "aret-pipe gc")? {
        Ok(lease) => lease,
        Err(other) => {
            bail!("{} is collecting garbage in the cache {} now; let it finish", other.describe(), root.display())
        }
    };
    let others: Vec<String> = lease::live_leases(root)?
        .into_iter()
        .filter(|(path, _)| path != lease.path())
        .map(|(_, record)| record.describe())
        .collect();
    if !others.is_empty() {
        bail!(
            "the cache {} is in use by {}; run gc when they have finished (a killed process's lease \
             ends within {} s)",
            root.display(),
            others.join("; "),
            lease::LEASE_TTL.as_secs()
        );
    }
    Ok(lease)
}

/// The stages `--force` names, checked against the graph: each a stage's name, or [`FORCE_ALL`]
/// for all of them (after `--until`'s cut).
fn forced_stages(graph: &StageGraph, force: &[String]) -> anyhow::Result<Vec<String>> {
    let names = graph.names();
    if let Some(unknown) = force.iter().find(|f| *f != FORCE_ALL && !names.contains(&f.as_str())) {
        bail!("--force {unknown}: no such stage in this run (stages: {}; or `{FORCE_ALL}`)", names.join(", "));
    }
    if force.iter().any(|f| f == FORCE_ALL) {
        return Ok(names.iter().map(|n| n.to_string()).collect());
    }
    Ok(force.to_vec())
}

/// The exit status of a run stopped by a signal (128 + SIGINT, the shells' convention).
const INTERRUPTED_EXIT: i32 = 130;

/// Ctrl-C, SIGTERM (`timeout`, a batch scheduler's time limit) or SIGHUP asks the run to stop:
/// the stages in progress finish and are cached, so the end table and `run_report.json` say
/// what was done. A second signal, a second or more after the first, quits at once (`timeout`
/// signals the process and then its group, so one request can arrive twice); the cache stays
/// consistent either way (every write is atomic).
fn stop_on_signals(stop: &StopRequest) {
    let stop = stop.clone();
    let mut first: Option<std::time::Instant> = None;
    let installed = ctrlc::set_handler(move || match first {
        Some(at) if at.elapsed().as_secs_f64() >= 1.0 => {
            eprintln!("aret-pipe: quitting at once");
            std::process::exit(INTERRUPTED_EXIT);
        }
        Some(_) => {}
        None => {
            first = Some(std::time::Instant::now());
            stop.request();
            eprintln!(
                "aret-pipe: stopping: the stages in progress finish and are cached, no other starts \
                 (signal again to quit at once)"
            );
        }
    });
    if let Err(e) = installed {
        eprintln!("aret-pipe: warning: a signal will end the run abruptly ({e})");
    }
}

/// Writes `out_dir/run_report.json`: every (patient, stage) outcome with its time. Stale
/// `.tmp-*` files of out_dir itself go first (a run without cohort stages publishes nothing
/// else there), and the line saying so joins the report.
fn write_report(store: &Store, out_dir: &Path, summary: &mut RunSummary) -> anyhow::Result<()> {
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let removed = leftovers::remove_stale_temps(store, out_dir)?;
    if !removed.is_empty() {
        let line = leftovers::describe(&removed, "removed", &out_dir.display().to_string());
        eprintln!("aret-pipe: {line}");
        summary.notices.push(line);
    }
    write_atomic(&out_dir.join("run_report.json"), &serde_json::to_vec_pretty(summary)?, false)
}

/// `aret-pipe status`: a table of what is cached and what is stale, and why; or, with `json`,
/// the same as one JSON document ([`plan_json`]).
pub fn status(config_path: &Path, args: &StatusArgs) -> anyhow::Result<String> {
    let p = prepare(config_path, &args.sets, args.patients.as_deref(), None)?;
    lease::wait_while_gc(p.store.root(), &mut |line| eprintln!("aret-pipe: {line}"));
    let rows = preview::preview(&p.graph, &p.store, &p.units, args.verify, &[]);
    say_remote_notices(&p.store);
    if args.json {
        return plan_json("status", config_path, &p.graph, &rows);
    }
    let mut cells = Vec::new();
    let mut notes = String::new();
    for r in &rows {
        let (cell, why) = status_cell(&r.state);
        if let Some(why) = why {
            notes.push_str(&format!("{} · {}: {why}\n", r.unit, r.stage));
        }
        cells.push((r.unit.clone(), r.stage.clone(), cell.to_string()));
    }
    Ok(format!("{}{notes}", progress::grid(&cells, &p.graph.names())))
}

/// The status table's cell for a (unit, stage), and the note that says why, if any.
fn status_cell(state: &State) -> (&'static str, Option<String>) {
    match state {
        State::Cached { .. } => ("cached", None),
        State::Compute(reasons) if reasons == &["never run"] => ("new", None),
        State::Compute(reasons) => ("stale", Some(reasons.join("; "))),
        State::AfterUpstream { own, .. } if own == &["never run"] => ("new", None),
        State::AfterUpstream { upstream, own } if own.is_empty() => ("pending", Some(format!("after `{upstream}`"))),
        State::AfterUpstream { own, .. } => ("stale", Some(own.join("; "))),
        State::Blocked(why) => ("blocked", Some(why.clone())),
    }
}

/// The plan of `status --json` and `run --dry-run --json`. The field names are the CLI's
/// contract, documented on `--json` in main.rs: rename none without changing that text.
#[derive(Serialize)]
struct PlanDocument<'a> {
    command: &'a str,
    config: String,
    stages: Vec<&'static str>,
    rows: Vec<PlanRow<'a>>,
}

/// One (unit, stage) of a [`PlanDocument`].
#[derive(Serialize)]
struct PlanRow<'a> {
    unit: &'a str,
    stage: &'a str,
    status: &'static str,
    cached: bool,
    would_run: bool,
    after: Option<&'a str>,
    reasons: Vec<&'a str>,
    key: Option<String>,
}

/// The preview `rows` as one pretty-printed JSON document (and a newline): `command` is
/// `status` or `dry-run`. The status table and the dry run's lines say the same in words.
pub fn plan_json(command: &str, config_path: &Path, graph: &StageGraph, rows: &[Row]) -> anyhow::Result<String> {
    let rows = rows
        .iter()
        .map(|r| {
            let (would_run, after, reasons): (bool, Option<&str>, Vec<&str>) = match &r.state {
                State::Cached { .. } => (false, None, vec![]),
                State::Compute(reasons) => (true, None, reasons.iter().map(String::as_str).collect()),
                State::AfterUpstream { upstream, own } => {
                    (!own.is_empty(), Some(upstream.as_str()), own.iter().map(String::as_str).collect())
                }
                State::Blocked(why) => (false, None, vec![why.as_str()]),
            };
            PlanRow {
                unit: &r.unit,
                stage: &r.stage,
                status: status_cell(&r.state).0,
                cached: matches!(r.state, State::Cached { .. }),
                would_run,
                after,
                reasons,
                key: r.key.map(|k| k.hex()),
            }
        })
        .collect();
    let document = PlanDocument { command, config: config_path.display().to_string(), stages: graph.names(), rows };
    Ok(serde_json::to_string_pretty(&document)? + "\n")
}

/// What `aret-pipe gc` forgets besides what no manifest references.
#[derive(Debug, Default, Clone)]
pub struct GcArgs {
    /// `section.key=value` over every configuration ([`Config::load_with`]).
    pub sets: Vec<String>,
    /// Keep only the results the configurations use now.
    pub prune: bool,
    /// Forget every result of these stages (cheap to compute again; early cutoff then serves
    /// what follows them from the cache).
    pub forget: Vec<String>,
    /// Report; delete nothing.
    pub dry_run: bool,
}

/// `aret-pipe gc`: deletes blobs no manifest references, and the `.tmp-*` files killed runs left
/// in the configurations' out dirs; with `prune`, first forgets every stage result that none of
/// `config_paths` uses now (all must share one cache), and every result of the stages in
/// `forget`. With `dry_run` it only reports what it would delete. Returns a one-line report.
/// It cleans the local cache only, never `cache_remote`.
pub fn gc(config_paths: &[PathBuf], args: &GcArgs) -> anyhow::Result<String> {
    let GcArgs { ref sets, prune, ref forget, dry_run } = *args;
    let Some(first) = config_paths.first() else { bail!("gc needs a configuration file") };
    if config_paths.len() > 1 && !prune {
        bail!("gc reads only the cache of its configuration; more than one matters only with --prune");
    }
    let config = Config::load_with(first, sets)?;
    let stages = pipeline::graph(&config)?.names();
    if let Some(unknown) = forget.iter().find(|f| !stages.contains(&f.as_str())) {
        bail!("--forget {unknown}: no such stage in {} (stages: {})", first.display(), stages.join(", "));
    }
    let cache_dir = config.cache_dir();
    let store = Store::open(&cache_dir)?;
    // A dry run deletes nothing, so it may run beside a run; a real one must not, on any host.
    let _gc_lease = if dry_run { None } else { Some(take_gc_lease(&store)?) };
    let keep = if prune { Some(results_in_use(config_paths, sets, &cache_dir)?) } else { None };
    let mut out_dirs = vec![config.out_dir()];
    for path in config_paths.iter().skip(1) {
        let out_dir = Config::load_with(path, sets)?.out_dir();
        if !out_dirs.iter().any(|d| same_dir(d, &out_dir)) {
            out_dirs.push(out_dir);
        }
    }
    // out_dir/<patient>/<replica>/ is the deepest folder a run publishes into.
    let mut temps: Vec<Doomed> = Vec::new();
    for dir in out_dirs.iter().filter(|d| d.is_dir()) {
        temps.extend(leftovers::stale_temps(&store, dir, 3)?);
    }
    let garbage = store.garbage(keep.as_ref(), forget)?;
    let ended_leases = lease::ended_leases(store.root())?;
    if !dry_run {
        garbage.delete()?;
        leftovers::delete(&temps)?;
        lease::remove(&ended_leases)?;
    }
    let mib = |bytes: u64| bytes as f64 / (1024.0 * 1024.0);
    let (freed, linked) = garbage.bytes();
    let (verb, forgot, deleted, frees) = if dry_run {
        ("gc --dry-run: would", "forget", "delete", "freeing")
    } else {
        ("gc:", "forgot", "deleted", "freed")
    };
    // Why results were forgotten: not in use, of a forgotten stage, or both.
    let mut why = Vec::new();
    match config_paths {
        _ if !prune => {}
        [one] => why.push(format!("not used now by {}", one.display())),
        many => why.push(format!("not used now by the {} configurations given", many.len())),
    }
    if !forget.is_empty() {
        why.push(format!("of {}", forget.join(", ")));
    }
    let mut line = if why.is_empty() {
        format!("{verb} {deleted} {} unreferenced file(s)", garbage.files.len())
    } else {
        format!(
            "{verb} {forgot} {} stage result(s) {}; {deleted} {} file(s) no kept result references",
            garbage.manifests.len(),
            why.join(" or "),
            garbage.files.len()
        )
    };
    line.push_str(&format!(", {frees} {:.1} MiB in {}", mib(freed), store.root().display()));
    if linked > 0 {
        line.push_str(&format!(" ({:.1} MiB more stays on disk until the out dirs linking it go)", mib(linked)));
    }
    if !temps.is_empty() {
        let dirs: Vec<String> = out_dirs.iter().map(|d| d.display().to_string()).collect();
        let verb = if dry_run { "would remove" } else { "removed" };
        line.push_str(&format!("; {}", leftovers::describe(&temps, verb, &dirs.join(", "))));
    }
    Ok(line)
}

/// The (stage, key) of every result the configurations at `config_paths` would take from the
/// cache now: what `gc --prune` keeps. Refuses a configuration with another cache.
fn results_in_use(
    config_paths: &[PathBuf],
    sets: &[String],
    cache_dir: &Path,
) -> anyhow::Result<HashSet<(String, Hash)>> {
    let mut keep = HashSet::new();
    for path in config_paths {
        let p = prepare(path, sets, None, None)?;
        if !same_dir(&p.config.cache_dir(), cache_dir) {
            bail!(
                "{} uses the cache {}, not {} like {}: prune one cache at a time",
                path.display(),
                p.config.cache_dir().display(),
                cache_dir.display(),
                config_paths[0].display()
            );
        }
        for row in preview::preview(&p.graph, &p.store, &p.units, false, &[]) {
            if let State::Cached { key } = row.state {
                keep.insert((row.stage, key));
            }
        }
    }
    Ok(keep)
}

/// Whether two paths name one directory (`presets/../cache` and `cache` do).
fn same_dir(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// `aret-pipe presets`: one line per product preset (`*.toml`) in `dir`, sorted by name: its name
/// (the file name without `.toml`), then its description, the text of the file's first line,
/// which should be a `# …` comment. A preset without one is listed with a note that says so.
pub fn presets(dir: &Path) -> anyhow::Result<String> {
    if !dir.is_dir() {
        bail!("{}: no such presets directory", dir.display());
    }
    let mut presets = Vec::new();
    for entry in std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))? {
        let path = entry.with_context(|| format!("reading {}", dir.display()))?.path();
        if path.extension().is_some_and(|e| e == "toml") && path.is_file() {
            let name = path.file_stem().unwrap_or_default().to_string_lossy().into_owned();
            let text = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            presets.push((name, preset_description(&String::from_utf8_lossy(&text))));
        }
    }
    if presets.is_empty() {
        bail!("{}: no presets in it (no *.toml file)", dir.display());
    }
    presets.sort();
    let width = presets.iter().map(|(name, _)| name.chars().count()).max().unwrap_or(0);
    let mut out = String::new();
    for (name, description) in &presets {
        let description =
            description.as_deref().unwrap_or("(no description: its first line should be a `# ...` comment)");
        out.push_str(&format!("{name:<width$}  {description}\n"));
    }
    Ok(out)
}

/// A preset's one-line description: its first line's text when that line is a `# …` comment.
fn preset_description(text: &str) -> Option<String> {
    let first = text.trim_start_matches('\u{feff}').lines().next()?;
    let comment = first.trim_end().strip_prefix('#')?.trim();
    (!comment.is_empty()).then(|| comment.to_string())
}

/// `aret-pipe completions`: the completion script of `cli` (the whole command line) for `shell`.
pub fn completions(shell: clap_complete::Shell, cli: &mut clap::Command) -> Vec<u8> {
    let name = cli.get_name().to_string();
    let mut script = Vec::new();
    clap_complete::generate(shell, cli, name, &mut script);
    script
}

/// `aret-pipe phantom`: writes each cohort patient's synthetic CT series, its LIDC XML and PNG
/// previews to `out/<patient>/`. Returns one line per patient with its generation time.
pub fn phantom(
    cohort: &Path,
    out: &Path,
    patients: Option<&[String]>,
    params: &crate::phantom::PhantomParams,
) -> anyhow::Result<String> {
    let units = dataset::phantom_cohort(cohort)?;
    let units = dataset::narrow(units, patients, cohort)?;
    let mut report = String::new();
    for unit in &units {
        let started = std::time::Instant::now();
        let files = unit.source_files.as_ref().expect("cohort units list their files");
        let (scan, xml) = (unit.source_dir.join(&files[0]), unit.source_dir.join(&files[1]));
        let generated = crate::phantom::patient::generate_from_files(&scan, &xml, params)?;
        let seconds = started.elapsed().as_secs_f64();
        let dir = out.join(&unit.id);
        let series_dir = dir.join("series");
        std::fs::create_dir_all(&series_dir).with_context(|| format!("creating {}", series_dir.display()))?;
        for (name, bytes) in &generated.series {
            write_atomic(&series_dir.join(name), bytes, false)?;
        }
        write_atomic(&dir.join(&generated.annotations.0), generated.annotations.1.as_bytes(), false)?;
        for (name, bytes) in &generated.previews {
            write_atomic(&dir.join(name), bytes, false)?;
        }
        let dims = generated.ct.geometry.dims;
        report.push_str(&format!(
            "{}: {}×{}×{} generated in {seconds:.2} s → {}\n",
            unit.id,
            dims[0],
            dims[1],
            dims[2],
            dir.display()
        ));
    }
    Ok(report)
}

/// The cohort and generator parameters of `config_path`'s phantom dataset: what `run` ingests.
pub fn phantom_source(config_path: &Path) -> anyhow::Result<(PathBuf, crate::phantom::PhantomParams)> {
    let config = Config::load(config_path)?;
    if config.dataset.kind != crate::config::DatasetKind::Phantom {
        bail!(
            "{}: [dataset] kind is not \"phantom\": only a phantom dataset is generated (its CT series is \
             already on disk under [dataset] root)",
            config_path.display()
        );
    }
    Ok((config.dataset_root(), config.dataset.phantom.clone().unwrap_or_default()))
}

/// `aret-pipe convert`: MetaImage volumes (`.mhd` + their raw data; uchar, short or float) to
/// one OpenVDB file, one float grid per input, in patient millimetres. Zero voxels become
/// inactive background. `grids` and `classes` pair with `inputs` in order (each given once per
/// input, or not at all: names default to the file stems, classes to unknown). Returns one
/// line per grid.
pub fn convert(inputs: &[PathBuf], grids: &[String], classes: &[GridClass], output: &Path) -> anyhow::Result<String> {
    for (flag, n) in [("--grid", grids.len()), ("--class", classes.len())] {
        if n != 0 && n != inputs.len() {
            bail!(
                "{flag} is given {n} time(s) for {} input(s); give it once per input, in order, or not at all",
                inputs.len()
            );
        }
    }
    let volumes = inputs.iter().map(|p| read_metaimage_f32(p)).collect::<anyhow::Result<Vec<_>>>()?;
    let names: Vec<String> = match grids {
        [] => inputs.iter().map(|p| p.file_stem().unwrap_or_default().to_string_lossy().into_owned()).collect(),
        _ => grids.to_vec(),
    };
    let float_grids: Vec<FloatGrid> = volumes
        .iter()
        .zip(&names)
        .enumerate()
        .map(|(n, (v, name))| FloatGrid {
            name,
            dims: v.geometry.dims,
            values: &v.data,
            voxel_size_mm: v.geometry.spacing_mm,
            origin_mm: v.geometry.origin_mm,
            class: classes.get(n).copied().unwrap_or(GridClass::Unknown),
        })
        .collect();
    let bytes = vdb::encode(&float_grids)?;
    write_atomic(output, &bytes, false)?;
    let mut report = String::new();
    for g in &float_grids {
        let active = g.values.iter().filter(|v| **v != 0.0).count();
        let [nx, ny, nz] = g.dims;
        report.push_str(&format!("{}: {nx}×{ny}×{nz}, {active} active voxel(s)\n", g.name));
    }
    report.push_str(&format!("→ {} ({} bytes)\n", output.display(), bytes.len()));
    Ok(report)
}

/// A MetaImage volume as float32, refusing what a VDB ScaleTranslateMap cannot place.
fn read_metaimage_f32(input: &Path) -> anyhow::Result<Volume<f32>> {
    use crate::formats::mhd;
    let header = std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?;
    let field = |key: &'static str| {
        mhd::header_field(&header, key).ok_or_else(|| anyhow::anyhow!("{}: header has no `{key}`", input.display()))
    };
    let data_file = field("ElementDataFile")?;
    if ["LOCAL", "LIST"].iter().any(|k| data_file.eq_ignore_ascii_case(k)) || data_file.contains('%') {
        bail!(
            "{}: ElementDataFile = {data_file} is not supported; give the data as one separate raw file",
            input.display()
        );
    }
    let raw_path = input.parent().unwrap_or(Path::new("")).join(data_file);
    let raw = std::fs::read(&raw_path).with_context(|| format!("reading {}", raw_path.display()))?;
    let context = || format!("decoding {}", input.display());
    let volume: Volume<f32> = match field("ElementType")? {
        "MET_FLOAT" => mhd::decode::<f32>(&header, &raw).with_context(context)?,
        "MET_SHORT" => mhd::decode::<i16>(&header, &raw).with_context(context)?.map(f32::from),
        "MET_UCHAR" => mhd::decode::<u8>(&header, &raw).with_context(context)?.map(f32::from),
        other => {
            bail!("{}: ElementType {other} is not supported (MET_FLOAT, MET_SHORT, MET_UCHAR are)", input.display())
        }
    };
    // OpenVDB's ScaleTranslateMap scales and shifts the index axes but cannot rotate them.
    let d = &volume.geometry.direction;
    let identity = d.iter().enumerate().all(|(a, row)| (0..3).all(|c| (row[c] - f64::from(a == c)).abs() < 1e-6));
    if !identity {
        bail!(
            "{}: TransformMatrix {d:?} is not the identity; the VDB transform (scale and translate) cannot rotate",
            input.display()
        );
    }
    Ok(volume)
}
