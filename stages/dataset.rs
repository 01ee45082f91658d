//! Which patients a configuration names, and where each one's files are.
//!
//! A patient ID names the patient's folder under `out_dir` and its entries in the cache, so
//! [`patient_id`] — the one place IDs are made, for every dataset kind — accepts only a name
//! that is one plain path component and reads the same wherever it is shown: see its doc for
//! the rule. Two patients whose IDs differ only in letter case are refused as well (they would
//! share a folder on a case-insensitive disk).

use crate::config::{Config, DatasetKind};
use crate::engine::run::Unit;
use anyhow::{anyhow, bail, Context as _};
use std::ffi::OsStr;
use std::path::Path;

/// Longest patient ID, in bytes: leaves room for the suffixes the cache adds (`.json`) within
/// the 255-byte file-name limit of common file systems.
pub const MAX_PATIENT_ID_BYTES: usize = 200;

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

/// `units` sorted by ID and narrowed to `only` (every ID in it must exist). Two units with the
/// same ID, or IDs equal but for letter case, are an error.
pub fn narrow(mut units: Vec<Unit>, only: Option<&[String]>, root: &Path) -> anyhow::Result<Vec<Unit>> {
    units.sort_by(|a, b| a.id.cmp(&b.id));
    refuse_colliding_ids(&units, root)?;
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

/// The patient ID a dataset entry's name gives, or why it cannot be one. `name` is the ID
/// candidate (a folder name, or a cohort file name less its suffix); `entry` is the file or
/// folder it comes from, named in the error.
///
/// The rule: the ID is valid UTF-8 (so no two names collapse into one lossy display), at most
/// [`MAX_PATIENT_ID_BYTES`] bytes, not empty, not `.` or `..` and not starting with `.` (a
/// hidden name), not starting with `-` (it would read as an option on a command line), without
/// leading or trailing whitespace, and without `/`, `\`, NUL or any other control character.
/// Everything else — letters of any script, digits, spaces inside, `_`, `-`, `.` — is kept
/// as it is, byte for byte.
pub fn patient_id(name: &OsStr, entry: &Path) -> anyhow::Result<String> {
    let refuse = |why: &str| {
        anyhow!(
            "{}: `{}` cannot be a patient ID: {why}; rename it (patient IDs become folder names under out_dir)",
            entry.display(),
            name.to_string_lossy().escape_debug()
        )
    };
    let Some(id) = name.to_str() else {
        return Err(refuse("the name is not valid UTF-8, so it would be shown (and could collide) as another name"));
    };
    if id.is_empty() {
        return Err(refuse("it is empty"));
    }
    if id.len() > MAX_PATIENT_ID_BYTES {
        return Err(refuse(&format!("it is {} bytes long, more than {MAX_PATIENT_ID_BYTES}", id.len())));
    }
    if id == "." || id == ".." {
        return Err(refuse("it names a folder itself, not a patient, and would write outside out_dir"));
    }
    if id.starts_with('.') {
        return Err(refuse("it starts with `.` (a hidden name)"));
    }
    if id.starts_with('-') {
        return Err(refuse("it starts with `-`, which reads as an option on a command line"));
    }
    if id.trim() != id {
        return Err(refuse("it starts or ends with whitespace"));
    }
    if let Some(c) = id.chars().find(|&c| c == '/' || c == '\\' || c.is_control()) {
        return Err(refuse(&format!("it contains {c:?}, a path separator or control character")));
    }
    Ok(id.to_string())
}

/// IDs must be unique, and unique ignoring letter case: `out_dir/<id>` of two patients must
/// never be one folder.
fn refuse_colliding_ids(units: &[Unit], root: &Path) -> anyhow::Result<()> {
    let mut folded: Vec<(String, &Unit)> = units.iter().map(|u| (u.id.to_lowercase(), u)).collect();
    folded.sort_by(|a, b| a.0.cmp(&b.0));
    if let Some(pair) = folded.windows(2).find(|w| w[0].0 == w[1].0) {
        let (a, b) = (pair[0].1, pair[1].1);
        bail!(
            "[dataset] {}: patients `{}` (from {}) and `{}` (from {}) would share one output folder \
             (IDs equal{}); rename one of them",
            root.display(),
            a.id,
            a.source_dir.display(),
            b.id,
            b.source_dir.display(),
            if a.id == b.id { "" } else { " but for letter case" }
        );
    }
    Ok(())
}

/// `root/<patient>/…`: each non-hidden sub-folder is one patient, named by the folder.
fn dicom_folders(root: &Path) -> anyhow::Result<Vec<Unit>> {
    let units = patient_folders(root, |_| true)?;
    if units.is_empty() {
        bail!("[dataset] root {} has no patient folders: expected one sub-folder per patient", root.display());
    }
    Ok(units)
}

/// The non-hidden sub-folders of `root` whose names `keep` accepts, each one patient named by
/// its folder (a name that makes no valid ID is an error; one `keep` refuses is passed over).
fn patient_folders(root: &Path, keep: impl Fn(&[u8]) -> bool) -> anyhow::Result<Vec<Unit>> {
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
        let name = entry.file_name();
        let bytes = name.as_encoded_bytes();
        if bytes.starts_with(b".") || !keep(bytes) || !entry.path().is_dir() {
            continue;
        }
        units.push(Unit::folder(patient_id(&name, &entry.path())?, entry.path()));
    }
    Ok(units)
}

/// The TCIA layout: `root/LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/…` (or `root` = that
/// `LIDC-IDRI` folder). Each `LIDC-IDRI-*` folder is one patient; other entries are ignored.
fn lidc_folders(root: &Path) -> anyhow::Result<Vec<Unit>> {
    let collection = root.join("LIDC-IDRI");
    let dir = if collection.is_dir() { collection } else { root.to_path_buf() };
    let units = patient_folders(&dir, |name| name.starts_with(b"LIDC-IDRI-"))
        .map_err(|e| anyhow!("{e:#} (kind = \"lidc\" expects root/LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/)"))?;
    if units.is_empty() {
        bail!(
            "[dataset] root {} has no LIDC-IDRI-XXXX patient folders (TCIA layout: LIDC-IDRI/LIDC-IDRI-XXXX/…)",
            dir.display()
        );
    }
    Ok(units)
}

/// A phantom cohort: each `<patient>.scan.json` (scan geometry) with its `<patient>.xml`
/// (the radiologists' annotations) is one patient. Every name ending in `.scan.json` is one,
/// hidden or not, so a name that makes no valid ID is an error rather than passed over.
pub fn phantom_cohort(cohort: &Path) -> anyhow::Result<Vec<Unit>> {
    const SUFFIX: &[u8] = b".scan.json";
    let entries =
        std::fs::read_dir(cohort).map_err(|e| anyhow!("[dataset] cohort {} cannot be read ({e})", cohort.display()))?;
    let mut units = Vec::new();
    for entry in entries {
        let entry = entry.with_context(|| format!("listing {}", cohort.display()))?;
        let name = entry.file_name();
        if !name.as_encoded_bytes().ends_with(SUFFIX) {
            continue;
        }
        // A name that is not UTF-8 is refused by `patient_id` whole, suffix and all.
        let id = match name.to_str() {
            Some(text) => patient_id(OsStr::new(&text[..text.len() - SUFFIX.len()]), &entry.path())?,
            None => patient_id(&name, &entry.path())?,
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
