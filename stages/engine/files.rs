//! Writing files that processes on many hosts share: each file is written under a temporary
//! name that carries its writer's host and process id ([`Owner`]), so that any process can
//! tell whether the writer may still be at work (see [`crate::lease`]), then renamed into place.

use anyhow::Context as _;
use std::fs;
use std::io::Write;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// The process that wrote a temporary file: its host and its process id there.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Owner {
    pub host: String,
    pub pid: u32,
}

impl Owner {
    /// This process.
    pub fn me() -> Owner {
        Owner { host: this_host(), pid: std::process::id() }
    }
}

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// A name no other process or thread on any host is using at the same moment:
/// `.tmp-<host>-<pid>-<n>-<nanos>` (see [`temp_owner`]).
pub fn temp_name() -> String {
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!(".tmp-{}-{}-{n}-{nanos}", this_host(), std::process::id())
}

/// The process a [`temp_name`] names, or `None` when `name` is not one. A name without a host
/// (`.tmp-<pid>-<n>-<nanos>`, as older versions wrote) is taken for one of this host.
pub fn temp_owner(name: &str) -> Option<Owner> {
    let rest = name.strip_prefix(".tmp-")?;
    let mut fields = rest.rsplitn(4, '-');
    let (_nanos, _n, pid) = (fields.next()?, fields.next()?, fields.next()?.parse().ok()?);
    let host = fields.next().map_or_else(this_host, str::to_string);
    Some(Owner { host, pid })
}

/// This host's name as file names carry it: letters, digits, `.` and `_` kept, anything else
/// (`-` included, which separates a name's fields) turned into `_`; at most 64 characters.
pub fn this_host() -> String {
    static HOST: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    HOST.get_or_init(|| {
        let raw = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .ok()
            .or_else(|| std::env::var("HOSTNAME").ok())
            .unwrap_or_default();
        let name: String = raw
            .trim()
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() || c == '.' || c == '_' { c } else { '_' })
            .take(64)
            .collect();
        if name.is_empty() {
            "localhost".into()
        } else {
            name
        }
    })
    .clone()
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, flushed to
/// disk, then renamed over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8], read_only: bool) -> anyhow::Result<()> {
    let dir = path.parent().expect("cache paths have a parent");
    fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let tmp = dir.join(temp_name());
    let result = (|| -> std::io::Result<()> {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        if read_only {
            set_read_only(&tmp)?;
        }
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result.with_context(|| format!("writing {}", path.display()))
}

/// Deletes the file at `path`; one already gone is no error (another process may have taken it).
pub fn remove_if_present(path: &Path) -> anyhow::Result<()> {
    match fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(e).with_context(|| format!("deleting {}", path.display()))
        }
        _ => Ok(()),
    }
}

/// Makes `path` read-only for everyone: mode 0444 on Unix.
pub fn set_read_only(path: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    let perms = std::os::unix::fs::PermissionsExt::from_mode(0o444);
    #[cfg(not(unix))]
    let perms = {
        let mut perms = fs::metadata(path)?.permissions();
        perms.set_readonly(true);
        perms
    };
    fs::set_permissions(path, perms)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_temp_name_gives_back_its_host_and_pid_and_an_old_one_this_host() {
        let me = Owner::me();
        assert_eq!(temp_owner(&temp_name()), Some(me.clone()));
        assert_eq!(
            temp_owner(".tmp-node_3.cluster-4242-0-17"),
            Some(Owner { host: "node_3.cluster".into(), pid: 4242 })
        );
        assert_eq!(temp_owner(".tmp-4242-0-17"), Some(Owner { host: me.host, pid: 4242 }));
        assert_eq!(temp_owner(".tmp-x-0-17"), None);
        assert_eq!(temp_owner("tmp-1-2-3"), None);
        assert!(!this_host().contains('-') && !this_host().is_empty());
    }
}
