//! The `aret-pipe` command line: parses arguments, then calls the library. Nothing else.

use aret_pipe::commands::{self, RunArgs, StatusArgs};
use clap::{Args, CommandFactory, Parser, Subcommand, ValueEnum};
use std::io::Write as _;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "aret-pipe", version, about = "Measure lung nodules in 3D from three X-rays")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the pipeline: compute what is not cached, publish results to out_dir.
    Run {
        /// The pipeline configuration (e.g. pipeline.toml).
        config: PathBuf,
        #[command(flatten)]
        sets: Sets,
        /// Only these patients (comma-separated IDs).
        #[arg(long, value_delimiter = ',')]
        patients: Option<Vec<String>>,
        /// Stop after this stage (and what it needs).
        #[arg(long)]
        until: Option<String>,
        /// Recompute this stage even when cached (repeat or comma-separate for several); `all`
        /// recomputes every stage (those --until keeps).
        #[arg(long, value_delimiter = ',')]
        force: Vec<String>,
        /// Print, per patient and stage, whether it would run and why; run nothing.
        #[arg(long)]
        dry_run: bool,
        #[command(flatten)]
        json: JsonPlan,
        /// Re-hash the input files instead of trusting their sizes and timestamps, and compute
        /// again every result whose manifest records no digest. (Every cached blob is re-hashed
        /// before use, and every manifest checked against its key, on every run.)
        #[arg(long)]
        verify: bool,
        /// Publish independent, writable copies of the results instead of read-only hard links
        /// into the cache: editing one then leaves the cache alone, at the cost of a second copy
        /// of every byte, and each run re-hashes the copies to see they still hold the results.
        #[arg(long)]
        copy: bool,
        /// Run the per-patient stages of shard K of N only (0-based, e.g. `0/4` … `3/4`): a
        /// patient's shard depends only on its ID and N. The cohort stages wait for --gather.
        #[arg(long, conflicts_with_all = ["gather", "shard_from_env"])]
        shard: Option<String>,
        /// The shard of a Slurm array task (SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT) or of
        /// a Kubernetes Indexed Job (JOB_COMPLETION_INDEX, with --shard-count).
        #[arg(long, conflicts_with = "gather")]
        shard_from_env: bool,
        /// The number of shards: for --shard-from-env where the scheduler does not say it, and for
        /// --gather to name the shards of the patients still missing.
        #[arg(long)]
        shard_count: Option<u64>,
        /// Run the cohort stages once every patient's results are cached (by the shards); fails
        /// naming the patients that are not, and the command that computes them.
        #[arg(long)]
        gather: bool,
    },
    /// Show what is cached and what is stale, and why.
    Status {
        config: PathBuf,
        #[command(flatten)]
        sets: Sets,
        #[arg(long, value_delimiter = ',')]
        patients: Option<Vec<String>>,
        #[command(flatten)]
        json: JsonPlan,
        /// Re-hash the input files, and call stale every result whose manifest records no digest.
        #[arg(long)]
        verify: bool,
    },
    /// Delete cache blobs that no manifest references; report the bytes freed.
    ///
    /// It cleans the local cache (`cache_dir`) only: a remote cache (`cache_remote`) is never
    /// read or changed by gc.
    ///
    /// With --prune, first forget every cached stage result that none of the given
    /// configurations uses now (results of old parameters, other presets, other patients), so
    /// their blobs go too. Try --dry-run first: a forgotten result must be computed again.
    Gc {
        /// The configuration whose cache to clean; with --prune, every configuration whose
        /// current results to keep (all sharing one cache).
        #[arg(required = true)]
        configs: Vec<PathBuf>,
        #[command(flatten)]
        sets: Sets,
        /// Keep only the results these configurations use now.
        #[arg(long)]
        prune: bool,
        /// Also forget every result of these stages (comma-separated), e.g. `ingest,hu`: the
        /// CT volumes, the largest part of a cache and seconds to compute again from the DICOM; the
        /// stages after them stay cached, as their bytes come out the same.
        #[arg(long, value_delimiter = ',')]
        forget: Vec<String>,
        /// Report what would be deleted; delete nothing.
        #[arg(long)]
        dry_run: bool,
    },
    /// List the product presets: each one's name and the first comment line of its file.
    Presets {
        /// The folder of presets (`*.toml`).
        #[arg(default_value = "presets")]
        dir: PathBuf,
    },
    /// Print the shell completion script.
    ///
    /// E.g. `aret-pipe completions bash > ~/.local/share/bash-completion/completions/aret-pipe`,
    /// `aret-pipe completions fish > ~/.config/fish/completions/aret-pipe.fish`.
    Completions {
        /// The shell to complete in.
        #[arg(value_enum)]
        shell: clap_complete::Shell,
    },
    /// Write synthetic CT series around a cohort's real LIDC annotations (DICOM + XML + previews).
    Phantom {
        /// The cohort folder: <patient>.scan.json + <patient>.xml per patient.
        #[arg(long, default_value = "tools/cohorts/paper19")]
        cohort: PathBuf,
        /// Export what this configuration's pipeline ingests: its [dataset] cohort and
        /// [dataset.phantom] table (seed, noise, nodule extent), instead of --cohort and --seed.
        #[arg(long, conflicts_with_all = ["seed", "cohort"])]
        config: Option<PathBuf>,
        /// Where to write <patient>/series/*.dcm, <patient>/<patient>.xml and previews.
        #[arg(long)]
        out: PathBuf,
        /// Only these patients (comma-separated IDs).
        #[arg(long, value_delimiter = ',')]
        patients: Option<Vec<String>>,
        /// Seed of the anatomy and noise (the pipeline's [dataset.phantom] seed; default 1).
        #[arg(long)]
        seed: Option<u64>,
    },
    /// Convert MetaImage volumes (.mhd + raw; float, short or uchar) to one OpenVDB file,
    /// one float grid per input: `convert density.mhd uncertainty.mhd out.vdb --class fog --class other`.
    Convert {
        /// The MetaImage headers (each one's ElementDataFile is read from beside it).
        #[arg(required = true, num_args = 1..)]
        inputs: Vec<PathBuf>,
        /// The .vdb file to write.
        output: PathBuf,
        /// Grid names, once per input in order (default: each input's file stem, e.g. `density`).
        #[arg(long)]
        grid: Vec<String>,
        /// What each input's values are, once per input in order: `fog` for a density in [0, 1]
        /// (volume renderers show it as smoke), `other` for anything else (the default).
        #[arg(long, value_enum)]
        class: Vec<ClassArg>,
    },
    /// Write the job files that run a cohort as shards on a cluster's scheduler, then a gather.
    Submit {
        #[command(subcommand)]
        target: SubmitTarget,
    },
    /// Developer entry point: one numeric kernel on MetaImage or JSON files (docs/kernels.md).
    #[command(hide = true)]
    Kernel {
        #[command(subcommand)]
        kernel: aret_pipe::kernel_command::KernelCommand,
    },
}

#[derive(Subcommand)]
enum SubmitTarget {
    /// A Slurm job array of shards (aret-shards.sbatch) and a gather job after it
    /// (aret-gather.sbatch, `afterany`).
    Slurm {
        /// The pipeline configuration.
        config: PathBuf,
        #[command(flatten)]
        shards: SubmitShards,
        /// `#SBATCH --partition`.
        #[arg(long)]
        partition: Option<String>,
        /// `#SBATCH --time`, e.g. 02:00:00.
        #[arg(long)]
        time: Option<String>,
        /// `#SBATCH --mem`, e.g. 8G.
        #[arg(long)]
        mem: Option<String>,
        /// Hand the scripts to sbatch and print the job ids.
        #[arg(long)]
        submit: bool,
    },
    /// A Kubernetes Indexed Job of shards and a gather Job (aret-pipe-jobs.yaml).
    K8s {
        /// The pipeline configuration, relative to the root of the claim.
        config: PathBuf,
        #[command(flatten)]
        shards: SubmitShards,
        /// The container image holding aret-pipe.
        #[arg(long)]
        image: String,
        /// The PersistentVolumeClaim holding the configuration, dataset and cache (mounted at /work).
        #[arg(long)]
        cache_pvc: String,
    },
}

/// How many shards, where the job files go, and whether only to show the shards.
#[derive(Args)]
struct SubmitShards {
    /// How many shards (array tasks).
    #[arg(long)]
    array: u64,
    /// At most M shards at once (Slurm's `--array=0-N%M`, a Job's `parallelism`). Many small
    /// shards, a few at a time, balance the load: a free machine takes the next shard.
    #[arg(long, value_name = "M")]
    max_running: Option<u64>,
    /// The folder the job files are written to.
    #[arg(long, default_value = aret_pipe::submit::SUBMIT_DIR)]
    out: PathBuf,
    /// Print each shard's patients; write nothing.
    #[arg(long)]
    dry_run: bool,
}

/// `--set` of `run`, `status` and `gc`.
#[derive(Args)]
struct Sets {
    /// Set `section.key` (or `section.variant.key`) to VALUE over the configuration, as an edit
    /// of the file would: typed and checked alike, and part of the cache key. Repeatable. VALUE
    /// is TOML (`64`, `[1, 2]`, `"text"`); a bare word is a string: `--set train.model=vm`.
    #[arg(long = "set", value_name = "SECTION.KEY=VALUE")]
    sets: Vec<String>,
}

/// `--json` of `status` and `run --dry-run`.
#[derive(Args)]
struct JsonPlan {
    /// Print the plan as one JSON document instead of the text, and nothing else on stdout
    ///
    /// Its fields (their names are stable):
    ///   command   "status" or "dry-run"
    ///   config    the configuration's path as given
    ///   stages    the stages' names in the graph's order
    ///   rows      one object per unit (a patient, a patient's replica `PATIENT/PART`, or
    ///             `cohort`) and stage, in the text's order, with:
    ///     unit, stage
    ///     status     the status table's cell: "cached", "new" (never run), "stale" (would run),
    ///                "pending" (only after `after`) or "blocked" (its inputs cannot be read)
    ///     cached     true when the cache serves it now
    ///     would_run  true when a run computes it whatever happens upstream
    ///     after      the stage computed before it (for `cohort`, as `PATIENT/STAGE`), or null;
    ///                with would_run false it runs unless that stage's outputs come out unchanged
    ///     reasons    why it would run, or why it cannot (blocked), as the text says; [] if cached
    ///     key        its cache key (64 hex digits) when every input it reads is known, else null
    #[arg(long, verbatim_doc_comment)]
    json: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum ClassArg {
    Fog,
    Other,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run {
            config,
            sets: Sets { sets },
            patients,
            until,
            force,
            dry_run,
            json: JsonPlan { json },
            verify,
            copy,
            shard,
            shard_from_env,
            shard_count,
            gather,
        } => {
            let shard = match (shard, shard_from_env) {
                _ if shard_count.is_some() && !shard_from_env && !gather => {
                    Err(anyhow::anyhow!("--shard-count goes with --shard-from-env or --gather"))
                }
                (Some(text), _) => aret_pipe::shard::Shard::parse(&text).map(Some),
                (None, true) => aret_pipe::shard::Shard::from_env(shard_count, |v| std::env::var(v).ok()).map(Some),
                (None, false) => Ok(None),
            };
            shard.and_then(|shard| {
                let gather = gather.then_some(commands::Gather { shard_count });
                let args = RunArgs { sets, patients, until, force, dry_run, json, verify, copy, shard, gather };
                commands::run(&config, &args)
            })
        }
        Command::Status { config, sets: Sets { sets }, patients, json: JsonPlan { json }, verify } => {
            commands::status(&config, &StatusArgs { sets, patients, verify, json }).map(|table| {
                print!("{table}");
                0
            })
        }
        Command::Gc { configs, sets: Sets { sets }, prune, forget, dry_run } => {
            commands::gc(&configs, &commands::GcArgs { sets, prune, forget, dry_run }).map(|line| {
                println!("{line}");
                0
            })
        }
        Command::Presets { dir } => commands::presets(&dir).map(|list| {
            print!("{list}");
            0
        }),
        Command::Completions { shell } => {
            let script = commands::completions(shell, &mut Cli::command());
            std::io::stdout().write_all(&script).map(|()| 0).map_err(anyhow::Error::from)
        }
        Command::Phantom { cohort, config, out, patients, seed } => {
            let source = match config {
                Some(path) => commands::phantom_source(&path),
                None => {
                    let defaults = aret_pipe::phantom::PhantomParams::default();
                    Ok((cohort, aret_pipe::phantom::PhantomParams { seed: seed.unwrap_or(defaults.seed), ..defaults }))
                }
            };
            source.and_then(|(cohort, params)| commands::phantom(&cohort, &out, patients.as_deref(), &params)).map(
                |report| {
                    print!("{report}");
                    0
                },
            )
        }
        Command::Submit { target } => match target {
            SubmitTarget::Slurm { config, shards, partition, time, mem, submit } => {
                let request = aret_pipe::submit::SlurmRequest {
                    shards: shards.array,
                    max_running: shards.max_running,
                    partition,
                    time,
                    mem,
                };
                aret_pipe::submit::slurm(&config, &request, &shards.out, submit, shards.dry_run)
            }
            SubmitTarget::K8s { config, shards, image, cache_pvc } => {
                let request = aret_pipe::submit::KubernetesRequest {
                    shards: shards.array,
                    max_running: shards.max_running,
                    image: &image,
                    claim: &cache_pvc,
                };
                aret_pipe::submit::kubernetes(&config, &request, &shards.out, shards.dry_run)
            }
        }
        .map(|report| {
            print!("{report}");
            0
        }),
        Command::Convert { inputs, output, grid, class } => {
            let classes: Vec<_> = class
                .into_iter()
                .map(|c| match c {
                    ClassArg::Fog => aret_pipe::formats::vdb::GridClass::FogVolume,
                    ClassArg::Other => aret_pipe::formats::vdb::GridClass::Unknown,
                })
                .collect();
            commands::convert(&inputs, &grid, &classes, &output).map(|report| {
                print!("{report}");
                0
            })
        }
        Command::Kernel { kernel } => aret_pipe::kernel_command::run(&kernel).map(|summary| {
            print!("{summary}");
            0
        }),
    };
    match result {
        Ok(code) => ExitCode::from(code as u8),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
