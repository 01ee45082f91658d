//! The valid values of every numeric key, checked on the merged layers before anything is built,
//! with an error that names the key, the file and line that gave it, and its range. The table
//! below is the one place these limits live; `docs/config_ranges.md` is written from it.

use std::fmt;
use toml::{Table, Value};

/// Which numbers a key takes.
#[derive(Debug, Clone, Copy)]
pub(super) enum Allowed {
    /// lo ≤ v ≤ hi.
    Closed(f64, f64),
    /// lo < v ≤ hi.
    AboveUpTo(f64, f64),
    /// lo ≤ v < hi.
    FromBelow(f64, f64),
    /// lo < v < hi.
    Between(f64, f64),
    /// One of these integers.
    OneOf(&'static [i64]),
}

impl Allowed {
    fn contains(self, v: f64) -> bool {
        match self {
            Allowed::Closed(lo, hi) => lo <= v && v <= hi,
            Allowed::AboveUpTo(lo, hi) => lo < v && v <= hi,
            Allowed::FromBelow(lo, hi) => lo <= v && v < hi,
            Allowed::Between(lo, hi) => lo < v && v < hi,
            Allowed::OneOf(values) => values.iter().any(|&x| x as f64 == v),
        }
    }
}

impl fmt::Display for Allowed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = |x: f64| match x {
            SEED_MAX => "2^63 - 1".to_string(),
            x if x == x.trunc() && x.abs() < 1e15 => format!("{}", x as i64),
            x => format!("{x}"),
        };
        match *self {
            Allowed::Closed(lo, hi) => write!(f, "[{}, {}]", n(lo), n(hi)),
            Allowed::AboveUpTo(lo, hi) => write!(f, "({}, {}]", n(lo), n(hi)),
            Allowed::FromBelow(lo, hi) => write!(f, "[{}, {})", n(lo), n(hi)),
            Allowed::Between(lo, hi) => write!(f, "({}, {})", n(lo), n(hi)),
            Allowed::OneOf(values) => {
                let values: Vec<String> = values.iter().map(i64::to_string).collect();
                write!(f, "one of {}", values.join(", "))
            }
        }
    }
}

/// A key (`*`: every key of the table), the numbers it takes (each element of a list), and
/// what they count.
#[derive(Debug, Clone, Copy)]
pub(super) struct KeyRange {
    pub table: &'static str,
    pub key: &'static str,
    pub allowed: Allowed,
    pub unit: &'static str,
}

const fn range(table: &'static str, key: &'static str, allowed: Allowed, unit: &'static str) -> KeyRange {
    KeyRange { table, key, allowed, unit }
}

/// The largest seed a TOML integer holds.
const SEED_MAX: f64 = i64::MAX as f64;

use Allowed::{AboveUpTo, Between, Closed, FromBelow, OneOf};

/// Every numeric key of the configuration and its valid values.
pub(super) const KEY_RANGES: &[KeyRange] = &[
    range("pipeline", "workers", Closed(1.0, 256.0), "patients at once"),
    range("pipeline.stage_workers", "*", Closed(1.0, 256.0), "patients at once"),
    range("dataset.phantom", "seed", Closed(0.0, SEED_MAX), ""),
    range("dataset.phantom", "noise_hu", Closed(0.0, 500.0), "HU"),
    range("dataset.phantom", "lung_hu", Closed(-1000.0, -500.0), "HU"),
    range("dataset.phantom", "lung_texture_hu", Closed(0.0, 200.0), "HU"),
    range("dataset.phantom", "min_vessel_radius_mm", Closed(0.1, 5.0), "mm"),
    range("ingest", "slice_gap_tolerance", FromBelow(0.0, 0.5), "of the median gap"),
    range("ingest", "clevel", AboveUpTo(0.0, 1.0), "of the readers"),
    range("hu", "hu_min", Closed(-2048.0, 4095.0), "HU"),
    range("hu", "hu_max", Closed(-2048.0, 4095.0), "HU"),
    range("drr", "width_px", Closed(8.0, 8192.0), "pixels"),
    range("drr", "height_px", Closed(8.0, 8192.0), "pixels"),
    range("drr", "focal_px", AboveUpTo(0.0, 1e6), "pixels"),
    range("drr", "distance", AboveUpTo(0.0, 1e4), "box units"),
    range("drr", "mm_per_unit", AboveUpTo(0.0, 1000.0), "mm"),
    range("drr", "aabb_min", Closed(-100.0, 100.0), "box units"),
    range("drr", "aabb_max", Closed(-100.0, 100.0), "box units"),
    range("drr", "roi_center", Closed(-1e4, 1e4), "mm"),
    range("drr", "attenuation_scale", AboveUpTo(0.0, 100.0), ""),
    range("drr", "photons", Closed(0.0, 1e12), "photons a pixel"),
    range("drr", "detector_noise", Closed(0.0, 1.0), "of the signal"),
    range("drr", "pose_error_deg", Closed(0.0, 45.0), "degrees"),
    range("drr", "pose_error_mm", Closed(0.0, 100.0), "mm"),
    range("drr", "view_angle_offsets_deg", Closed(-180.0, 180.0), "degrees"),
    range("drr", "seed", Closed(0.0, SEED_MAX), ""),
    range("drr.tiles", "counts", Closed(1.0, 64.0), "boxes an axis"),
    range("drr.tiles", "step_mm", AboveUpTo(0.0, 1000.0), "mm"),
    range("train", "grid", Closed(2.0, 512.0), "nodes a side"),
    range("train", "scale", AboveUpTo(0.0, 100.0), ""),
    range("train", "log_every", Closed(0.0, 1e9), "steps"),
    range("train", "threads", Closed(0.0, 1024.0), "threads; 0: all cores"),
    range("train.dense_tv", "iterations", Closed(1.0, 1e6), "steps"),
    range("train.dense_tv", "tolerance", FromBelow(0.0, 1.0), "relative change"),
    range("train.dense_tv", "lambda", Closed(0.0, 1000.0), ""),
    range("train.dense_tv", "epsilon", AboveUpTo(0.0, 10.0), ""),
    range("train.vm", "rank", Closed(1.0, 256.0), "components"),
    range("train.vm", "shift", Closed(-100.0, 100.0), ""),
    range("train.vm", "iterations", Closed(1.0, 1e7), "steps"),
    range("train.vm", "batch_rays", Closed(1.0, 1_048_576.0), "rays a step"),
    range("train.vm", "lr", AboveUpTo(0.0, 10.0), ""),
    range("train.vm", "lr_decay_ratio", AboveUpTo(0.0, 1.0), ""),
    range("train.vm", "lambda_l1", Closed(0.0, 1000.0), ""),
    range("train.vm", "lambda_tv", Closed(0.0, 1000.0), ""),
    range("train.vm", "lambda_tv3d", Closed(0.0, 1000.0), ""),
    range("train.vm", "init_scale", AboveUpTo(0.0, 10.0), ""),
    range("train.vm", "alpha_mask_iterations", Closed(0.0, 1e7), "steps"),
    range("train.vm", "alpha_threshold", FromBelow(0.0, 1.0), ""),
    range("train.vm", "seed", Closed(0.0, SEED_MAX), ""),
    range("sweep", "percentiles", Closed(0.0, 100.0), "percent"),
    range("sweep", "connectivity", OneOf(&[6, 18, 26]), "neighbours"),
    range("sweep", "min_voxels", Closed(1.0, 1e9), "voxels"),
    range("sweep", "closing_radius", Closed(0.0, 16.0), "voxels"),
    range("sweep", "diameter_mm", Closed(0.0, 500.0), "mm"),
    range("sweep", "background_mm", AboveUpTo(0.0, 200.0), "mm"),
    range("select.blob", "scales_mm", AboveUpTo(0.0, 100.0), "mm"),
    range("select.blob", "inside_mm", Closed(0.0, 100.0), "mm"),
    range("select.blob", "rival_ratio", AboveUpTo(0.0, 100.0), ""),
    range("select.blob", "guided_faint_ratio", Closed(0.0, 1.0), ""),
    range("select.half_max", "fraction", Between(0.0, 1.0), "of the peak"),
    range("select.half_max", "guided_diameter_ratio", Closed(0.0, 100.0), "annotated diameters"),
    range("select.half_max", "guided_reach_diameters", AboveUpTo(0.0, 100.0), "annotated diameters"),
    range("metrics", "bootstrap_resamples", Closed(100.0, 1e7), "resamples"),
    range("metrics", "seed", Closed(0.0, SEED_MAX), ""),
];

/// The first number of `merged` outside its key's range, as an error; `locate` gives the file
/// and line of a key (`["drr", "width_px"]`).
pub(super) fn check(merged: &Table, locate: impl Fn(&[&str]) -> Option<String>) -> anyhow::Result<()> {
    for r in KEY_RANGES {
        let path: Vec<&str> = r.table.split('.').collect();
        let Some(table) = path.iter().try_fold(merged, |t, name| t.get(*name).and_then(Value::as_table)) else {
            continue;
        };
        for (key, value) in table.iter().filter(|(key, _)| r.key == "*" || *key == r.key) {
            let numbers: Vec<f64> = match value {
                Value::Array(items) => items.iter().filter_map(number).collect(),
                other => number(other).into_iter().collect(),
            };
            let Some(bad) = numbers.into_iter().find(|&v| !r.allowed.contains(v)) else { continue };
            let keys: Vec<&str> = path.iter().copied().chain([key.as_str()]).collect();
            let place = locate(&keys).map_or(String::new(), |w| format!("{w}, "));
            let unit = if r.unit.is_empty() { String::new() } else { format!(" ({})", r.unit) };
            anyhow::bail!("{place}[{}] {key}: {bad} is out of range: it takes {}{unit}", r.table, r.allowed);
        }
    }
    Ok(())
}

fn number(value: &Value) -> Option<f64> {
    match value {
        Value::Integer(i) => Some(*i as f64),
        Value::Float(f) => Some(*f),
        _ => None,
    }
}

/// `docs/config_ranges.md`: the table above as Markdown (the test that keeps that file current
/// writes it).
#[cfg(test)]
pub(super) fn markdown() -> String {
    let mut out = String::from(
        "# The valid values of every numeric key\n\n\
         Written from `stages/config/ranges.rs` (`UPDATE_DOCS=1 cargo test --lib config` rewrites it). A value \
         outside its range is refused with an error naming the key, the file and line that gave it, and the \
         range; each number of a list is checked.\n\n| table | key | valid values | unit |\n| --- | --- | --- | --- |\n",
    );
    for r in KEY_RANGES {
        let key = if r.key == "*" { "every key".to_string() } else { format!("`{}`", r.key) };
        out.push_str(&format!("| `[{}]` | {key} | {} | {} |\n", r.table, r.allowed, r.unit));
    }
    out
}
