//! A bounded, deterministic mutation fuzzer for the two readers that take files from outside:
//! the DICOM CT reader and the LIDC XML reader (with the ground-truth kernels behind it). Valid
//! small inputs — a slice from the project's own DICOM writer, a two-read LIDC message — are
//! flipped, overwritten, spliced, cut and grown at random, and each result is read inside
//! `catch_unwind`. Every outcome must be `Ok` or `Err`: no panic, and no input taking long
//! enough to be a hang.
//!
//! Iteration `i` of a reader uses the seed `SEED ^ i` alone, so a failure names the iteration
//! that reproduces it. The count per reader is `FUZZ_ITERATIONS`: 20,000 each by default (about
//! 10 s on a busy 2-core machine); `FUZZ_ITERATIONS=50000` is the full run of 10⁵ in all. A
//! failing input is written to the test target's `fuzz-failures/` folder for a closer look.

use aret_pipe::formats::dicom::{read_ct_series, DEFAULT_GAP_TOLERANCE};
use aret_pipe::formats::dicom_writer::{write_ct_series, SeriesMeta};
use aret_pipe::formats::lidc_xml;
use aret_pipe::kernels::consensus::{scan_truth, GroundTruthParams, ScanGeometry};
use aret_pipe::volume::{Geometry, Volume};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const SEED: u64 = 0x5EED_F022_D1C0_0001;
/// Mutated inputs never grow past this, so every read is bounded.
const MAX_INPUT_BYTES: usize = 64 << 10;
/// Far above any read of a 64 KiB input (milliseconds); only a hang gets near it.
const HANG: Duration = Duration::from_secs(5);

fn iterations() -> u64 {
    std::env::var("FUZZ_ITERATIONS").ok().and_then(|v| v.parse().ok()).unwrap_or(20_000)
}

/// xorshift64*: small, fast, and the same on every platform.
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One to four mutations of `input`: bit flips, overwritten bytes, inserted or deleted runs,
/// a copied chunk, a dictionary token spliced in, a cut; capped at [`MAX_INPUT_BYTES`].
fn mutate(input: &[u8], tokens: &[&[u8]], rng: &mut Rng) -> Vec<u8> {
    let mut bytes = input.to_vec();
    for _ in 0..1 + rng.below(4) {
        let at = rng.below(bytes.len() + 1);
        match rng.below(7) {
            0 if at < bytes.len() => bytes[at] ^= 1 << rng.below(8),
            1 if at < bytes.len() => bytes[at] = rng.next() as u8,
            2 => {
                let run: Vec<u8> = (0..1 + rng.below(16)).map(|_| rng.next() as u8).collect();
                bytes.splice(at..at, run);
            }
            3 => {
                let end = (at + 1 + rng.below(64)).min(bytes.len());
                bytes.drain(at.min(end)..end);
            }
            4 if !bytes.is_empty() => {
                let from = rng.below(bytes.len());
                let chunk = bytes[from..(from + 1 + rng.below(256)).min(bytes.len())].to_vec();
                bytes.splice(at..at, chunk);
            }
            5 => {
                let token = tokens[rng.below(tokens.len())];
                bytes.splice(at..at, token.iter().copied());
            }
            _ => bytes.truncate(at),
        }
    }
    bytes.truncate(MAX_INPUT_BYTES);
    bytes
}

/// Runs `read` on `runs` inputs from `mutate`; returns the iterations that panicked or hung.
/// `read` says whether it accepted the input, for the tally printed at the end.
fn fuzz(
    name: &str,
    runs: u64,
    mutate: impl Fn(&mut Rng) -> Vec<u8>,
    read: impl Fn(&[u8]) -> bool,
) -> Vec<(u64, &'static str)> {
    let (mut failures, mut accepted) = (Vec::new(), 0);
    let (mut slowest, started) = (Duration::ZERO, Instant::now());
    for i in 0..runs {
        let input = mutate(&mut Rng::new(SEED ^ i));
        let began = Instant::now();
        let outcome = catch_unwind(AssertUnwindSafe(|| read(&input)));
        let panicked = outcome.is_err();
        accepted += usize::from(outcome.unwrap_or(false));
        let took = began.elapsed();
        slowest = slowest.max(took);
        let failure = if panicked { Some("panic") } else { (took > HANG).then_some("hang") };
        if let Some(kind) = failure {
            let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("fuzz-failures");
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join(format!("{name}-{i}.bin")), &input).unwrap();
            failures.push((i, kind));
        }
    }
    eprintln!(
        "{name}: {runs} inputs ({accepted} accepted) in {:?}, slowest {slowest:?}, {} failures",
        started.elapsed(),
        failures.len()
    );
    failures
}

/// One 6 × 5 slice from the project's own writer, and its neighbour above.
fn valid_slices() -> (Vec<u8>, Vec<u8>) {
    let geometry = Geometry {
        dims: [6, 5, 2],
        spacing_mm: [0.7, 0.7, 2.5],
        origin_mm: [-10.0, -10.0, -100.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let data: Vec<i16> = (0..geometry.len() as i16).map(|v| v * 37 - 900).collect();
    let meta = SeriesMeta {
        patient_id: "FUZZ-0001".into(),
        study_instance_uid: "1.2.826.0.1.3680043.8.498.7".into(),
        series_instance_uid: "1.2.826.0.1.3680043.8.498.7.1".into(),
        sop_instance_uids: vec![],
        slice_thickness_mm: None,
        series_description: "fuzz".into(),
    };
    let mut files = write_ct_series(&Volume { geometry, data }, &meta).unwrap();
    let above = files.pop().unwrap().1;
    (files.pop().unwrap().1, above)
}

#[test]
fn dicom_reader_survives_mutated_slices() {
    let (valid, above) = valid_slices();
    let dir = tempfile::tempdir().unwrap();
    let (victim, neighbour) = (dir.path().join("000001.dcm"), dir.path().join("000002.dcm"));
    std::fs::write(&neighbour, &above).unwrap();
    let files: Vec<PathBuf> = vec![victim.clone(), neighbour];
    // The unmutated pair reads: mutations start from a valid series.
    std::fs::write(&victim, &valid).unwrap();
    assert_eq!(read_ct_series(&files, DEFAULT_GAP_TOLERANCE).unwrap().hu.geometry.dims, [6, 5, 2]);
    let tokens: [&[u8]; 8] = [
        b"DICM",
        &[0xFF, 0xFF, 0xFF, 0xFF],
        &[0xFE, 0xFF, 0x00, 0xE0],
        &[0xFE, 0xFF, 0xDD, 0xE0],
        b"SQ\0\0\xFF\xFF\xFF\xFF",
        &[0xE0, 0x7F, 0x10, 0x00],
        &[0x28, 0x00, 0x00, 0x01, b'U', b'S', 2, 0, 8, 0],
        b"1.2.840.10008.1.2.2\0",
    ];
    let failures = fuzz(
        "dicom",
        iterations(),
        |rng| mutate(&valid, &tokens, rng),
        |bytes| {
            std::fs::write(&victim, bytes).unwrap();
            read_ct_series(&files, DEFAULT_GAP_TOLERANCE).is_ok()
        },
    );
    assert!(failures.is_empty(), "inputs that panicked or hung (iteration, kind): {failures:?}");
}

fn valid_message() -> String {
    let roi = |z: f64, inclusion: &str, points: &[(i32, i32)]| {
        let edges: String = points
            .iter()
            .map(|(x, y)| format!("<edgeMap><xCoord>{x}</xCoord><yCoord>{y}</yCoord></edgeMap>"))
            .collect();
        format!("<roi><imageZposition>{z}</imageZposition><inclusion>{inclusion}</inclusion>{edges}</roi>")
    };
    let ratings = "<characteristics><subtlety>5</subtlety><internalStructure>1</internalStructure>\
        <calcification>6</calcification><sphericity>3</sphericity><margin>3</margin><lobulation>3</lobulation>\
        <spiculation>4</spiculation><texture>5</texture><malignancy>5</malignancy></characteristics>";
    let square = [(10, 10), (14, 10), (14, 14), (10, 14)];
    let read = |id: &str, z: f64| {
        format!(
            "<unblindedReadNodule><noduleID>{id}</noduleID>{ratings}{}{}</unblindedReadNodule>",
            roi(z, "TRUE", &square),
            roi(z + 2.5, "TRUE", &[(9, 9), (15, 9), (15, 15), (9, 15)])
        )
    };
    format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<LidcReadMessage xmlns=\"http://www.nih.gov\">\
         <ResponseHeader><SeriesInstanceUid>1.2.3</SeriesInstanceUid></ResponseHeader>\n\
         <readingSession><servicingRadiologistID>r1</servicingRadiologistID>{}\
         <nonNodule><nonNoduleID>n</nonNoduleID><imageZposition>-100</imageZposition>\
         <locus><xCoord>3</xCoord><yCoord>4</yCoord></locus></nonNodule></readingSession>\n\
         <readingSession>{}</readingSession></LidcReadMessage>\n",
        read("N1", -100.0),
        roi(-97.5, "FALSE", &square).replace("<roi>", "<unblindedReadNodule><noduleID>N2</noduleID><roi>")
            + "</unblindedReadNodule>"
            + &read("N3", -97.5)
    )
}

#[test]
fn lidc_xml_reader_and_ground_truth_survive_mutated_messages() {
    let valid = valid_message();
    let geometry = ScanGeometry::new((0..12).map(|k| -105.0 + 2.5 * k as f64).collect(), 0.7, 64, 64).unwrap();
    let read =
        |text: &str| lidc_xml::parse(text).map(|m| scan_truth(&m, &geometry, 2.5, &GroundTruthParams::default()));
    let truth = read(&valid).unwrap().unwrap();
    assert_eq!(truth.nodules.len(), 1, "the valid message has one nodule, read by both sessions");
    assert_eq!(truth.nodules[0].annotation_count(), 2);
    let tokens: [&[u8]; 12] = [
        b"<a>",
        b"</roi>",
        b"<roi>",
        b"<edgeMap><xCoord>63</xCoord><yCoord>0</yCoord></edgeMap>",
        b"<imageZposition>1e308</imageZposition>",
        b"-2147483649",
        b"<!--",
        b"<![CDATA[",
        b"]]>",
        b"&#0;",
        b"<!DOCTYPE x [<!ENTITY e \"&e;\">]>",
        b"<?pi ?>",
    ];
    // Half the inputs keep the markup and change values or whole elements, so that most of
    // them reach the ground-truth kernels; the other half are byte-level damage.
    let mutate_xml = |rng: &mut Rng| match rng.below(2) {
        0 => mutate_xml_structure(&valid, rng).into_bytes(),
        _ => mutate(valid.as_bytes(), &tokens, rng),
    };
    let failures =
        fuzz("lidc-xml", iterations(), mutate_xml, |bytes| matches!(read(&String::from_utf8_lossy(bytes)), Ok(Ok(_))));
    assert!(failures.is_empty(), "inputs that panicked or hung (iteration, kind): {failures:?}");
}

/// One to four edits that keep the XML well-formed: a text value replaced by a hostile one, or a
/// whole `roi`, `edgeMap` or read removed or repeated.
fn mutate_xml_structure(valid: &str, rng: &mut Rng) -> String {
    const VALUES: [&str; 14] =
        ["0", "-1", "63", "64", "511", "1e308", "NaN", "-inf", "-97.5", "2147483647", "TRUE", "false", "", " 7 "];
    const ELEMENTS: [&str; 3] = ["roi", "edgeMap", "unblindedReadNodule"];
    let mut text = valid.to_string();
    for _ in 0..1 + rng.below(4) {
        if rng.below(2) == 0 {
            // A text value: the characters between a '>' and the next '<', if not blank.
            let values: Vec<(usize, usize)> = text
                .match_indices('>')
                .filter_map(|(at, _)| text[at + 1..].find('<').map(|len| (at + 1, at + 1 + len)))
                .filter(|&(from, to)| !text[from..to].trim().is_empty())
                .collect();
            if let Some(&(from, to)) = values.get(rng.below(values.len())) {
                text.replace_range(from..to, VALUES[rng.below(VALUES.len())]);
            }
        } else {
            let name = ELEMENTS[rng.below(ELEMENTS.len())];
            let (open, close) = (format!("<{name}>"), format!("</{name}>"));
            let starts: Vec<usize> = text.match_indices(&open).map(|(at, _)| at).collect();
            let Some(&from) = starts.get(rng.below(starts.len())) else { continue };
            let Some(len) = text[from..].find(&close) else { continue };
            let element = text[from..from + len + close.len()].to_string();
            match rng.below(3) {
                0 => text.replace_range(from..from + element.len(), ""),
                _ => text.insert_str(from, &element.repeat(1 + rng.below(8))),
            }
        }
    }
    text
}
