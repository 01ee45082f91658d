//! Publishing results: `out_dir/<patient>/<name>` entries are hard links to cache blobs where
//! the filesystem allows, else copies. Each entry is replaced atomically.

use super::store::{temp_name, OutputRef, Store};
use anyhow::Context as _;
use std::fs;
use std::path::Path;

/// Makes `dir/<output name>` show each output's bytes.
pub fn publish(store: &Store, dir: &Path, outputs: &[OutputRef]) -> anyhow::Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("creating output folder {}", dir.display()))?;
    for output in outputs {
        let blob = store.blob_path(&output.hash);
        let target = dir.join(&output.name);
        if same_file(&blob, &target) {
            continue;
        }
        let tmp = dir.join(temp_name());
        if fs::hard_link(&blob, &tmp).is_err() {
            fs::copy(&blob, &tmp).with_context(|| format!("copying {} to {}", blob.display(), tmp.display()))?;
        }
        fs::rename(&tmp, &target).with_context(|| format!("writing {}", target.display()))?;
    }
    Ok(())
}

#[cfg(unix)]
fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (fs::metadata(a), fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => false,
    }
}

#[cfg(not(unix))]
fn same_file(_a: &Path, _b: &Path) -> bool {
    false
}
