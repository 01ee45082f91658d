//! `aret-pipe kernel …`: one numeric kernel of the sweep/select stages on files, for
//! developers and for the cross-checks in `tests/py` (scipy, cc3d, numpy, trimesh, pyvista,
//! pymeshlab read what this writes). Hidden from `--help`: it is a test entry point, not part
//! of the pipeline. Inputs and outputs are MetaImage (`.mhd` + `.raw`); a mask is MET_UCHAR,
//! non-zero meaning set. A JSON summary goes to stdout. `statistics` instead reads paired
//! samples as JSON and prints every cohort statistic of them. The image filters (`gaussian`,
//! `blob`, `hessian-blob`, `edt`, `otsu`, `fill-holes`) take the spacing from the header. See `docs/kernels.md`.

use crate::formats::{mhd, obj};
use crate::kernels::components::{label, Connectivity};
use crate::kernels::statistics::{self as st, StatisticsError};
use crate::kernels::{filters, marching_cubes, mesh, morphology, stats};
use crate::volume::Volume;
use anyhow::{bail, Context as _};
use clap::Subcommand;
use serde_json::json;
use std::path::{Path, PathBuf};

#[derive(Debug, Subcommand)]
pub enum KernelCommand {
    /// Connected components: labels (MET_UINT, 0 = background, numbered as scipy.ndimage.label)
    /// to OUT; prints {"count", "sizes"}.
    Components {
        mask: PathBuf,
        out: PathBuf,
        /// 6, 18 or 26.
        #[arg(long, default_value_t = 26)]
        connectivity: u32,
        /// Drop components with fewer voxels (then renumber).
        #[arg(long, default_value_t = 0)]
        min_voxels: usize,
    },
    /// Binary dilation with the ball of integer radius R (border value 0, as scipy).
    Dilate {
        mask: PathBuf,
        out: PathBuf,
        #[arg(long, default_value_t = 2)]
        radius: usize,
    },
    /// Binary erosion with the ball of integer radius R (border value 0, as scipy).
    Erode {
        mask: PathBuf,
        out: PathBuf,
        #[arg(long, default_value_t = 2)]
        radius: usize,
    },
    /// Binary closing with the ball of radius R on the mask zero-padded by R, cropped back.
    Close {
        mask: PathBuf,
        out: PathBuf,
        #[arg(long, default_value_t = 2)]
        radius: usize,
    },
    /// numpy's linear percentiles of every value of a MET_DOUBLE or MET_FLOAT volume; prints
    /// {"percentiles", "values"}.
    Percentiles {
        values: PathBuf,
        /// Comma-separated percentiles in [0, 100].
        #[arg(long, value_delimiter = ',', required = true)]
        p: Vec<f64>,
    },
    /// Marching cubes of a mask (closed, outward, patient mm) to a Wavefront OBJ; prints
    /// {"vertices", "triangles", "enclosed_volume_mm3", "voxel_volume_mm3", "closed_and_oriented"}.
    Mesh {
        mask: PathBuf,
        out: PathBuf,
        /// Write per-vertex normals (`vn`) too.
        #[arg(long)]
        normals: bool,
    },
    /// scipy.ndimage.gaussian_filter (mode "nearest", truncate 4) of a MET_FLOAT volume with
    /// σ = SIGMA_MM on every axis (σ/spacing voxels); MET_FLOAT out. Prints {"voxels"}.
    Gaussian {
        values: PathBuf,
        out: PathBuf,
        #[arg(long)]
        sigma_mm: f64,
    },
    /// The scale-normalised negative Laplacian of Gaussian at scale S_MM of a MET_FLOAT volume
    /// (kernels::filters::blob_response); MET_FLOAT out. Prints {"voxels"}.
    Blob {
        values: PathBuf,
        out: PathBuf,
        #[arg(long)]
        s_mm: f64,
    },
    /// The scale-normalised Hessian blob response s²·max(0, −λ₁) at scale S_MM of a MET_FLOAT
    /// volume (kernels::filters::hessian_blob_response); MET_FLOAT out. Prints {"voxels"}.
    HessianBlob {
        values: PathBuf,
        out: PathBuf,
        #[arg(long)]
        s_mm: f64,
    },
    /// Euclidean distance in mm from every set voxel to the nearest unset one
    /// (scipy.ndimage.distance_transform_edt with the header's spacing); MET_DOUBLE out, +inf
    /// everywhere when no voxel is unset. Prints {"voxels", "max_mm"} (null when infinite).
    Edt { mask: PathBuf, out: PathBuf },
    /// Otsu's threshold (skimage.filters.threshold_otsu, 256 bins) of every value of a
    /// MET_FLOAT volume; prints {"threshold"}, null without two distinct finite values.
    Otsu { values: PathBuf },
    /// scipy.ndimage.binary_fill_holes (4-connectivity) on every slice perpendicular to AXIS
    /// (0 = x, 1 = y, 2 = z). Prints {"voxels"}.
    FillHoles {
        mask: PathBuf,
        out: PathBuf,
        #[arg(long)]
        axis: usize,
    },
    /// The cohort statistics of paired samples read from a JSON file (`-` for stdin):
    /// {"x": [...], "y": [...]} (x is the prediction, y the truth). Prints every statistic of
    /// kernels::statistics; one that is undefined for this input is {"error": "..."}.
    Statistics {
        input: PathBuf,
        #[arg(long, default_value_t = 10_000)]
        resamples: usize,
        #[arg(long, default_value_t = 0.95)]
        confidence: f64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
}

/// Runs `command`; returns the JSON summary to print.
pub fn run(command: &KernelCommand) -> anyhow::Result<String> {
    let summary = match command {
        KernelCommand::Components { mask, out, connectivity, min_voxels } => {
            let connectivity = Connectivity::try_from(*connectivity)?;
            let m = read_mask(mask)?;
            let c = label(&m.data, m.geometry.dims, connectivity).without_small(*min_voxels);
            write_volume(out, &Volume { geometry: m.geometry, data: c.labels.clone() })?;
            json!({ "count": c.count(), "sizes": c.sizes })
        }
        KernelCommand::Dilate { mask, out, radius } => morph(mask, out, |m, d| morphology::dilate(m, d, *radius))?,
        KernelCommand::Erode { mask, out, radius } => morph(mask, out, |m, d| morphology::erode(m, d, *radius))?,
        KernelCommand::Close { mask, out, radius } => morph(mask, out, |m, d| morphology::close(m, d, *radius))?,
        KernelCommand::Percentiles { values, p } => {
            let v = read_values(values)?;
            json!({ "percentiles": p, "values": stats::percentiles(&v, p)? })
        }
        KernelCommand::Mesh { mask, out, normals } => {
            let m = read_mask(mask)?;
            let surface = marching_cubes::mesh_mask(&m.data, &m.geometry);
            let volume = mesh::enclosed_volume_mm3(&surface);
            let voxels = m.data.iter().filter(|&&v| v).count() as f64;
            let voxel_volume = voxels * m.geometry.spacing_mm.iter().product::<f64>();
            let vertex_normals = normals.then(|| mesh::vertex_normals(&surface));
            let comment = format!("enclosed volume {volume} mm³; voxel volume {voxel_volume} mm³");
            let text = obj::encode(&surface.vertices, vertex_normals.as_deref(), &surface.triangles, &[&comment]);
            std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
            json!({
                "vertices": surface.vertices.len(),
                "triangles": surface.triangles.len(),
                "enclosed_volume_mm3": volume,
                "voxel_volume_mm3": voxel_volume,
                "closed_and_oriented": mesh::check_edges(&surface).is_closed_and_oriented(),
            })
        }
        KernelCommand::Gaussian { values, out, sigma_mm } => {
            filter(values, out, |v, d, s| filters::gaussian_mm(v, d, s, *sigma_mm))?
        }
        KernelCommand::Blob { values, out, s_mm } => {
            filter(values, out, |v, d, s| filters::blob_response(v, d, s, *s_mm))?
        }
        KernelCommand::HessianBlob { values, out, s_mm } => {
            filter(values, out, |v, d, s| filters::hessian_blob_response(v, d, s, *s_mm))?
        }
        KernelCommand::Edt { mask, out } => {
            let m = read_mask(mask)?;
            let d = filters::distance_inside_mm(&m.data, m.geometry.dims, m.geometry.spacing_mm);
            let max = d.iter().copied().fold(0.0, f64::max);
            write_volume(out, &Volume { geometry: m.geometry, data: d })?;
            json!({ "voxels": m.data.iter().filter(|&&v| v).count(), "max_mm": max.is_finite().then_some(max) })
        }
        KernelCommand::Otsu { values } => {
            let v = read_floats(values)?;
            json!({ "threshold": filters::otsu_threshold(&v.data).map(f64::from) })
        }
        KernelCommand::FillHoles { mask, out, axis } => {
            anyhow::ensure!(*axis < 3, "--axis must be 0 (x), 1 (y) or 2 (z), got {axis}");
            morph(mask, out, |m, d| filters::fill_holes_per_slice(m, d, *axis))?
        }
        KernelCommand::Statistics { input, resamples, confidence, seed } => {
            statistics(input, *resamples, *confidence, *seed)?
        }
    };
    Ok(format!("{summary}\n"))
}

/// Every statistic of `kernels::statistics` on the pairs in `input`, each as its value or
/// {"error"}: the cross-check compares each with scipy, and the errors with scipy's nan.
fn statistics(input: &Path, resamples: usize, confidence: f64, seed: u64) -> anyhow::Result<serde_json::Value> {
    #[derive(serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Pairs {
        x: Vec<f64>,
        y: Vec<f64>,
    }
    let text = if input == Path::new("-") {
        std::io::read_to_string(std::io::stdin()).context("reading stdin")?
    } else {
        std::fs::read_to_string(input).with_context(|| format!("reading {}", input.display()))?
    };
    let Pairs { x, y } = serde_json::from_str(&text).with_context(|| format!("parsing {}", input.display()))?;
    let or_error =
        |r: Result<serde_json::Value, StatisticsError>| r.unwrap_or_else(|e| json!({ "error": e.to_string() }));
    let correlation = |c: st::Correlation| json!({ "r": c.r, "p": c.p_two_sided });
    let ci = |c: st::BootstrapCi| json!({ "lo": c.lo, "hi": c.hi, "undefined": c.undefined });
    let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let r_of = |x: &[f64], y: &[f64]| st::pearson(x, y).map_or(f64::NAN, |c| c.r);
    let rho_of = |x: &[f64], y: &[f64]| st::spearman(x, y).map_or(f64::NAN, |c| c.r);
    Ok(json!({
        "n": x.len(),
        "mean_x": or_error(st::mean(&x).map(|m| json!(m))),
        "median_x": or_error(st::median(&x).map(|m| json!(m))),
        "pearson": or_error(st::pearson(&x, &y).map(correlation)),
        "spearman": or_error(st::spearman(&x, &y).map(correlation)),
        "wilcoxon": or_error(st::wilcoxon_signed_rank(&x, &y).map(|w| json!({
            "w": w.w, "p": w.p_two_sided, "method": w.method, "n_nonzero": w.n_nonzero,
        }))),
        "bland_altman": or_error(st::bland_altman(&x, &y).map(|b| json!({
            "bias": b.bias, "sd": b.sd, "loa": b.loa, "bias_ci": b.bias_ci,
        }))),
        "bootstrap": {
            "mean_x": or_error(st::bootstrap_ci(&x, mean_of, resamples, confidence, seed).map(ci)),
            "median_x": or_error(st::bootstrap_ci(&x, stats::median, resamples, confidence, seed).map(ci)),
            "pearson_r": or_error(st::bootstrap_ci_paired(&x, &y, r_of, resamples, confidence, seed).map(ci)),
            "spearman_r": or_error(st::bootstrap_ci_paired(&x, &y, rho_of, resamples, confidence, seed).map(ci)),
        },
    }))
}

fn morph(mask: &Path, out: &Path, f: impl Fn(&[bool], [usize; 3]) -> Vec<bool>) -> anyhow::Result<serde_json::Value> {
    let m = read_mask(mask)?;
    let result = f(&m.data, m.geometry.dims);
    let set = result.iter().filter(|&&v| v).count();
    write_volume(out, &Volume { geometry: m.geometry, data: result.iter().map(|&v| u8::from(v)).collect() })?;
    Ok(json!({ "voxels": set }))
}

/// A filter of a MET_FLOAT volume given its dims and spacing, written as MET_FLOAT.
fn filter(
    values: &Path,
    out: &Path,
    f: impl Fn(&[f32], [usize; 3], [f64; 3]) -> Vec<f32>,
) -> anyhow::Result<serde_json::Value> {
    let v = read_floats(values)?;
    let result = f(&v.data, v.geometry.dims, v.geometry.spacing_mm);
    write_volume(out, &Volume { geometry: v.geometry, data: result })?;
    Ok(json!({ "voxels": v.data.len() }))
}

/// A MET_FLOAT MetaImage.
fn read_floats(path: &Path) -> anyhow::Result<Volume<f32>> {
    let (header, raw) = read_files(path)?;
    mhd::decode(&header, &raw).with_context(|| format!("reading {} (MET_FLOAT expected)", path.display()))
}

/// A MET_UCHAR MetaImage as a mask (non-zero = set).
fn read_mask(path: &Path) -> anyhow::Result<Volume<bool>> {
    let (header, raw) = read_files(path)?;
    let v: Volume<u8> = mhd::decode(&header, &raw).with_context(|| format!("reading {}", path.display()))?;
    Ok(v.map(|x| x != 0))
}

/// Every value of a MET_DOUBLE (exact) or MET_FLOAT (widened) MetaImage.
fn read_values(path: &Path) -> anyhow::Result<Vec<f64>> {
    let (header, raw) = read_files(path)?;
    if let Ok(v) = mhd::decode::<f64>(&header, &raw) {
        return Ok(v.data);
    }
    let v: Volume<f32> = mhd::decode(&header, &raw)
        .with_context(|| format!("reading {} (MET_DOUBLE or MET_FLOAT expected)", path.display()))?;
    Ok(v.data.into_iter().map(f64::from).collect())
}

/// The header text and the raw bytes it names.
fn read_files(path: &Path) -> anyhow::Result<(String, Vec<u8>)> {
    let header = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let Some(name) = mhd::header_field(&header, "ElementDataFile") else {
        bail!("{}: no ElementDataFile line (a MetaImage header with a separate .raw is expected)", path.display());
    };
    let raw_path = path.parent().unwrap_or(Path::new(".")).join(name);
    let raw = std::fs::read(&raw_path).with_context(|| format!("reading {}", raw_path.display()))?;
    Ok((header, raw))
}

/// `out` (.mhd) and its `.raw` beside it.
fn write_volume<T: mhd::MetaElement>(out: &Path, volume: &Volume<T>) -> anyhow::Result<()> {
    let raw_path = out.with_extension("raw");
    let raw_name = raw_path.file_name().and_then(|n| n.to_str()).context("output file name is not UTF-8")?;
    let (header, raw) = mhd::encode(volume, raw_name);
    std::fs::write(out, header).with_context(|| format!("writing {}", out.display()))?;
    std::fs::write(&raw_path, raw).with_context(|| format!("writing {}", raw_path.display()))?;
    Ok(())
}
