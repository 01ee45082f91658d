//! `pipeline.toml`: the schema, its defaults, and errors that name the key, its file and line.
//!
//! Each stage's table deserialises straight into that stage's `Params`, whose defaults are the
//! shipped method; unknown keys and wrong types are errors. A configuration is read in layers
//! ([`layers`]): the file a configuration `extends`, the file itself, then each `--set`.
//! Relative paths are taken relative to the folder of the file that gives them.

mod layers;
mod ranges;

use crate::stage::{drr, grid, hu, ingest, metrics, select, sweep, train};
use anyhow::bail;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    pub pipeline: PipelineSection,
    pub dataset: DatasetSection,
    #[serde(default)]
    pub ingest: ingest::Params,
    #[serde(default)]
    pub hu: hu::Params,
    #[serde(default)]
    pub drr: drr::Params,
    #[serde(default)]
    pub train: train::Params,
    #[serde(default)]
    pub grid: grid::Params,
    #[serde(default)]
    pub sweep: sweep::Params,
    #[serde(default)]
    pub select: select::Params,
    #[serde(default)]
    pub metrics: metrics::Params,
    /// The folder relative paths are resolved against (the config file's folder).
    #[serde(skip)]
    pub base_dir: PathBuf,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineSection {
    /// A name for this configuration, shown in reports.
    pub name: String,
    #[serde(default = "default_cache_dir")]
    pub cache_dir: PathBuf,
    /// A remote cache shared by many machines behind `cache_dir` (`s3://bucket/prefix`,
    /// `gs://…`, `az://…`, `file:///folder`; see `crate::engine::remote`). Unset or `""`: none.
    #[serde(default)]
    pub cache_remote: Option<String>,
    #[serde(default = "default_out_dir")]
    pub out_dir: PathBuf,
    /// Worker threads per stage (patients a stage works on at once).
    #[serde(default = "default_workers")]
    pub workers: usize,
    /// Per-stage overrides of `workers`, e.g. `{ train = 1 }`.
    #[serde(default)]
    pub stage_workers: BTreeMap<String, usize>,
}

fn default_cache_dir() -> PathBuf {
    "cache".into()
}
fn default_out_dir() -> PathBuf {
    "out".into()
}
fn default_workers() -> usize {
    2
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DatasetKind {
    /// `root/<patient>/…`: one folder per patient holding a CT series (any nesting) and
    /// optionally its LIDC XML.
    Dicom,
    /// The TCIA download layout: `root/LIDC-IDRI/LIDC-IDRI-XXXX/<study>/<series>/` with the
    /// `*.dcm` files and the XML (`root` may also be the `LIDC-IDRI` folder itself).
    Lidc,
    /// A synthetic-CT cohort built around real LIDC annotations: `cohort/<patient>.xml` +
    /// `<patient>.scan.json`, generated into the cache on first run.
    Phantom,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetSection {
    pub kind: DatasetKind,
    /// `dicom`, `lidc`: the dataset folder.
    pub root: Option<PathBuf>,
    /// `phantom`: the cohort folder of annotations and scan geometry.
    pub cohort: Option<PathBuf>,
    /// `phantom`: the generator's parameters (`[dataset.phantom]`; defaults when absent).
    pub phantom: Option<crate::phantom::PhantomParams>,
}

impl DatasetSection {
    /// Each kind has its folder (a key of another kind is refused as the layers are merged).
    fn check(&self) -> anyhow::Result<()> {
        let kind = serde_json::to_string(&self.kind).expect("kind serialises");
        match self.kind {
            DatasetKind::Dicom | DatasetKind::Lidc if self.root.is_none() => {
                bail!("[dataset] kind = {kind} needs `root`, the dataset folder")
            }
            DatasetKind::Phantom if self.cohort.is_none() => {
                bail!("[dataset] kind = \"phantom\" needs `cohort`, e.g. \"tools/cohorts/paper19\"")
            }
            _ => Ok(()),
        }
    }
}

impl Config {
    /// Reads and checks `path` and what it `extends`. Errors name the file, the key and its line.
    pub fn load(path: &Path) -> anyhow::Result<Config> {
        Config::load_with(path, &[])
    }

    /// [`Config::load`], then each `section.key=value` of `sets` over it, typed and checked as
    /// if the file said so (a path given there is relative to the current folder).
    pub fn load_with(path: &Path, sets: &[String]) -> anyhow::Result<Config> {
        let mut stack = layers::Stack::read(path)?;
        for set in sets {
            stack.push_set(set)?;
        }
        let mut config = stack.resolve()?;
        config.base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        if config.base_dir.as_os_str().is_empty() {
            config.base_dir = ".".into();
        }
        Ok(config)
    }

    /// Parses configuration text (paths stay relative; no `extends`).
    pub fn parse(text: &str) -> anyhow::Result<Config> {
        layers::Stack::from_text(text)?.resolve()
    }

    fn check(&self) -> anyhow::Result<()> {
        if self.pipeline.workers == 0 {
            bail!("[pipeline] workers must be at least 1");
        }
        let stages = crate::stage::STAGE_NAMES;
        for (name, &n) in &self.pipeline.stage_workers {
            if !stages.contains(&name.as_str()) {
                bail!("[pipeline.stage_workers] has `{name}`, which is not a stage (stages: {})", stages.join(", "));
            }
            if n == 0 {
                bail!("[pipeline.stage_workers] {name} must be at least 1");
            }
        }
        self.dataset.check()?;
        self.check_phantom_consensus_level()?;
        self.hu.check()?;
        self.drr.check()?;
        self.train.check()?;
        self.ingest.check()?;
        self.sweep.check()?;
        self.select.check()?;
        Ok(())
    }

    /// A phantom drawn as its consensus is the ground truth only when `ingest` scores against
    /// the same level.
    fn check_phantom_consensus_level(&self) -> anyhow::Result<()> {
        use crate::kernels::consensus::DEFAULT_CLEVEL;
        let extent = self.dataset.phantom.as_ref().map(|p| p.nodule_extent);
        if extent == Some(crate::phantom::NoduleExtent::Consensus) && self.ingest.clevel != DEFAULT_CLEVEL {
            bail!(
                "[dataset.phantom] nodule_extent = \"consensus\" draws each nodule as its {} % consensus, but \
                 [ingest] clevel = {} scores it against another level: set clevel = {DEFAULT_CLEVEL}, or draw \
                 nodule_extent = \"readers\" (graded by the fraction of readers) or \"union\"",
                100.0 * DEFAULT_CLEVEL,
                self.ingest.clevel
            );
        }
        Ok(())
    }

    pub fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.base_dir.join(p)
        }
    }

    pub fn cache_dir(&self) -> PathBuf {
        self.resolve(&self.pipeline.cache_dir)
    }

    /// The remote cache's URL, if one is set (`""` sets none).
    pub fn cache_remote(&self) -> Option<&str> {
        self.pipeline.cache_remote.as_deref().filter(|url| !url.is_empty())
    }

    /// A `cache_remote` that is not a remote cache URL is an error naming the key, where it is
    /// set (`where_is`) and the URLs it takes.
    fn check_cache_remote(&self, where_is: impl Fn(&[&str]) -> Option<String>) -> anyhow::Result<()> {
        let Some(url) = self.cache_remote() else { return Ok(()) };
        if let Err(why) = crate::engine::remote::check_url(url) {
            let place = where_is(&["pipeline", "cache_remote"]).map_or(String::new(), |w| format!("{w}: "));
            bail!("{place}[pipeline] cache_remote: {why}; it takes {}", crate::engine::remote::SCHEMES);
        }
        Ok(())
    }

    pub fn out_dir(&self) -> PathBuf {
        self.resolve(&self.pipeline.out_dir)
    }

    /// The dataset's folder: `root`, or `cohort` for a phantom dataset.
    pub fn dataset_root(&self) -> PathBuf {
        let dir = self.dataset.root.as_ref().or(self.dataset.cohort.as_ref()).expect("checked by Config::parse");
        self.resolve(dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = "[pipeline]\nname = \"t\"\n[dataset]\nkind = \"dicom\"\nroot = \"data\"\n";

    #[test]
    fn minimal_config_gets_defaults() {
        let c = Config::parse(MINIMAL).unwrap();
        assert_eq!(c.pipeline.workers, 2);
        assert_eq!(c.hu.hu_max, 400.0);
    }

    #[test]
    fn unknown_key_names_key_and_line() {
        let text = format!("{MINIMAL}[hu]\nhu_maxx = 3\n");
        let e = Config::parse(&text).unwrap_err().to_string();
        assert!(e.contains("line 7") && e.contains("hu_maxx"), "{e}");
    }

    #[test]
    fn wrong_type_names_key_and_line() {
        let text = format!("{MINIMAL}[hu]\nhu_max = \"high\"\n");
        let e = Config::parse(&text).unwrap_err().to_string();
        assert!(e.contains("line 7") && e.contains("hu_max"), "{e}");
    }

    #[test]
    fn keys_in_future_stage_tables_are_rejected() {
        let e = Config::parse(&format!("{MINIMAL}[grid]\nsize = 3\n")).unwrap_err().to_string();
        assert!(e.contains("size"), "{e}");
        let e = Config::parse(&format!("{MINIMAL}[train]\niters = 3\n")).unwrap_err().to_string();
        assert!(e.contains("[train] iters") && e.contains("dense_tv"), "{e}");
    }

    #[test]
    fn drr_focal_and_roi_center_take_words_or_numbers() {
        use crate::stage::drr::{Focal, RoiCenter, RoiMode};
        let c = Config::parse(&format!("{MINIMAL}[drr]\nfocal_px = 1280\nroi_center = \"lungs\"\n")).unwrap();
        assert_eq!((c.drr.focal_px, c.drr.roi_center), (Focal::Px(1280.0), RoiCenter::Mode(RoiMode::Lungs)));
        let c = Config::parse(&format!("{MINIMAL}[drr]\nroi_center = [1.0, -2.5, 30]\n")).unwrap();
        assert_eq!(c.drr.roi_center, RoiCenter::Mm([1.0, -2.5, 30.0]));
        let e = Config::parse(&format!("{MINIMAL}[drr]\nfocal_px = \"wide\"\n")).unwrap_err().to_string();
        assert!(e.contains("line 7") && e.contains("focal_px"), "{e}");
    }

    #[test]
    fn dataset_kinds_need_their_own_keys() {
        let phantom = MINIMAL.replace("kind = \"dicom\"\nroot = \"data\"", "kind = \"phantom\"\ncohort = \"c\"");
        assert!(Config::parse(&phantom).is_ok());
        let e = Config::parse(&MINIMAL.replace("root = \"data\"", "cohort = \"c\"")).unwrap_err().to_string();
        assert!(e.contains("[dataset] cohort is read only by kind = \"phantom\""), "{e}");
        let e = Config::parse(&MINIMAL.replace("root = \"data\"\n", "")).unwrap_err().to_string();
        assert!(e.contains("needs `root`"), "{e}");
        let e = Config::parse(&MINIMAL.replace("\"dicom\"", "\"phantom\"")).unwrap_err().to_string();
        assert!(
            e.contains("line 5") && e.contains("[dataset] root is read only by kind = \"dicom\" or \"lidc\""),
            "{e}"
        );
        let e = Config::parse(&MINIMAL.replace("\"dicom\"\nroot = \"data\"", "\"phantom\"")).unwrap_err().to_string();
        assert!(e.contains("needs `cohort`"), "{e}");
        let e = Config::parse(&MINIMAL.replace("\"dicom\"", "\"nifti\"")).unwrap_err().to_string();
        assert!(e.contains("nifti") && e.contains("line 4"), "{e}");
    }

    #[test]
    fn a_consensus_phantom_is_scored_at_its_own_level() {
        let phantom = MINIMAL.replace("kind = \"dicom\"\nroot = \"data\"", "kind = \"phantom\"\ncohort = \"c\"");
        let consensus = format!("{phantom}\n[dataset.phantom]\nnodule_extent = \"consensus\"\n");
        assert!(Config::parse(&consensus).is_ok());
        assert!(Config::parse(&format!("{consensus}[ingest]\nclevel = 0.5\n")).is_ok());
        let e = Config::parse(&format!("{consensus}[ingest]\nclevel = 0.3\n")).unwrap_err().to_string();
        assert!(e.contains("nodule_extent") && e.contains("clevel = 0.3") && e.contains("clevel = 0.5"), "{e}");
        let readers = consensus.replace("\"consensus\"", "\"readers\"");
        assert!(Config::parse(&format!("{readers}[ingest]\nclevel = 0.3\n")).is_ok());
    }

    #[test]
    fn stage_workers_must_name_stages() {
        let text = MINIMAL.replace("name = \"t\"\n", "name = \"t\"\nstage_workers = { trian = 1 }\n");
        let e = Config::parse(&text).unwrap_err().to_string();
        assert!(e.contains("trian"), "{e}");
    }

    #[test]
    fn cache_remote_takes_object_store_urls_and_names_itself_when_refused() {
        let with = |url: &str| MINIMAL.replace("name = \"t\"\n", &format!("name = \"t\"\ncache_remote = \"{url}\"\n"));
        for url in ["s3://bucket/prefix", "gs://bucket/a/b", "az://container/p", "azure://c/p", "file:///tmp/cache"] {
            let c = Config::parse(&with(url)).unwrap();
            assert_eq!(c.cache_remote(), Some(url));
        }
        assert_eq!(Config::parse(&with("")).unwrap().cache_remote(), None);
        assert_eq!(Config::parse(MINIMAL).unwrap().cache_remote(), None);
        for url in ["ftp://host/x", "bucket/prefix", "memory:///", "s3://KEYID:SECRET@bucket/p", "http://host/x"] {
            let e = Config::parse(&with(url)).unwrap_err().to_string();
            assert!(
                e.contains("line 3") && e.contains("[pipeline] cache_remote") && e.contains("s3://bucket/prefix"),
                "{e}"
            );
            assert!(!e.contains("SECRET"), "{e}");
        }
    }

    #[test]
    fn a_number_outside_its_range_names_the_key_its_line_and_the_range() {
        let cases = [
            ("[drr]\nwidth_px = 100000\n", "[drr] width_px: 100000 is out of range: it takes [8, 8192] (pixels)"),
            ("[train]\nthreads = 100000\n", "[train] threads: 100000 is out of range: it takes [0, 1024]"),
            (
                "[metrics]\nbootstrap_resamples = 0\n",
                "[metrics] bootstrap_resamples: 0 is out of range: it takes [100, 10000000]",
            ),
            ("[select.half_max]\nfraction = 1.0\n", "[select.half_max] fraction: 1 is out of range: it takes (0, 1)"),
            ("[sweep]\npercentiles = [50.0, 101.0]\n", "[sweep] percentiles: 101 is out of range"),
            ("[sweep]\nconnectivity = 8\n", "[sweep] connectivity: 8 is out of range: it takes one of 6, 18, 26"),
            ("[drr]\npose_error_deg = nan\n", "[drr] pose_error_deg: NaN is out of range"),
        ];
        for (table, expected) in cases {
            let e = Config::parse(&format!("{MINIMAL}{table}")).unwrap_err().to_string();
            assert!(e.contains("line 7") && e.contains(expected), "{e}");
        }
        let workers = MINIMAL.replace("name = \"t\"\n", "name = \"t\"\nstage_workers = { train = 5000 }\n");
        let e = Config::parse(&workers).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("[pipeline.stage_workers] train: 5000"), "{e}");
        // The ends of a closed range are valid.
        assert!(Config::parse(&format!("{MINIMAL}[drr]\nwidth_px = 8192\nheight_px = 8\n")).is_ok());
    }

    #[test]
    fn every_numeric_key_has_a_range_that_its_default_lies_in() {
        let c = Config::parse(MINIMAL).unwrap();
        let mut defaults = toml::Table::new();
        let mut put = |name: &str, value: toml::Value| {
            let (table, sub) = name.split_once('.').map_or((name, None), |(t, s)| (t, Some(s)));
            let slot = defaults.entry(table).or_insert_with(|| toml::Value::Table(toml::Table::new()));
            let slot = slot.as_table_mut().unwrap();
            match sub {
                Some(sub) => {
                    slot.insert(sub.to_string(), value);
                }
                None => slot.extend(value.as_table().unwrap().clone()),
            }
        };
        put("pipeline", toml::Value::try_from(toml::toml! { workers = 2 }).unwrap());
        put("dataset.phantom", toml::Value::try_from(crate::phantom::PhantomParams::default()).unwrap());
        put("ingest", toml::Value::try_from(&c.ingest).unwrap());
        put("hu", toml::Value::try_from(&c.hu).unwrap());
        put("drr", toml::Value::try_from(&c.drr).unwrap());
        put("train", toml::Value::try_from(&c.train).unwrap());
        put("grid", toml::Value::try_from(&c.grid).unwrap());
        put("sweep", toml::Value::try_from(&c.sweep).unwrap());
        put("select", toml::Value::try_from(&c.select).unwrap());
        put("metrics", toml::Value::try_from(&c.metrics).unwrap());
        fn numeric_keys(prefix: &str, table: &toml::Table, out: &mut Vec<(String, String)>) {
            for (key, value) in table {
                match value {
                    toml::Value::Table(t) => numeric_keys(&format!("{prefix}.{key}"), t, out),
                    toml::Value::Integer(_) | toml::Value::Float(_) => out.push((prefix.to_string(), key.clone())),
                    toml::Value::Array(a) if a.iter().any(|v| v.is_integer() || v.is_float()) => {
                        out.push((prefix.to_string(), key.clone()))
                    }
                    _ => {}
                }
            }
        }
        let mut keys = Vec::new();
        for (table, value) in &defaults {
            numeric_keys(table, value.as_table().unwrap(), &mut keys);
        }
        // Keys that take a word or a number, whose defaults are words.
        keys.extend([("drr".to_string(), "focal_px".to_string()), ("drr".to_string(), "roi_center".to_string())]);
        assert!(keys.len() > 60, "{keys:?}");
        for (table, key) in &keys {
            assert!(
                ranges::KEY_RANGES.iter().any(|r| r.table == table && r.key == key),
                "[{table}] {key} has no range in stages/config/ranges.rs"
            );
        }
        ranges::check(&defaults, |_| None).expect("the defaults lie in their ranges");
        // The connectivity serialises as a word; its number must be in range too.
        assert!(ranges::check(&toml::from_str("[sweep]\nconnectivity = 26").unwrap(), |_| None).is_ok());
    }

    #[test]
    fn the_ranges_document_is_written_from_the_table() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/config_ranges.md");
        let expected = ranges::markdown();
        if std::env::var_os("UPDATE_DOCS").is_some() {
            std::fs::write(&path, &expected).unwrap();
        }
        let on_disk = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(on_disk == expected, "docs/config_ranges.md is stale: UPDATE_DOCS=1 cargo test --lib config");
    }
}
