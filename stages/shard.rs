//! Cohorts over many machines: `run --shard K/N` computes the per-patient stages of the patients
//! in shard K of N, and `run --gather` the cohort stages once every patient is cached. A
//! patient's shard depends only on its ID and N (a hash of the ID), so adding patients moves no
//! patient already placed, and each shard holds about 1/N of the cohort.

use anyhow::{bail, Context as _};

/// Shard `index` of `count` (0-based: `0/4` … `3/4`, as Slurm arrays `--array=0-3` and
/// Kubernetes Indexed Jobs number their tasks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

/// The variables a scheduler sets for an array task: its index, and (Slurm) the array's size.
const SLURM_INDEX: &str = "SLURM_ARRAY_TASK_ID";
const SLURM_COUNT: &str = "SLURM_ARRAY_TASK_COUNT";
const K8S_INDEX: &str = "JOB_COMPLETION_INDEX";

impl Shard {
    /// `K/N` with 0 ≤ K < N.
    pub fn parse(text: &str) -> anyhow::Result<Shard> {
        let (k, n) = text.split_once('/').with_context(|| format!("--shard {text}: write K/N, e.g. 0/4"))?;
        let number =
            |s: &str| s.trim().parse::<u64>().with_context(|| format!("--shard {text}: `{s}` is not a number"));
        Shard::new(number(k)?, number(n)?).with_context(|| format!("--shard {text}"))
    }

    fn new(index: u64, count: u64) -> anyhow::Result<Shard> {
        if count == 0 || index >= count {
            bail!("the shard index must lie in 0..{count} (0-based), and there must be at least one shard");
        }
        Ok(Shard { index, count })
    }

    /// The shard a scheduler's array task stands for: Slurm's `SLURM_ARRAY_TASK_ID` (with
    /// `SLURM_ARRAY_TASK_COUNT`, or `count`) or Kubernetes' `JOB_COMPLETION_INDEX` (with `count`).
    pub fn from_env(count: Option<u64>, var: impl Fn(&str) -> Option<String>) -> anyhow::Result<Shard> {
        let read = |name: &str| -> anyhow::Result<Option<u64>> {
            var(name)
                .map(|v| v.trim().parse::<u64>().with_context(|| format!("{name}={v} is not a number")))
                .transpose()
        };
        let (index, from) = match (read(SLURM_INDEX)?, read(K8S_INDEX)?) {
            (Some(i), _) => (i, SLURM_INDEX),
            (None, Some(i)) => (i, K8S_INDEX),
            (None, None) => bail!(
                "--shard-from-env: neither {SLURM_INDEX} (a Slurm array task) nor {K8S_INDEX} (a Kubernetes \
                 Indexed Job) is set; give the shard as --shard K/N"
            ),
        };
        let count = match (count, read(SLURM_COUNT)?) {
            (Some(n), _) => n,
            (None, Some(n)) if from == SLURM_INDEX => n,
            _ => bail!("--shard-from-env: {from} gives the index; give the number of shards with --shard-count N"),
        };
        Shard::new(index, count).with_context(|| format!("--shard-from-env ({from})"))
    }

    /// Whether `patient` is in this shard.
    pub fn holds(&self, patient: &str) -> bool {
        shard_of(patient, self.count) == self.index
    }
}

/// The shard of `count` that `patient` falls in: the first 8 bytes of the blake3 hash of its
/// ID, modulo `count`.
pub fn shard_of(patient: &str, count: u64) -> u64 {
    let hash = blake3::hash(patient.as_bytes());
    let first: [u8; 8] = hash.as_bytes()[..8].try_into().expect("a blake3 hash has 32 bytes");
    u64::from_le_bytes(first) % count
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn every_patient_falls_in_exactly_one_shard_about_evenly_and_stays_there() {
        let ids: Vec<String> = (1..=1010).map(|i| format!("LIDC-IDRI-{i:04}")).collect();
        let shards: Vec<Shard> = (0..8).map(|k| Shard { index: k, count: 8 }).collect();
        for id in &ids {
            assert_eq!(shards.iter().filter(|s| s.holds(id)).count(), 1, "{id}");
        }
        let sizes: Vec<usize> = shards.iter().map(|s| ids.iter().filter(|id| s.holds(id)).count()).collect();
        // 1,010 / 8 = 126 a shard; a hash keeps each within a few standard deviations (±11).
        assert!(sizes.iter().all(|&n| (90..=165).contains(&n)), "{sizes:?}");
        // A patient's shard depends only on its ID and N: the first hundred keep theirs when the
        // rest are added.
        let first: HashMap<&String, u64> = ids[..100].iter().map(|id| (id, shard_of(id, 8))).collect();
        assert!(first.iter().all(|(id, &k)| shard_of(id, 8) == k));
    }

    #[test]
    fn shards_parse_from_the_command_line_and_the_schedulers_variables() {
        assert_eq!(Shard::parse("2/4").unwrap(), Shard { index: 2, count: 4 });
        for bad in ["4/4", "1/0", "a/4", "2", "-1/4"] {
            assert!(Shard::parse(bad).is_err(), "{bad}");
        }
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |name: &str| pairs.iter().find(|(k, _)| *k == name).map(|(_, v)| v.to_string())
        };
        let slurm = env(&[("SLURM_ARRAY_TASK_ID", "3"), ("SLURM_ARRAY_TASK_COUNT", "5")]);
        assert_eq!(Shard::from_env(None, slurm).unwrap(), Shard { index: 3, count: 5 });
        let k8s = env(&[("JOB_COMPLETION_INDEX", "1")]);
        assert_eq!(Shard::from_env(Some(2), k8s).unwrap(), Shard { index: 1, count: 2 });
        let e = Shard::from_env(None, env(&[("JOB_COMPLETION_INDEX", "1")])).unwrap_err().to_string();
        assert!(e.contains("--shard-count"), "{e}");
        let e = Shard::from_env(Some(2), env(&[])).unwrap_err().to_string();
        assert!(e.contains("SLURM_ARRAY_TASK_ID") && e.contains("JOB_COMPLETION_INDEX"), "{e}");
        assert!(Shard::from_env(Some(2), env(&[("JOB_COMPLETION_INDEX", "2")])).is_err());
    }
}
