//! A bounded, seeded mutation fuzzer for the configuration loader: the shipped `pipeline.toml`
//! and the product presets (each through its `extends`), mutated byte by byte and line by line,
//! must each load or be refused with an error, never panic. `FUZZ_CONFIG_ITERATIONS` sets the
//! count (default 100,000).

use aret_pipe::config::Config;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;
use std::time::Instant;

/// Values that probe the loader's edges, put in place of a key's value.
const EDGE_VALUES: &[&str] = &[
    "0",
    "-1",
    "1e308",
    "-1e308",
    "nan",
    "inf",
    "-inf",
    "9223372036854775807",
    "-9223372036854775808",
    "18446744073709551616",
    "0.0",
    "1e-320",
    "\"\"",
    "\"../..\"",
    "[]",
    "[[]]",
    "{}",
    "true",
    "[1, \"a\"]",
    "\"\u{0}\"",
    "1979-05-27T07:32:00Z",
    "[1e308, -1e308, nan]",
];

/// The texts mutated: the shipped `pipeline.toml`, parsed from text, and each product preset,
/// loaded from a file that extends an unmutated copy of it, so that `extends` and the layers
/// are mutated too.
fn seeds() -> (String, Vec<String>) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let shipped = std::fs::read_to_string(root.join("pipeline.toml")).unwrap();
    let mut presets = Vec::new();
    for entry in std::fs::read_dir(root.join("presets")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            presets.push(std::fs::read_to_string(&path).unwrap());
        }
    }
    presets.sort();
    (shipped, presets)
}

/// Bytes a mutation inserts: TOML's punctuation, digits and a newline.
const INSERTED: &[u8] = b"=[]{}\".,#\n\\0123456789-+e";

fn mutate(text: &str, rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut bytes = text.as_bytes().to_vec();
    for _ in 0..rng.gen_range(1..=4) {
        match rng.gen_range(0..7) {
            0 if !bytes.is_empty() => {
                let i = rng.gen_range(0..bytes.len());
                bytes[i] ^= 1 << rng.gen_range(0..8);
            }
            1 => {
                let i = rng.gen_range(0..=bytes.len());
                bytes.insert(i, INSERTED[rng.gen_range(0..INSERTED.len())]);
            }
            2 if !bytes.is_empty() => {
                let i = rng.gen_range(0..bytes.len());
                let n = rng.gen_range(1..=16.min(bytes.len() - i));
                bytes.drain(i..i + n);
            }
            3 => bytes.truncate(rng.gen_range(0..=bytes.len())),
            _ => {
                // A key's value replaced by an edge value, or its line doubled or dropped.
                let lines: Vec<&[u8]> = bytes.split(|&b| b == b'\n').collect();
                let i = rng.gen_range(0..lines.len());
                let line = lines[i].to_vec();
                let replaced: Vec<u8> = match (rng.gen_range(0..3), line.iter().position(|&b| b == b'=')) {
                    (0, Some(eq)) => {
                        let edge = EDGE_VALUES[rng.gen_range(0..EDGE_VALUES.len())];
                        [&line[..=eq], b" ", edge.as_bytes()].concat()
                    }
                    (1, _) => [line.as_slice(), b"\n", line.as_slice()].concat(),
                    _ => Vec::new(),
                };
                let mut out: Vec<Vec<u8>> = lines.iter().map(|l| l.to_vec()).collect();
                out[i] = replaced;
                bytes = out.join(&b'\n');
            }
        }
    }
    bytes
}

#[test]
fn mutated_configurations_load_or_are_refused_and_never_panic() {
    let iterations: usize =
        std::env::var("FUZZ_CONFIG_ITERATIONS").ok().and_then(|v| v.parse().ok()).unwrap_or(100_000);
    let (shipped, presets) = seeds();
    assert!(presets.len() >= 5, "the product presets");
    // The presets' folder beside an unmutated pipeline.toml, as in the repository.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("pipeline.toml"), &shipped).unwrap();
    std::fs::create_dir(dir.path().join("presets")).unwrap();
    let fuzzed = dir.path().join("presets").join("fuzzed.toml");
    let mut rng = ChaCha8Rng::seed_from_u64(20261129);
    let (mut loaded, mut refused) = (0usize, 0usize);
    let started = Instant::now();
    for i in 0..iterations {
        let seed = if i % (presets.len() + 1) == 0 { &shipped } else { &presets[i % (presets.len() + 1) - 1] };
        let bytes = mutate(seed, &mut rng);
        let is_shipped = std::ptr::eq(seed, &shipped);
        if !is_shipped {
            std::fs::write(&fuzzed, &bytes).unwrap();
        }
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            let config = if is_shipped {
                // The file reader refuses non-UTF-8 before the parser sees it.
                let text = String::from_utf8(bytes.clone()).map_err(|e| anyhow::anyhow!("not UTF-8: {e}"))?;
                Config::parse(&text)
            } else {
                Config::load(&fuzzed)
            };
            config.map(|_| ())
        }));
        match outcome {
            Ok(Ok(())) => loaded += 1,
            Ok(Err(e)) => {
                assert!(!e.to_string().trim().is_empty(), "an empty error for:\n{}", String::from_utf8_lossy(&bytes));
                refused += 1;
            }
            Err(_) => panic!("the loader panicked on iteration {i}:\n{}", String::from_utf8_lossy(&bytes)),
        }
    }
    assert_eq!(loaded + refused, iterations);
    assert!(loaded > 0 && refused > 0, "the mutations reach both sides: {loaded} loaded, {refused} refused");
    eprintln!(
        "{iterations} mutated configurations: {loaded} loaded, {refused} refused, 0 panics, in {:.1} s",
        started.elapsed().as_secs_f64()
    );
}
