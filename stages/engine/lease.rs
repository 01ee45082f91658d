//! Leases: how `aret-pipe` processes on many hosts that share one cache folder (over NFS, say)
//! tell each other that they are alive, without relying on `flock` across hosts.
//!
//! ```text
//! cache/leases/<host>-<pid>-<n>.json   a run: host, pid, what it is, until when it is alive
//! cache/leases/gc.json                 the one `gc` deleting from the cache
//! ```
//! A process holding a lease rewrites it every [`RENEW_EVERY`] with an expiry [`LEASE_TTL`]
//! ahead, and deletes it when it ends. A lease is live while its expiry is ahead of the
//! reader's clock and, when it names the reader's own host, its process still exists: a
//! process killed on this host is seen gone at once, one killed elsewhere once its lease
//! expires. `gc` takes `gc.json` (created exclusively, so two never delete at once) and
//! refuses while any other lease is live; a run waits while `gc.json` is live. Temporary files
//! carry their writer's host and pid ([`Owner`]), and are stale once no live lease names it.
//!
//! Hosts' clocks must agree to well within [`LEASE_TTL`]. A directory's listing on NFS may be
//! cached for up to the mount's `acdirmax`; see `docs/cluster.md` for when to run `gc`.

use super::files::{remove_if_present, this_host, write_atomic, Owner};
use super::lock::SAY_AFTER;
use anyhow::Context as _;
use crossbeam_channel::{bounded, Sender};
use serde::{Deserialize, Serialize};
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// How far ahead of its last renewal a lease expires.
pub const LEASE_TTL: Duration = Duration::from_secs(120);

/// How often a holder renews its lease.
pub const RENEW_EVERY: Duration = Duration::from_secs(30);

/// How often a run waiting for `gc` looks again.
const RETRY_EVERY: Duration = Duration::from_millis(100);

/// The file name of the lease `gc` holds.
pub const GC_LEASE: &str = "gc.json";

/// What a lease file holds.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LeaseRecord {
    pub host: String,
    pub pid: u32,
    /// What the process is doing: `aret-pipe run`, `aret-pipe gc`, ….
    pub holder: String,
    pub started_unix: u64,
    pub expires_unix: u64,
}

impl LeaseRecord {
    /// Whether it still marks a live process, seen from this host at `now_unix`.
    pub fn is_live(&self, now_unix: u64) -> bool {
        self.expires_unix > now_unix && (self.host != this_host() || process_exists(self.pid))
    }

    /// "aret-pipe run on node-3 (pid 4242), alive until 12:03:40 UTC".
    pub fn describe(&self) -> String {
        let t = self.expires_unix % 86_400;
        format!(
            "{} on {} (pid {}), alive until {:02}:{:02}:{:02} UTC unless renewed",
            self.holder,
            self.host,
            self.pid,
            t / 3600,
            t / 60 % 60,
            t % 60
        )
    }

    fn owner(&self) -> Owner {
        Owner { host: self.host.clone(), pid: self.pid }
    }
}

/// A held lease, renewed from a thread of its own and deleted on drop.
pub struct Lease {
    path: PathBuf,
    stop: Option<Sender<()>>,
    renewer: Option<JoinHandle<()>>,
}

static LEASE_COUNTER: AtomicU64 = AtomicU64::new(0);

impl Lease {
    /// Takes a lease for this process in the cache at `root`, as `holder` (e.g. `aret-pipe run`).
    pub fn take(root: &Path, holder: &str) -> anyhow::Result<Lease> {
        let me = Owner::me();
        let n = LEASE_COUNTER.fetch_add(1, Ordering::Relaxed);
        let path = leases_dir(root).join(format!("{}-{}-{n}.json", me.host, me.pid));
        let record = record(holder, unix_now());
        write_atomic(&path, &serde_json::to_vec_pretty(&record)?, false)?;
        Ok(Lease::renewed(path, record))
    }

    /// Takes the cache's `gc` lease, or returns the live one another process holds. A lease
    /// that is no longer live is replaced.
    pub fn take_gc(root: &Path, holder: &str) -> anyhow::Result<Result<Lease, LeaseRecord>> {
        let path = leases_dir(root).join(GC_LEASE);
        fs::create_dir_all(leases_dir(root))?;
        let record = record(holder, unix_now());
        let bytes = serde_json::to_vec_pretty(&record)?;
        for _ in 0..2 {
            match fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut file) => {
                    std::io::Write::write_all(&mut file, &bytes)
                        .and_then(|()| file.sync_all())
                        .with_context(|| format!("writing {}", path.display()))?;
                    return Ok(Ok(Lease::renewed(path, record)));
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    match read_record(&path) {
                        Some(other) if other.is_live(unix_now()) => return Ok(Err(other)),
                        // Ended or unreadable: a killed gc's; clear it and try once more.
                        _ => remove_if_present(&path)?,
                    }
                }
                Err(e) => return Err(e).with_context(|| format!("creating {}", path.display())),
            }
        }
        anyhow::bail!("{} keeps reappearing: another gc is starting at the same moment; try again", path.display())
    }

    fn renewed(path: PathBuf, mut record: LeaseRecord) -> Lease {
        let (stop, stopped) = bounded::<()>(1);
        let renew_path = path.clone();
        let renewer = std::thread::spawn(move || {
            while let Err(crossbeam_channel::RecvTimeoutError::Timeout) = stopped.recv_timeout(RENEW_EVERY) {
                record.expires_unix = unix_now() + LEASE_TTL.as_secs();
                if let Ok(bytes) = serde_json::to_vec_pretty(&record) {
                    // Best effort: a missed renewal only shortens the lease.
                    let _ = write_atomic(&renew_path, &bytes, false);
                }
            }
        });
        Lease { path, stop: Some(stop), renewer: Some(renewer) }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(renewer) = self.renewer.take() {
            let _ = renewer.join();
        }
        let _ = fs::remove_file(&self.path);
    }
}

/// The live leases in the cache at `root`, each with its file.
pub fn live_leases(root: &Path) -> anyhow::Result<Vec<(PathBuf, LeaseRecord)>> {
    let now = unix_now();
    Ok(all_leases(root)?
        .into_iter()
        .filter(|(_, r)| r.as_ref().is_some_and(|r| r.is_live(now)))
        .map(|(p, r)| (p, r.expect("filtered on Some")))
        .collect())
}

/// Every lease file in the cache at `root`, with its record when it parses (a lease being
/// rewritten at the moment of reading never shows half-written: renewals rename into place).
pub fn all_leases(root: &Path) -> anyhow::Result<Vec<(PathBuf, Option<LeaseRecord>)>> {
    let dir = leases_dir(root);
    let entries = match fs::read_dir(&dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(vec![]),
        Err(e) => return Err(e).with_context(|| format!("listing {}", dir.display())),
    };
    let mut leases = Vec::new();
    for entry in entries {
        let path = entry.with_context(|| format!("listing {}", dir.display()))?.path();
        let is_lease = path.extension().is_some_and(|e| e == "json")
            && !path.file_name().is_some_and(|n| n.to_string_lossy().starts_with(".tmp-"));
        if is_lease {
            let record = read_record(&path);
            leases.push((path, record));
        }
    }
    leases.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(leases)
}

/// The lease files in the cache at `root` that mark no live process: ended, or unreadable.
pub fn ended_leases(root: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let now = unix_now();
    Ok(all_leases(root)?
        .into_iter()
        .filter(|(_, r)| !r.as_ref().is_some_and(|r| r.is_live(now)))
        .map(|(p, _)| p)
        .collect())
}

/// Deletes the lease files `paths` (one already gone is no error).
pub fn remove(paths: &[PathBuf]) -> anyhow::Result<()> {
    paths.iter().try_for_each(|p| remove_if_present(p))
}

/// The processes that hold a live lease in the cache at `root`.
pub fn live_owners(root: &Path) -> anyhow::Result<Vec<Owner>> {
    Ok(live_leases(root)?.iter().map(|(_, r)| r.owner()).collect())
}

/// The live `gc` lease of the cache at `root`, if any.
pub fn live_gc(root: &Path) -> Option<LeaseRecord> {
    read_record(&leases_dir(root).join(GC_LEASE)).filter(|r| r.is_live(unix_now()))
}

/// Waits while another process holds a live `gc` lease on the cache at `root`; a wait longer
/// than [`SAY_AFTER`] calls `say` once with one line naming the cache and the `gc`. Returns
/// how long it waited. Take this process's own lease first: a `gc` starting meanwhile then
/// sees it and refuses.
pub fn wait_while_gc(root: &Path, say: &mut dyn FnMut(String)) -> Duration {
    let started = Instant::now();
    let mut said = false;
    while let Some(gc) = live_gc(root) {
        if !said && started.elapsed() >= SAY_AFTER {
            said = true;
            say(format!("waiting for {} to finish with the cache {} …", gc.describe(), root.display()));
        }
        std::thread::sleep(RETRY_EVERY);
    }
    started.elapsed()
}

pub fn leases_dir(root: &Path) -> PathBuf {
    root.join("leases")
}

pub fn unix_now() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

fn record(holder: &str, now: u64) -> LeaseRecord {
    let me = Owner::me();
    LeaseRecord {
        host: me.host,
        pid: me.pid,
        holder: holder.to_string(),
        started_unix: now,
        expires_unix: now + LEASE_TTL.as_secs(),
    }
}

fn read_record(path: &Path) -> Option<LeaseRecord> {
    serde_json::from_slice(&fs::read(path).ok()?).ok()
}

/// Whether a process with this id exists on this host (Linux: in `/proc`; elsewhere assumed,
/// so that only the lease's expiry ends it).
fn process_exists(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ended_pid() -> u32 {
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        pid
    }

    #[test]
    fn a_lease_lives_until_it_expires_or_its_process_on_this_host_ends() {
        let now = unix_now();
        let lease = |host: &str, pid: u32, expires_unix: u64| LeaseRecord {
            host: host.into(),
            pid,
            holder: "aret-pipe run".into(),
            started_unix: now - 10,
            expires_unix,
        };
        let here = this_host();
        assert!(lease(&here, std::process::id(), now + 60).is_live(now));
        assert!(!lease(&here, std::process::id(), now).is_live(now), "expired");
        assert!(!lease(&here, ended_pid(), now + 60).is_live(now), "killed here: seen at once");
        assert!(lease("elsewhere", ended_pid(), now + 60).is_live(now), "elsewhere: only expiry tells");
        assert!(!lease("elsewhere", 1, now - 1).is_live(now));
    }

    #[test]
    fn one_gc_at_a_time_and_a_killed_gcs_lease_is_taken_over() {
        let root = tempfile::tempdir().unwrap();
        let run = Lease::take(root.path(), "aret-pipe run").unwrap();
        assert_eq!(live_leases(root.path()).unwrap().len(), 1);
        let gc = Lease::take_gc(root.path(), "aret-pipe gc").unwrap().unwrap();
        assert!(live_gc(root.path()).is_some());
        let refused = Lease::take_gc(root.path(), "aret-pipe gc").unwrap().err().unwrap();
        assert_eq!((refused.pid, refused.holder.as_str()), (std::process::id(), "aret-pipe gc"));
        drop((gc, run));
        assert!(all_leases(root.path()).unwrap().is_empty(), "dropped leases are deleted");
        // What a gc killed on this host leaves: its lease names a process that has ended.
        let mut left = record("aret-pipe gc", unix_now());
        left.pid = ended_pid();
        let path = leases_dir(root.path()).join(GC_LEASE);
        std::fs::write(&path, serde_json::to_vec(&left).unwrap()).unwrap();
        assert!(live_gc(root.path()).is_none() && ended_leases(root.path()).unwrap() == [path]);
        let gc = Lease::take_gc(root.path(), "aret-pipe gc").unwrap().unwrap();
        assert_eq!(live_gc(root.path()).map(|r| r.pid), Some(std::process::id()));
        drop(gc);
    }
}
