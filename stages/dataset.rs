//! Which patients a configuration names, and where each one's files are.

use crate::config::{Config, DatasetKind};
use crate::engine::run::Unit;
use anyhow::{anyhow, bail, Context as _};

/// The patients of `[dataset]`, sorted by ID, optionally narrowed to `only`.
pub fn units(config: &Config, only: Option<&[String]>) -> anyhow::Result<Vec<Unit>> {
    let root = config.dataset_root();
    let mut units = match config.dataset.kind {
        DatasetKind::Dicom => dicom_folders(&root)?,
    };
    units.sort_by(|a, b| a.id.cmp(&b.id));
    if let Some(only) = only {
        let unknown: Vec<&String> = only.iter().filter(|id| !units.iter().any(|u| &u.id == *id)).collect();
        if !unknown.is_empty() {
            let known: Vec<&str> = units.iter().map(|u| u.id.as_str()).collect();
            bail!(
                "--patients names {} not in the dataset at {} (it has: {})",
                unknown.iter().map(|s| format!("`{s}`")).collect::<Vec<_>>().join(", "),
                root.display(),
                known.join(", ")
            );
        }
        units.retain(|u| only.contains(&u.id));
    }
    Ok(units)
}

/// `root/<patient>/…`: each non-hidden sub-folder is one patient, named by the folder.
fn dicom_folders(root: &std::path::Path) -> anyhow::Result<Vec<Unit>> {
    let entries = std::fs::read_dir(root).map_err(|e| {
        anyhow!(
            "[dataset] root {} cannot be read ({e}): put one sub-folder per patient holding its CT series there, \
             or point `root` in the configuration elsewhere",
            root.display()
        )
    })?;
    let mut units = Vec::new();
    for entry in entries {
        let entry = entry.with_context(|| format!("listing {}", root.display()))?;
        let name = entry.file_name().to_string_lossy().to_string();
        if name.starts_with('.') || !entry.path().is_dir() {
            continue;
        }
        units.push(Unit::folder(name, entry.path()));
    }
    if units.is_empty() {
        bail!("[dataset] root {} has no patient folders: expected one sub-folder per patient", root.display());
    }
    Ok(units)
}
