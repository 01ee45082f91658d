//! The DICOM reader on slices whose pixel-format tags lie about their pixel data, and on series
//! whose first or last slice is empty or cut short: each must be an error naming the file and
//! the tag, never garbage HU or a silently shorter volume.

mod support;

use aret_pipe::formats::dicom::{read_ct_series, DEFAULT_GAP_TOLERANCE};
use dicom_core::Tag;
use dicom_dictionary_std::tags;
use std::path::{Path, PathBuf};
use support::dicom_writer::{self as w, SliceSpec};

fn read_err(files: &[PathBuf]) -> String {
    match read_ct_series(files, DEFAULT_GAP_TOLERANCE) {
        Ok(s) => panic!("expected an error, got a volume of {:?}", s.hu.geometry.dims),
        Err(e) => e.to_string(),
    }
}

#[track_caller]
fn assert_mentions(message: &str, needles: &[&str]) {
    for needle in needles {
        assert!(message.contains(needle), "message lacks {needle:?}:\n{message}");
    }
}

/// Overwrites the value of the explicit-VR little-endian US element `tag` in `path`.
fn patch_us(path: &Path, tag: Tag, value: u16) {
    let mut bytes = std::fs::read(path).unwrap();
    let [g0, g1] = tag.0.to_le_bytes();
    let [e0, e1] = tag.1.to_le_bytes();
    let header = [g0, g1, e0, e1, b'U', b'S', 2, 0];
    let at = bytes.windows(8).position(|w| w == header).unwrap_or_else(|| panic!("no US element {tag}"));
    bytes[at + 8..at + 10].copy_from_slice(&value.to_le_bytes());
    std::fs::write(path, bytes).unwrap();
}

/// BitsAllocated 8 over 16-bit data (and the reverse, and other mismatches) once decoded the
/// first half of the bytes as pixels and exited 0.
#[test]
fn pixel_data_length_must_match_the_pixel_format_tags() {
    type Damage = fn(&Path);
    let cases: [(Damage, &[&str]); 4] = [
        (
            |p| {
                patch_us(p, tags::BITS_ALLOCATED, 8);
                patch_us(p, tags::BITS_STORED, 8);
                patch_us(p, tags::HIGH_BIT, 7);
            },
            &[
                "PixelData (7FE0,0010) holds 96 bytes",
                "BitsAllocated (0028,0100)",
                "6 × 8 × 1 × 8/8",
                "needs 48",
                "garbage",
            ],
        ),
        (|p| patch_us(p, tags::ROWS, 5), &["holds 96 bytes", "Rows (0028,0010)", "5 × 8 × 1 × 16/8", "needs 80"]),
        (|p| patch_us(p, tags::COLUMNS, 9), &["holds 96 bytes", "9 × 1 × 16/8", "needs 108", "truncated"]),
        (|p| patch_us(p, tags::HIGH_BIT, 11), &["HighBit (0028,0102) = 11", "not supported", "BitsStored − 1"]),
    ];
    for (damage, needles) in cases {
        let dir = tempfile::tempdir().unwrap();
        let files = w::write_series(dir.path(), &w::series(3), w::default_name);
        damage(&files[1]);
        let err = read_err(&files);
        assert_mentions(&err, &["slice_1.dcm"]);
        assert_mentions(&err, needles);
    }
}

#[test]
fn eight_bit_data_over_sixteen_bit_tags_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut specs = w::series(2);
    specs[0].bits_allocated = 8;
    specs[0].bits_stored = 8;
    specs[0].stored.iter_mut().for_each(|v| *v %= 128);
    let files = w::write_series(dir.path(), &specs, w::default_name);
    patch_us(&files[0], tags::BITS_ALLOCATED, 16);
    assert_mentions(&read_err(&files), &["slice_0.dcm", "holds 48 bytes", "needs 96"]);
}

/// An odd pixel count of 8-bit data is padded to even length with one byte: that is valid.
#[test]
fn one_pad_byte_after_odd_length_eight_bit_data_is_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let mut specs = w::series(2);
    for s in &mut specs {
        s.rows = 3;
        s.cols = 5;
        s.bits_allocated = 8;
        s.bits_stored = 8;
        s.stored = (0..15).map(|v| v * 3).collect();
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let series = read_ct_series(&files, DEFAULT_GAP_TOLERANCE).unwrap();
    assert_eq!(series.hu.geometry.dims, [5, 3, 2]);
    assert_eq!(series.hu.data[..15], specs[0].expected_hu()[..]);
}

/// A 0-byte or cut first or last slice once counted as "not DICOM" and the volume silently
/// lost that slice: no gap shows a slice missing at an end.
#[test]
fn an_empty_or_cut_end_slice_is_an_error_naming_it() {
    let mut cases = 0;
    for end in [0, 4] {
        for len in [0, 1, 100, 131] {
            for name in ["slice_x.dcm", "SLICE_X.DCM", "000042"] {
                let dir = tempfile::tempdir().unwrap();
                let mut files = w::write_series(dir.path(), &w::series(5), w::default_name);
                let bytes = std::fs::read(&files[end]).unwrap();
                std::fs::remove_file(&files[end]).unwrap();
                files[end] = dir.path().join(name);
                std::fs::write(&files[end], &bytes[..len]).unwrap();
                let err = read_err(&files);
                assert_mentions(&err, &[name, &format!("{len} bytes without the DICOM 'DICM' marker"), "shorten"]);
                cases += 1;
            }
        }
    }
    assert_eq!(cases, 24);
}

#[test]
fn a_file_named_dcm_without_the_marker_is_an_error_whatever_its_size() {
    let dir = tempfile::tempdir().unwrap();
    let mut files = w::write_series(dir.path(), &w::series(3), w::default_name);
    // A slice with its 132-byte Part 10 header stripped: what an old ACR-NEMA export looks like.
    let bytes = std::fs::read(&files[2]).unwrap();
    std::fs::write(&files[2], &bytes[132..]).unwrap();
    files.push(dir.path().join("notes.txt"));
    std::fs::write(files.last().unwrap(), "x".repeat(10)).unwrap();
    assert_mentions(&read_err(&files), &["slice_2.dcm", "named like a DICOM file"]);
}

/// What clearly is something else is still skipped and counted: other extensions of any size,
/// and unnamed files long enough to have shown the marker.
#[test]
fn files_that_clearly_are_something_else_are_still_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let mut files = w::write_series(dir.path(), &w::series(3), w::default_name);
    for (name, body) in
        [("README.txt", "3 slices".to_string()), ("empty.json", String::new()), ("LICENSE", "x".repeat(500))]
    {
        files.push(dir.path().join(name));
        std::fs::write(files.last().unwrap(), body).unwrap();
    }
    let mut scout = SliceSpec::ct(7);
    scout.modality = "CR".into();
    scout.sop_class_uid = "1.2.840.10008.5.1.4.1.1.1".into();
    files.push(dir.path().join("scout.dcm"));
    w::write_slice(files.last().unwrap(), &scout);
    let series = read_ct_series(&files, DEFAULT_GAP_TOLERANCE).unwrap();
    assert_eq!(series.hu.geometry.dims[2], 3);
    assert_eq!((series.skipped.len(), series.skipped_not_dicom()), (4, 3));
}

/// Two letters that are no standard VR (here `UI` of TransferSyntaxUID turned `UF`) once made
/// the parser guess a 4-byte length and zero-fill a buffer of it (a second per slice, and
/// gigabytes) before failing: the reader refuses the file before the parser sees it.
#[test]
fn an_element_with_a_value_representation_outside_the_standard_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let files = w::write_series(dir.path(), &w::series(2), w::default_name);
    let mut bytes = std::fs::read(&files[0]).unwrap();
    let at = bytes.windows(6).position(|w| w == [0x02, 0x00, 0x10, 0x00, b'U', b'I']).unwrap();
    bytes[at + 5] = b'F';
    std::fs::write(&files[0], bytes).unwrap();
    assert_mentions(&read_err(&files), &["slice_0.dcm", "(0002,0010) has an invalid value representation"]);
}
