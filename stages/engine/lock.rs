//! Advisory file locks between `aret-pipe` processes sharing one cache.
//!
//! `run` holds the cache's lock shared, `gc` exclusive, so garbage collection never deletes a
//! blob a running pipeline is about to use. While computing a (stage, key), a process holds that
//! key's lock: a second process wanting the same key waits, then finds it cached. The kernel
//! drops every lock when a process dies, even by SIGKILL.

use anyhow::Context as _;
use std::fs::{File, OpenOptions};
use std::path::Path;

/// A held lock; released on drop.
pub struct FileLock {
    _file: File,
}

fn open(path: &Path) -> anyhow::Result<File> {
    OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(path)
        .with_context(|| format!("opening lock file {}", path.display()))
}

impl FileLock {
    pub fn shared(path: &Path) -> anyhow::Result<FileLock> {
        let file = open(path)?;
        file.lock_shared().with_context(|| format!("locking {}", path.display()))?;
        Ok(FileLock { _file: file })
    }

    pub fn exclusive(path: &Path) -> anyhow::Result<FileLock> {
        let file = open(path)?;
        file.lock().with_context(|| format!("locking {}", path.display()))?;
        Ok(FileLock { _file: file })
    }

    /// The exclusive lock if nobody holds the file, else `None`.
    pub fn try_exclusive(path: &Path) -> anyhow::Result<Option<FileLock>> {
        let file = open(path)?;
        match file.try_lock() {
            Ok(()) => Ok(Some(FileLock { _file: file })),
            Err(std::fs::TryLockError::WouldBlock) => Ok(None),
            Err(std::fs::TryLockError::Error(e)) => Err(e).with_context(|| format!("locking {}", path.display())),
        }
    }
}
