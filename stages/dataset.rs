//! Which patients a configuration names, and where each one's files are.

use crate::config::{Config, DatasetKind};
use crate::engine::run::Unit;
use anyhow::{anyhow, bail, Context as _};
use std::path::Path;

/// The patients of `[dataset]`, sorted by ID, optionally narrowed to `only`.
pub fn units(config: &Config, only: Option<&[String]>) -> anyhow::Result<Vec<Unit>> {
    let root = config.dataset_root();
    let units = match config.dataset.kind {
        DatasetKind::Dicom => dicom_folders(&root)?,
        DatasetKind::Lidc => lidc_folders(&root)?,
        DatasetKind::Phantom => phantom_cohort(&root)?,
    };
    narrow(units, only, &root)
}

/// `units` sorted by ID and narrowed to `only` (every ID in it must exist).
pub fn narrow(mut units: Vec<Unit>, only: Option<&[String]>, root: &Path) -> anyhow::Result<Vec<Unit>> {
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
fn dicom_folders(root: &Path) -> anyhow::Result<Vec<Unit>> {
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

/// The TCIA layout: `root/LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/…` (or `root` = that
/// `LIDC-IDRI` folder). Each `LIDC-IDRI-*` folder is one patient; other entries are ignored.
fn lidc_folders(root: &Path) -> anyhow::Result<Vec<Unit>> {
    let collection = root.join("LIDC-IDRI");
    let dir = if collection.is_dir() { collection } else { root.to_path_buf() };
    let units: Vec<Unit> = dicom_folders(&dir)
        .map_err(|e| anyhow!("{e:#} (kind = \"lidc\" expects root/LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/)"))?
        .into_iter()
        .filter(|u| u.id.starts_with("LIDC-IDRI-"))
        .collect();
    if units.is_empty() {
        bail!(
            "[dataset] root {} has no LIDC-IDRI-XXXX patient folders (TCIA layout: LIDC-IDRI/LIDC-IDRI-XXXX/…)",
            dir.display()
        );
    }
    Ok(units)
}

/// A phantom cohort: each `<patient>.scan.json` (scan geometry) with its `<patient>.xml`
/// (the radiologists' annotations) is one patient.
pub fn phantom_cohort(cohort: &Path) -> anyhow::Result<Vec<Unit>> {
    let entries =
        std::fs::read_dir(cohort).map_err(|e| anyhow!("[dataset] cohort {} cannot be read ({e})", cohort.display()))?;
    let mut units = Vec::new();
    for entry in entries {
        let name = entry.with_context(|| format!("listing {}", cohort.display()))?.file_name();
        let Some(id) = name.to_string_lossy().strip_suffix(".scan.json").map(str::to_string) else {
            continue;
        };
        let xml = format!("{id}.xml");
        if !cohort.join(&xml).is_file() {
            bail!("cohort patient `{id}` has {id}.scan.json but no {xml} in {}", cohort.display());
        }
        units.push(Unit {
            id: id.clone(),
            source_dir: cohort.to_path_buf(),
            source_files: Some(vec![format!("{id}.scan.json"), xml]),
        });
    }
    if units.is_empty() {
        bail!("[dataset] cohort {} has no <patient>.scan.json files", cohort.display());
    }
    Ok(units)
}
