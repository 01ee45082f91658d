//! Advisory file locks on a (stage, key) between `aret-pipe` processes sharing one cache.
//!
//! While computing a (stage, key), a process holds that key's lock: a second process wanting
//! the same key waits, then finds it cached. The kernel drops every lock when a process dies,
//! even by SIGKILL. The locks only save work: where a filesystem keeps none (an NFS mount
//! without a lock manager), two processes may compute one key at once, and converge, since a
//! key's outputs are the same bytes whoever computes them and each lands by an atomic rename.
//! Which processes are alive, and whether `gc` may delete, is told by leases instead
//! ([`crate::lease`]), which need no locks across hosts.
//!
//! A process that must wait for a lock says so once the wait passes [`SAY_AFTER`], naming the
//! lock and, when the holder wrote it into the lock file ([`FileLock::describe_holder`]), who
//! holds it.

use anyhow::Context as _;
use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;
use std::time::{Duration, Instant};

/// A held lock; released on drop.
pub struct FileLock {
    file: File,
}

/// How long a process waits for a lock before it says what it waits for.
pub const SAY_AFTER: Duration = Duration::from_secs(1);

/// How often a waiting process tries the lock again.
const RETRY_EVERY: Duration = Duration::from_millis(20);

fn open(path: &Path) -> anyhow::Result<File> {
    OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(path)
        .with_context(|| format!("opening lock file {}", path.display()))
}

impl FileLock {
    /// The exclusive lock, waiting as long as it takes, silently.
    pub fn exclusive(path: &Path) -> anyhow::Result<FileLock> {
        let file = open(path)?;
        file.lock().with_context(|| format!("locking {}", path.display()))?;
        Ok(FileLock { file })
    }

    /// The exclusive lock at `path`, waiting as long as it takes. A wait longer than
    /// [`SAY_AFTER`] calls `say` once with one line: "waiting for another aret-pipe process to
    /// release `what` (the path; held by: its holder's description, when known) …". Returns
    /// the lock and how long the wait was.
    pub fn wait(path: &Path, what: &str, say: &mut dyn FnMut(String)) -> anyhow::Result<(FileLock, Duration)> {
        let file = open(path)?;
        let started = Instant::now();
        let mut said = false;
        loop {
            match file.try_lock() {
                Ok(()) => return Ok((FileLock { file }, started.elapsed())),
                Err(TryLockError::WouldBlock) => {}
                Err(TryLockError::Error(e)) if locks_unsupported(&e) => {
                    say(format!(
                        "{} cannot be locked ({e}): going on without it; a process on another host may \
                         compute the same result at the same time, to the same bytes",
                        path.display()
                    ));
                    return Ok((FileLock { file }, started.elapsed()));
                }
                Err(TryLockError::Error(e)) => return Err(e).with_context(|| format!("locking {}", path.display())),
            }
            if !said && started.elapsed() >= SAY_AFTER {
                said = true;
                let holder = std::fs::read_to_string(path).unwrap_or_default();
                let holder = holder.trim();
                let held_by = if holder.is_empty() { String::new() } else { format!("; held by {holder}") };
                say(format!("waiting for another aret-pipe process to release {what} ({}{held_by}) …", path.display()));
            }
            std::thread::sleep(RETRY_EVERY);
        }
    }

    /// Writes who holds this exclusive lock into its file, for the processes that wait on it
    /// ([`FileLock::wait`]). Best effort: a lock works without it.
    pub fn describe_holder(&self, holder: &str) {
        let mut file = &self.file;
        let _ = file
            .set_len(0)
            .and_then(|()| file.seek(SeekFrom::Start(0)))
            .and_then(|_| file.write_all(format!("{holder} (pid {})\n", std::process::id()).as_bytes()));
    }
}

/// Whether `e` says the filesystem keeps no locks (an NFS mount without a lock manager), as
/// opposed to a real failure.
fn locks_unsupported(e: &std::io::Error) -> bool {
    const ENOLCK: i32 = 37;
    const EOPNOTSUPP: i32 = 95;
    e.kind() == std::io::ErrorKind::Unsupported || matches!(e.raw_os_error(), Some(ENOLCK | EOPNOTSUPP))
}
