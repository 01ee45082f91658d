//! What a run needs of the machine, estimated before anything is allocated: a configuration
//! whose fits could not fit in memory is refused with the keys that size them.

use crate::config::Config;
use anyhow::bail;

/// The train stage's peak memory for the configuration's patients at once, against what the
/// machine has available (`MemAvailable`; no check where it cannot be read).
pub fn check_memory(config: &Config) -> anyhow::Result<()> {
    let Some(available) = available_bytes() else { return Ok(()) };
    check_memory_against(config, available)
}

fn check_memory_against(config: &Config, available: u64) -> anyhow::Result<()> {
    let (width, height) = (config.drr.width_px as u64, config.drr.height_px as u64);
    let one_fit = config.train.peak_bytes_estimate(3 * width * height);
    let workers = config.pipeline.stage_workers.get("train").copied().unwrap_or(config.pipeline.workers).max(1);
    let needed = one_fit.saturating_mul(workers as u64);
    if needed > available {
        let gb = |b: u64| b as f64 / 1e9;
        bail!(
            "[train] grid = {} with [drr] width_px × height_px = {width} × {height} needs about {:.1} GB a \
             patient's fit, {:.1} GB for {workers} at once, and this machine has {:.1} GB available: lower \
             grid, width_px or height_px, or fit fewer patients at once ([pipeline] workers, or \
             stage_workers = {{ train = 1 }})",
            config.train.grid,
            gb(one_fit),
            gb(needed),
            gb(available)
        );
    }
    Ok(())
}

/// `MemAvailable` of `/proc/meminfo`, in bytes.
fn available_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

#[cfg(test)]
mod tests {
    use super::*;

    const MINIMAL: &str = "[pipeline]\nname = \"t\"\n[dataset]\nkind = \"dicom\"\nroot = \"data\"\n";

    #[test]
    fn a_fit_larger_than_the_memory_is_refused_naming_its_keys() {
        let big = Config::parse(&format!("{MINIMAL}[train]\ngrid = 512\n[drr]\nwidth_px = 8192\nheight_px = 8192\n"))
            .unwrap();
        let e = check_memory_against(&big, 32_000_000_000).unwrap_err().to_string();
        assert!(
            e.contains("grid = 512")
                && e.contains("8192 × 8192")
                && e.contains("25.8 GB a patient")
                && e.contains("32.0 GB available"),
            "{e}"
        );
        // The shipped configuration's two fits at once take well under a gigabyte.
        let shipped = Config::parse(MINIMAL).unwrap();
        assert!(check_memory_against(&shipped, 1_000_000_000).is_ok());
        // Fitting one patient at a time halves what two would need.
        let two = shipped.train.peak_bytes_estimate(3 * 256 * 256) * 2;
        assert!(check_memory_against(&shipped, two - 1).is_err());
        let one =
            Config::parse(&MINIMAL.replace("name = \"t\"\n", "name = \"t\"\nstage_workers = { train = 1 }\n")).unwrap();
        assert!(check_memory_against(&one, two - 1).is_ok());
    }

    #[test]
    fn this_machine_says_how_much_memory_it_has() {
        if cfg!(target_os = "linux") {
            assert!(available_bytes().is_some_and(|b| b > 0));
        }
    }
}
