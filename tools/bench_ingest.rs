//! Benchmark: DICOM ingest of one CT series (read, decode, sort, HU) — median of N runs.
//!
//! `cargo run --release --example bench_ingest -- DIR [RUNS]`, DIR a folder holding one series.
//! Target: ≤ 0.5 s for 512×512×~130 on 2 cores.

use aret_pipe::formats::dicom::{read_ct_series, DEFAULT_GAP_TOLERANCE};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = args.next().ok_or_else(|| anyhow::anyhow!("usage: bench_ingest DIR [RUNS]"))?;
    let runs: usize = args.next().map(|r| r.parse()).transpose()?.unwrap_or(5);
    let files: Vec<_> = walkdir::WalkDir::new(&dir)
        .into_iter()
        .filter_map(Result::ok)
        .filter(|e| e.file_type().is_file())
        .map(|e| e.path().to_path_buf())
        .collect();
    let mut seconds = Vec::with_capacity(runs);
    let mut dims = [0; 3];
    for _ in 0..runs {
        let t = Instant::now();
        let series = read_ct_series(&files, DEFAULT_GAP_TOLERANCE)?;
        seconds.push(t.elapsed().as_secs_f64());
        dims = series.hu.geometry.dims;
    }
    seconds.sort_by(f64::total_cmp);
    let list: Vec<String> = seconds.iter().map(|s| format!("{s:.3}")).collect();
    println!("ingest {}x{}x{} from {} files: runs (s) {}", dims[0], dims[1], dims[2], files.len(), list.join(" "));
    println!("median ingest: {:.3} s (target <= 0.5 s)", seconds[seconds.len() / 2]);
    Ok(())
}
