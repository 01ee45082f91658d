//! `aret-pipe submit`: the job files that run a cohort on a cluster's own scheduler, as shards
//! ([`crate::shard`]) over one shared cache, then a gather. Slurm gets an array script and a
//! gather script that runs after the array (`afterany`: the gather itself says which patients
//! are missing); Kubernetes gets an Indexed Job and a gather Job. Nothing is scheduled here
//! except by `sbatch` itself with `--submit`.

use crate::config::Config;
use crate::dataset;
use crate::engine::files::write_atomic;
use anyhow::{bail, Context as _};
use std::path::{Path, PathBuf};
use std::process::Command;

/// What a Slurm array asks for, each passed to `#SBATCH` as given.
#[derive(Debug, Clone, Default)]
pub struct SlurmRequest {
    pub shards: u64,
    /// At most this many shards at once (Slurm's array throttle, `%M`); `None`: all.
    pub max_running: Option<u64>,
    pub partition: Option<String>,
    pub time: Option<String>,
    pub mem: Option<String>,
}

/// How many shards run at once: `max_running` (at least 1, at most `shards`), else all of them.
/// Many small shards a few at a time balance the load across machines: each machine takes the
/// next shard when it is free, where one big shard a machine waits for the slowest.
fn max_running(shards: u64, max_running: Option<u64>) -> anyhow::Result<u64> {
    if shards == 0 {
        bail!("--array must be at least 1");
    }
    match max_running {
        Some(0) => bail!("--max-running must be at least 1"),
        Some(m) => Ok(m.min(shards)),
        None => Ok(shards),
    }
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

/// The folder `submit` writes the job files into unless told otherwise.
pub const SUBMIT_DIR: &str = "submit";
/// The Slurm array script of the shards, in the submit folder.
pub const SLURM_SHARDS_SCRIPT: &str = "aret-shards.sbatch";
/// The Slurm script of the gather, in the submit folder.
pub const SLURM_GATHER_SCRIPT: &str = "aret-gather.sbatch";
/// The Kubernetes Jobs (the shards' Indexed Job, then the gather Job), in the submit folder.
pub const K8S_JOBS: &str = "aret-pipe-jobs.yaml";

/// Where Slurm writes array task K's output: one file per job and task (`%A` the array's job id,
/// `%a` the task), so a task submitted again does not overwrite the log of the run it replaces.
pub const SLURM_SHARD_LOG: &str = "shard-%A_%a.out";
/// Where Slurm writes the gather's output, one file per gather job (`%j`).
pub const SLURM_GATHER_LOG: &str = "gather-%j.out";

/// The array script and the gather script of a Slurm run.
pub fn slurm_scripts(request: &SlurmRequest, launch: &Launch, logs: &Path) -> anyhow::Result<[String; 2]> {
    let running = max_running(request.shards, request.max_running)?;
    let (program, config, workdir) = (quoted(launch.program)?, quoted(launch.config)?, quoted(launch.workdir)?);
    if logs.to_str().is_none_or(|l| l.contains(char::is_whitespace) || l.contains('%')) {
        bail!("{}: Slurm's --output takes a path without spaces or `%`", logs.display());
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
        head(
            "aret-pipe-shards",
            &match request.max_running {
                Some(_) => format!("#SBATCH --array=0-{}%{running}\n", request.shards - 1),
                None => format!("#SBATCH --array=0-{}\n", request.shards - 1),
            },
            SLURM_SHARD_LOG
        ),
        n = request.shards
    );
    let gather = format!(
        "{}# After every shard (afterany): the cohort stages, or the list of patients still missing.\n\
         exec {program} run {config} --gather --shard-count {n}\n",
        head("aret-pipe-gather", "", SLURM_GATHER_LOG),
        n = request.shards
    );
    Ok([shards, gather])
}

/// What a Kubernetes run mounts and runs.
pub struct KubernetesRequest<'a> {
    pub shards: u64,
    /// At most this many pods at once (the Job's `parallelism`); `None`: all.
    pub max_running: Option<u64>,
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
    let running = max_running(request.shards, request.max_running)?;
    let q = |s: &str| serde_json::to_string(s).expect("a string serialises");
    let job = |name: &str, args: &[&str], indexed: bool| {
        let spec = if indexed {
            format!(
                "  completionMode: Indexed\n  completions: {}\n  parallelism: {running}\n  backoffLimitPerIndex: 1\n",
                request.shards
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
        job("aret-pipe-gather", &["run", config, "--gather", "--shard-count", &n], false)
    ))
}

/// `sbatch` the array, then the gather after it; returns both job ids. When the gather is refused
/// the error names the array's job id, which is queued by then.
fn sbatch(shards_script: &Path, gather_script: &Path) -> anyhow::Result<[String; 2]> {
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
    let after = format!("--dependency=afterany:{array}");
    let gather = run(&[&after], gather_script).with_context(|| {
        format!(
            "the shards are queued as job {array} but the gather is not: submit it with `sbatch {after} {}`, \
             or cancel the shards with `scancel {array}`",
            gather_script.display()
        )
    })?;
    Ok([array, gather])
}

/// The absolute form of `path` (the tasks may start anywhere).
fn absolute(path: &Path) -> anyhow::Result<PathBuf> {
    std::fs::canonicalize(path).with_context(|| format!("{} does not exist", path.display()))
}

/// How each shard of `shards` splits the configuration's patients, a line each.
fn shard_lines(config: &Config, shards: u64) -> anyhow::Result<String> {
    let units = dataset::units(config, None)?;
    let mut text = String::new();
    for index in 0..shards {
        let shard = crate::shard::Shard { index, count: shards };
        let ids: Vec<&str> = units.iter().filter(|u| shard.holds(&u.id)).map(|u| u.id.as_str()).collect();
        text.push_str(&format!("shard {index}/{shards}: {} patients: {}\n", ids.len(), ids.join(", ")));
    }
    Ok(text)
}

/// `aret-pipe submit slurm`: writes the array and gather scripts into `out` (with `dry_run`,
/// only prints the shards), and with `submit` hands them to `sbatch`.
pub fn slurm(
    config_path: &Path,
    request: &SlurmRequest,
    out: &Path,
    submit: bool,
    dry_run: bool,
) -> anyhow::Result<String> {
    let config = Config::load(config_path)?;
    let mut report = shard_lines(&config, request.shards.max(1))?;
    if dry_run {
        return Ok(report);
    }
    std::fs::create_dir_all(out.join("logs")).with_context(|| format!("creating {}", out.display()))?;
    let config_abs = absolute(config_path)?;
    let program = std::env::current_exe().context("finding this aret-pipe")?;
    let workdir = absolute(Path::new("."))?;
    let launch = Launch { program: &program, config: &config_abs, workdir: &workdir };
    let logs = absolute(&out.join("logs"))?;
    let [shards, gather] = slurm_scripts(request, &launch, &logs)?;
    let (shards_path, gather_path) = (out.join(SLURM_SHARDS_SCRIPT), out.join(SLURM_GATHER_SCRIPT));
    write_atomic(&shards_path, shards.as_bytes(), false)?;
    write_atomic(&gather_path, gather.as_bytes(), false)?;
    report.push_str(&format!(
        "wrote {} (task K: `aret-pipe run {} --shard K/{}`) and {} (then `--gather`)\n",
        shards_path.display(),
        config_path.display(),
        request.shards,
        gather_path.display()
    ));
    if submit {
        let [array, gather] = sbatch(&shards_path, &gather_path)?;
        report.push_str(&format!(
            "submitted: the shards as job {array}, the gather as job {gather} (afterany:{array})\n\
             logs: {logs}/{} for task K, {logs}/{}\n",
            SLURM_SHARD_LOG.replace("%A", &array).replace("%a", "K"),
            SLURM_GATHER_LOG.replace("%j", &gather),
            logs = logs.display(),
        ));
    } else {
        report.push_str(&format!(
            "submit with: jid=$(sbatch --parsable {}) && sbatch --dependency=afterany:$jid {}\n\
             logs: {logs}/{} for task K of array job J, {logs}/{} for gather job G\n",
            shards_path.display(),
            gather_path.display(),
            SLURM_SHARD_LOG.replace("%A", "J").replace("%a", "K"),
            SLURM_GATHER_LOG.replace("%j", "G"),
            logs = logs.display(),
        ));
    }
    Ok(report)
}

/// `aret-pipe submit k8s`: writes the Indexed Job and the gather Job into `out`/aret-pipe-jobs.yaml
/// (with `dry_run`, only prints the shards). The configuration's path is taken as it lies in the
/// claim, whose root is this folder's layout.
pub fn kubernetes(
    config_path: &Path,
    request: &KubernetesRequest,
    out: &Path,
    dry_run: bool,
) -> anyhow::Result<String> {
    if config_path.is_absolute() {
        bail!(
            "{}: give the configuration's path relative to the root of the claim (mounted at {} in the pods), \
             and run submit from that root",
            config_path.display(),
            K8S_MOUNT
        );
    }
    let config = Config::load(config_path)?;
    let mut report = shard_lines(&config, request.shards.max(1))?;
    if dry_run {
        return Ok(report);
    }
    let in_claim = config_path.to_str().with_context(|| format!("{} is not UTF-8", config_path.display()))?;
    let yaml = kubernetes_manifests(request, in_claim)?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let path = out.join(K8S_JOBS);
    write_atomic(&path, yaml.as_bytes(), false)?;
    report.push_str(&format!(
        "wrote {}: pod K runs `aret-pipe run {in_claim} --shard K/{}`; then the gather Job runs `--gather`\n",
        path.display(),
        request.shards
    ));
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slurm_scripts_run_each_shard_then_the_gather_with_quoted_paths() {
        let request = SlurmRequest {
            shards: 4,
            max_running: None,
            partition: Some("debug".into()),
            time: Some("01:00:00".into()),
            mem: None,
        };
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
        assert!(shards.contains("#SBATCH --output=/c/logs/shard-%A_%a.out\n"), "{shards}");
        assert!(gather.contains("#SBATCH --output=/c/logs/gather-%j.out\n"), "{gather}");
        assert!(slurm_scripts(&request, &launch, Path::new("/c/100%")).is_err(), "% is Slurm's pattern mark");
        let throttled = SlurmRequest { shards: 256, max_running: Some(32), ..request.clone() };
        let [shards, _] = slurm_scripts(&throttled, &launch, Path::new("/c/logs")).unwrap();
        assert!(shards.contains("#SBATCH --array=0-255%32\n") && shards.contains("--shard-count 256\n"), "{shards}");
        let never = SlurmRequest { max_running: Some(0), ..request.clone() };
        assert!(slurm_scripts(&never, &launch, Path::new("/c/logs"))
            .unwrap_err()
            .to_string()
            .contains("--max-running"));
        let bad = SlurmRequest { time: Some("1 h".into()), ..request };
        assert!(slurm_scripts(&bad, &launch, Path::new("/c/logs")).unwrap_err().to_string().contains("--time"));
    }
}
