//! Leases of pretend processes, written into a cache as a process on another host (or one that
//! ended) would have left them.

#![allow(dead_code)] // shared by several test crates; each uses a subset

use aret_pipe::engine::lease::{leases_dir, unix_now, LeaseRecord, GC_LEASE};
use std::path::{Path, PathBuf};

/// Writes the lease of `holder` on `host` (pid `pid`), expiring `expires_in_s` from now
/// (negative: already expired); a `holder` of `aret-pipe gc` writes the gc lease. Returns its path.
pub fn pretend_lease(cache: &Path, host: &str, pid: u32, holder: &str, expires_in_s: i64) -> PathBuf {
    let now = unix_now();
    let record = LeaseRecord {
        host: host.into(),
        pid,
        holder: holder.into(),
        started_unix: now - 5,
        expires_unix: now.saturating_add_signed(expires_in_s),
    };
    let name = if holder == "aret-pipe gc" { GC_LEASE.to_string() } else { format!("{host}-{pid}-0.json") };
    let path = leases_dir(cache).join(name);
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, serde_json::to_vec_pretty(&record).unwrap()).unwrap();
    path
}
