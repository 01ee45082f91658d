//! `aret-pipe submit`: the job files that run a cohort on a cluster's own scheduler, as shards
//! ([`crate::shard`]) over one shared cache, then a gather. Slurm gets an array script and a
//! gather script that runs after the array (`afterany`: the gather itself says which patients
//! are missing); Kubernetes gets an Indexed Job and a gather Job. Nothing is scheduled here
//! except by `sbatch` itself with `--submit`.

use anyhow::{bail, Context as _};
use std::path::{Path, PathBuf};
use std::process::Command;

/// What a Slurm array asks for, each passed to `#SBATCH` as given.
#[derive(Debug, Clone, Default)]
pub struct SlurmRequest {
    pub shards: u64,
    pub partition: Option<String>,
    pub time: Option<String>,
    pub mem: Option<String>,
}

/// Where the tasks find the tool and the configuration.
pub struct Launch<'a> {
    /// The `aret-pipe` the tasks run.
    pub program: &'a Path,
    /// The configuration, as the tasks name it.
    pub config: &'a Path,
    /// The folder the tasks run in (relative paths of the configuration are taken from its own
    /// folder whatever this is).
    pub workdir: &'a Path,
}

fn quoted(path: &Path) -> anyhow::Result<String> {
    let text = path.to_str().with_context(|| format!("{} is not UTF-8: name it otherwise", path.display()))?;
    Ok(shlex::try_quote(text).with_context(|| format!("{text} cannot be quoted for a shell"))?.into_owned())
}

/// The array script and the gather script of a Slurm run.
pub fn slurm_scripts(request: &SlurmRequest, launch: &Launch, logs: &Path) -> anyhow::Result<[String; 2]> {
    if request.shards == 0 {
        bail!("--array must be at least 1");
    }
    let (program, config, workdir) = (quoted(launch.program)?, quoted(launch.config)?, quoted(launch.workdir)?);
    if logs.to_str().is_none_or(|l| l.contains(char::is_whitespace)) {
        bail!("{}: Slurm's --output takes a path without spaces", logs.display());
    }
    let mut directives = String::new();
    for (flag, value) in [("partition", &request.partition), ("time", &request.time), ("mem", &request.mem)] {
        if let Some(value) = value {
            if value.contains(char::is_whitespace) || value.is_empty() {
                bail!("--{flag} `{value}`: a Slurm value has no spaces");
            }
            directives.push_str(&format!("#SBATCH --{flag}={value}\n"));
        }
    }
    let head = |name: &str, extra: &str, log: &str| {
        format!(
            "#!/bin/bash\n#SBATCH --job-name={name}\n{extra}{directives}#SBATCH --output={}/{log}\nset -euo pipefail\ncd {workdir}\n",
            logs.display()
        )
    };
    let shards = format!(
        "{}# Task K of the array computes shard K of {n}: the per-patient stages of its patients.\n\
         exec {program} run {config} --shard-from-env --shard-count {n}\n",
        head("aret-pipe-shards", &format!("#SBATCH --array=0-{}\n", request.shards - 1), "shard-%a.out"),
        n = request.shards
    );
    let gather = format!(
        "{}# After every shard (afterany): the cohort stages, or the list of patients still missing.\n\
         exec {program} run {config} --gather\n",
        head("aret-pipe-gather", "", "gather.out")
    );
    Ok([shards, gather])
}

/// What a Kubernetes run mounts and runs.
pub struct KubernetesRequest<'a> {
    pub shards: u64,
    pub image: &'a str,
    /// The PersistentVolumeClaim holding the configuration, the dataset and the cache, mounted
    /// at [`K8S_MOUNT`] where the tasks run.
    pub claim: &'a str,
}

/// Where the claim is mounted in every pod, and the tasks' working folder.
pub const K8S_MOUNT: &str = "/work";

/// The Indexed Job of the shards and the gather Job, as one YAML stream. `config` is the
/// configuration's path inside the claim.
pub fn kubernetes_manifests(request: &KubernetesRequest, config: &str) -> anyhow::Result<String> {
    if request.shards == 0 {
        bail!("--array must be at least 1");
    }
    let q = |s: &str| serde_json::to_string(s).expect("a string serialises");
    let job = |name: &str, args: &[&str], indexed: bool| {
        let spec = if indexed {
            format!(
                "  completionMode: Indexed\n  completions: {n}\n  parallelism: {n}\n  backoffLimitPerIndex: 1\n",
                n = request.shards
            )
        } else {
            "  backoffLimit: 1\n".to_string()
        };
        let args: Vec<String> = args.iter().map(|a| q(a)).collect();
        format!(
            "apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: {name}\nspec:\n{spec}  template:\n    spec:\n      \
             restartPolicy: Never\n      containers:\n        - name: aret-pipe\n          image: {image}\n          \
             workingDir: {mount}\n          command: [\"aret-pipe\"]\n          args: [{args}]\n          \
             volumeMounts:\n            - name: cohort\n              mountPath: {mount}\n      volumes:\n        \
             - name: cohort\n          persistentVolumeClaim:\n            claimName: {claim}\n",
            name = q(name),
            image = q(request.image),
            mount = q(K8S_MOUNT),
            args = args.join(", "),
            claim = q(request.claim),
        )
    };
    let n = request.shards.to_string();
    Ok(format!(
        "# The shards: pod K (JOB_COMPLETION_INDEX) computes shard K of {n}.\n{}---\n\
         # The gather: apply it once the shards' Job has completed (kubectl wait --for=condition=complete).\n{}",
        job("aret-pipe-shards", &["run", config, "--shard-from-env", "--shard-count", &n], true),
        job("aret-pipe-gather", &["run", config, "--gather"], false)
    ))
}

/// `sbatch` the array, then the gather after it; returns both job ids.
pub fn sbatch(shards_script: &Path, gather_script: &Path) -> anyhow::Result<[String; 2]> {
    let run = |args: &[&str], script: &Path| -> anyhow::Result<String> {
        let out = Command::new("sbatch")
            .arg("--parsable")
            .args(args)
            .arg(script)
            .output()
            .context("running sbatch (is this a Slurm login node?)")?;
        if !out.status.success() {
            bail!("sbatch {} failed: {}", script.display(), String::from_utf8_lossy(&out.stderr).trim());
        }
        // `--parsable` prints "jobid" or "jobid;cluster".
        let text = String::from_utf8_lossy(&out.stdout);
        Ok(text.trim().split(';').next().unwrap_or_default().to_string())
    };
    let array = run(&[], shards_script)?;
    let gather = run(&[&format!("--dependency=afterany:{array}")], gather_script)?;
    Ok([array, gather])
}

/// The absolute form of `path` (the tasks may start anywhere).
pub fn absolute(path: &Path) -> anyhow::Result<PathBuf> {
    std::fs::canonicalize(path).with_context(|| format!("{} does not exist", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slurm_scripts_run_each_shard_then_the_gather_with_quoted_paths() {
        let request =
            SlurmRequest { shards: 4, partition: Some("debug".into()), time: Some("01:00:00".into()), mem: None };
        let launch = Launch {
            program: Path::new("/opt/aret pipe/aret-pipe"),
            config: Path::new("/c/p.toml"),
            workdir: Path::new("/c"),
        };
        let [shards, gather] = slurm_scripts(&request, &launch, Path::new("/c/logs")).unwrap();
        assert!(shards.starts_with("#!/bin/bash\n#SBATCH --job-name=aret-pipe-shards\n#SBATCH --array=0-3\n"));
        assert!(shards.contains("#SBATCH --partition=debug\n#SBATCH --time=01:00:00\n") && !shards.contains("--mem"));
        assert!(shards.contains("exec '/opt/aret pipe/aret-pipe' run /c/p.toml --shard-from-env --shard-count 4\n"));
        assert!(gather.contains("--gather") && !gather.contains("--array"), "{gather}");
        let bad = SlurmRequest { time: Some("1 h".into()), ..request };
        assert!(slurm_scripts(&bad, &launch, Path::new("/c/logs")).unwrap_err().to_string().contains("--time"));
    }
}
