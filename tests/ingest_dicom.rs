//! The DICOM CT-series reader on series written by `support::dicom_writer`: geometry,
//! per-slice rescale, pixel decoding, transfer syntaxes, skipped files, and every error
//! with its message (file, tag by keyword and number, remedy).

mod support;

use aret_pipe::formats::dicom::{read_ct_series, CtSeries, DicomError, DEFAULT_GAP_TOLERANCE};
use dicom_dictionary_std::tags;
use std::path::{Path, PathBuf};
use support::dicom_writer::{self as w, SliceSpec};

fn tmp() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

fn read_ok(files: &[PathBuf]) -> CtSeries {
    match read_ct_series(files, DEFAULT_GAP_TOLERANCE) {
        Ok(series) => series,
        Err(e) => panic!("expected a series, got: {e}"),
    }
}

fn read_err(files: &[PathBuf]) -> String {
    match read_ct_series(files, DEFAULT_GAP_TOLERANCE) {
        Ok(_) => panic!("expected an error"),
        Err(e) => e.to_string(),
    }
}

fn name_of(path: &Path) -> String {
    path.file_name().unwrap().to_string_lossy().into_owned()
}

#[track_caller]
fn assert_mentions(message: &str, needles: &[&str]) {
    for needle in needles {
        assert!(message.contains(needle), "message lacks {needle:?}:\n{message}");
    }
}

/// The HU volume the reader must build from `specs`, given in ascending slice order.
fn expected_volume(specs_ascending: &[&SliceSpec]) -> Vec<i16> {
    specs_ascending.iter().flat_map(|s| s.expected_hu()).collect()
}

// ----------------------------------------------------------------------------- success

#[test]
fn reads_a_plain_series_with_its_geometry() {
    let dir = tmp();
    let specs = w::series(5);
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);

    let g = &s.hu.geometry;
    assert_eq!(g.dims, [8, 6, 5]);
    // PixelSpacing is [row spacing 0.7, column spacing 0.6]: axis 0 (columns) gets 0.6.
    assert_eq!(g.spacing_mm[0], 0.6);
    assert_eq!(g.spacing_mm[1], 0.7);
    assert!((g.spacing_mm[2] - 2.5).abs() < 1e-9);
    assert_eq!(g.origin_mm, [-100.0, -80.0, 10.0]);
    assert_eq!(g.direction, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
    assert_eq!(s.slice_positions_mm, vec![10.0, 12.5, 15.0, 17.5, 20.0]);
    assert!((s.slice_gap_mm - 2.5).abs() < 1e-9);
    assert_eq!(s.slice_thickness_mm, Some(2.5));
    assert_eq!(s.hu_rounding_max_abs, 0.0);
    assert_eq!(s.transfer_syntax, w::EXPLICIT_LE);
    assert!(s.skipped.is_empty());
    let ordered: Vec<&SliceSpec> = specs.iter().collect();
    assert_eq!(s.hu.data, expected_volume(&ordered));
    // Layout [slice][row][col]: voxel (i=3, j=2, k=4) is stored value 900+37*(2*8+3)+400.
    assert_eq!(s.hu.data[g.index(3, 2, 4)], (900 + 37 * 19 + 400 - 1024) as i16);
}

#[test]
fn shuffled_file_order_gives_the_same_volume() {
    let dir = tmp();
    let specs = w::series(5);
    // File names unrelated to position, so path order is not slice order either.
    let names = ["c.dcm", "a.dcm", "e.dcm", "b.dcm", "d.dcm"];
    let files = w::write_series(dir.path(), &specs, |k| names[k].to_string());
    let reference = read_ok(&files);
    for permutation in [[4, 2, 0, 3, 1], [1, 0, 3, 4, 2], [3, 4, 1, 2, 0]] {
        let shuffled: Vec<PathBuf> = permutation.iter().map(|&i| files[i].clone()).collect();
        let s = read_ok(&shuffled);
        assert_eq!(s.hu, reference.hu);
        assert_eq!(s.slice_positions_mm, reference.slice_positions_mm);
    }
    let ordered: Vec<&SliceSpec> = specs.iter().collect();
    assert_eq!(reference.hu.data, expected_volume(&ordered));
}

#[test]
fn rescale_is_applied_per_slice() {
    let dir = tmp();
    let mut specs = w::series(4);
    for (k, spec) in specs.iter_mut().enumerate() {
        spec.slope = Some([1.0, 2.0, 0.5, 1.0][k]);
        spec.intercept = Some([-1024.0, -2000.0, -500.0, 0.0][k]);
    }
    // Slope 0.5 on odd stored values gives x.5 HU: rounded half away from zero.
    specs[2].stored[0] = 1;
    specs[2].stored[1] = -1;
    specs[2].intercept = Some(0.0);
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);
    let ordered: Vec<&SliceSpec> = specs.iter().collect();
    assert_eq!(s.hu.data, expected_volume(&ordered));
    let slice2 = &s.hu.data[2 * 48..3 * 48];
    assert_eq!(&slice2[..2], &[1, -1]);
    assert_eq!(s.hu_rounding_max_abs, 0.5);
    // Slope 2 and intercept −2000 on slice 1: spot-check one voxel by hand.
    assert_eq!(s.hu.data[48], ((900 + 100) * 2 - 2000) as i16);
}

#[test]
fn missing_rescale_defaults_to_identity_and_hu_saturate() {
    let dir = tmp();
    let mut specs = w::series(2);
    specs[0].slope = None;
    specs[0].intercept = None;
    specs[1].slope = Some(10.0);
    specs[1].stored[0] = 30000; // 300000 HU: saturates to 32767
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);
    assert_eq!(s.hu.data[0], 900);
    assert_eq!(s.hu.data[48], i16::MAX);
    assert_eq!(s.hu_rounding_max_abs, 300000.0 - 1024.0 - 32767.0);
}

#[test]
fn decreasing_z_is_sorted_ascending_with_origin_at_the_lowest_slice() {
    let dir = tmp();
    let mut specs = w::series(5);
    for (k, spec) in specs.iter_mut().enumerate() {
        spec.ipp[2] = 50.0 - 2.5 * k as f64; // instance 1 is the highest slice
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);
    assert_eq!(s.hu.geometry.origin_mm, [-100.0, -80.0, 40.0]);
    assert_eq!(s.slice_positions_mm, vec![40.0, 42.5, 45.0, 47.5, 50.0]);
    assert_eq!(s.hu.geometry.direction[2], [0.0, 0.0, 1.0]);
    let ascending: Vec<&SliceSpec> = specs.iter().rev().collect();
    assert_eq!(s.hu.data, expected_volume(&ascending));
}

#[test]
fn oblique_and_sagittal_orientations_sort_along_the_normal() {
    // Sagittal: columns step along +y (posterior), rows along −z (feet).
    let dir = tmp();
    let iop = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0];
    let normal = [-1.0, 0.0, 0.0]; // (0,1,0) × (0,0,−1)
    let mut specs = w::series(3);
    for (k, spec) in specs.iter_mut().enumerate() {
        spec.iop = iop;
        spec.ipp = [5.0 + 2.0 * k as f64, -10.0, 30.0]; // x increases: position decreases
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);
    assert_eq!(s.hu.geometry.direction, [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], normal]);
    assert_eq!(s.hu.geometry.origin_mm, [9.0, -10.0, 30.0]);
    assert_eq!(s.slice_positions_mm, vec![-9.0, -7.0, -5.0]);
    let ascending: Vec<&SliceSpec> = specs.iter().rev().collect();
    assert_eq!(s.hu.data, expected_volume(&ascending));
}

#[test]
fn signed_and_unsigned_pixel_data() {
    type Edit = fn(&mut SliceSpec);
    let cases: [(&str, Edit); 6] = [
        ("signed 16-bit", |s: &mut SliceSpec| {
            s.stored = (0..48).map(|p| p * 700 - 16000).collect();
        }),
        ("unsigned 16-bit above 32767", |s: &mut SliceSpec| {
            s.signed = false;
            s.stored = (0..48).map(|p| 30000 + p * 300).collect();
            s.intercept = Some(-32768.0);
        }),
        ("signed 12-bit, high bits zero: sign-extended", |s: &mut SliceSpec| {
            s.bits_stored = 12;
            s.mask_to_bits_stored = true;
            s.stored = (0..48).map(|p| p * 80 - 2000).collect();
        }),
        // As pydicom 3: unsigned data is masked to BitsStored (junk high bits dropped).
        ("unsigned 12-bit with high bits set: masked", |s: &mut SliceSpec| {
            s.signed = false;
            s.bits_stored = 12;
            s.stored = (0..48).map(|p| 0xF000 + p * 50).collect();
            s.intercept = Some(0.0);
        }),
        ("unsigned 8-bit", |s: &mut SliceSpec| {
            s.bits_allocated = 8;
            s.bits_stored = 8;
            s.signed = false;
            s.stored = (0..48).map(|p| p * 5).collect();
        }),
        ("signed 8-bit", |s: &mut SliceSpec| {
            s.bits_allocated = 8;
            s.bits_stored = 8;
            s.stored = (0..48).map(|p| p * 5 - 120).collect();
        }),
    ];
    for (label, edit) in cases {
        let dir = tmp();
        let mut specs = w::series(2);
        specs.iter_mut().for_each(edit);
        let files = w::write_series(dir.path(), &specs, w::default_name);
        let s = read_ok(&files);
        let ordered: Vec<&SliceSpec> = specs.iter().collect();
        assert_eq!(s.hu.data, expected_volume(&ordered), "{label}");
    }
    // The expectations above are not vacuous: spot-check the decoded values themselves.
    let mut spec = SliceSpec::ct(0);
    spec.bits_stored = 12;
    spec.mask_to_bits_stored = true;
    spec.stored[0] = -3; // written as 0x0FFD
    spec.intercept = Some(0.0);
    assert_eq!(spec.expected_hu()[0], -3);
    let mut spec = SliceSpec::ct(0);
    spec.signed = false;
    spec.bits_stored = 12;
    spec.stored[0] = 0xF001;
    spec.intercept = Some(0.0);
    assert_eq!(spec.expected_hu()[0], 1); // masked to 12 bits: 0x001
    spec.bits_stored = 16;
    assert_eq!(spec.expected_hu()[0], i16::MAX); // 61441 saturates
}

#[test]
fn all_native_transfer_syntaxes_and_missing_preamble_read_the_same() {
    let dir = tmp();
    let reference_files = w::write_series(dir.path(), &w::series(3), |k| format!("ref{k}.dcm"));
    let reference = read_ok(&reference_files);
    for ts in [w::IMPLICIT_LE, w::EXPLICIT_BE, w::DEFLATED_LE, w::EXPLICIT_LE] {
        for preamble in [true, false] {
            let sub = tmp();
            let mut specs = w::series(3);
            for s in &mut specs {
                s.transfer_syntax = ts.into();
                s.preamble = preamble;
            }
            let files = w::write_series(sub.path(), &specs, w::default_name);
            let s = read_ok(&files);
            assert_eq!(s.hu, reference.hu, "{ts}, preamble {preamble}");
            assert_eq!(s.transfer_syntax, ts);
        }
    }
}

#[test]
fn non_dicom_and_non_ct_files_are_skipped_with_a_reason() {
    let dir = tmp();
    let mut files = w::write_series(dir.path(), &w::series(3), w::default_name);
    let readme = dir.path().join("README.txt");
    std::fs::write(&readme, "CT of the chest, 3 slices\n").unwrap();
    let xml = dir.path().join("annotation.xml");
    std::fs::write(&xml, "<?xml version=\"1.0\"?><nodules/>").unwrap();
    // Empty, but named as something else: an empty file without an extension could be a
    // slice cut to nothing, and is an error (tests/dicom_damage.rs).
    let empty = dir.path().join("empty.txt");
    std::fs::write(&empty, "").unwrap();
    let mut cr = SliceSpec::ct(7);
    cr.modality = "CR".into();
    cr.sop_class_uid = "1.2.840.10008.5.1.4.1.1.1".into();
    cr.series_uid = "1.2.3.999".into(); // another series: must not count as mixing
    let cr_path = dir.path().join("scout.dcm");
    w::write_slice(&cr_path, &cr);
    files.extend([readme.clone(), xml.clone(), empty.clone(), cr_path.clone()]);

    let s = read_ok(&files);
    assert_eq!(s.hu.geometry.dims, [8, 6, 3]);
    let reasons: Vec<(String, &str)> = s.skipped.iter().map(|(p, r)| (name_of(p), r.as_str())).collect();
    assert_eq!(reasons.len(), 4, "{reasons:?}");
    for (name, reason) in &reasons {
        match name.as_str() {
            "scout.dcm" => assert_mentions(reason, &["not a CT image", "Modality (0008,0060)", "'CR'"]),
            _ => assert_mentions(reason, &["not a DICOM file", "DICM"]),
        }
    }
}

#[test]
fn ct_by_sop_class_without_modality_is_kept() {
    let dir = tmp();
    let mut specs = w::series(2);
    for s in &mut specs {
        s.omit.push(tags::MODALITY);
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_eq!(read_ok(&files).hu.geometry.dims[2], 2);
}

#[test]
fn single_slice_spacing_falls_back_to_thickness_then_spacing_between_slices_then_1mm() {
    let dir = tmp();
    let mut spec = SliceSpec::ct(0);
    let path = dir.path().join("one.dcm");
    let cases = [(Some(3.0), Some(4.0), 3.0), (None, Some(4.0), 4.0), (None, None, 1.0)];
    for (thickness, between, expected) in cases {
        spec.slice_thickness = thickness;
        spec.spacing_between_slices = between;
        w::write_slice(&path, &spec);
        let s = read_ok(std::slice::from_ref(&path));
        assert_eq!(s.hu.geometry.dims, [8, 6, 1]);
        assert_eq!(s.hu.geometry.spacing_mm[2], expected);
        assert_eq!(s.slice_gap_mm, expected);
        assert_eq!(s.slice_positions_mm, vec![10.0]);
        assert_eq!(s.slice_thickness_mm, thickness);
        assert_eq!(s.hu.data, spec.expected_hu());
    }
}

#[test]
fn tiny_spacing_jitter_within_one_percent_is_accepted() {
    let dir = tmp();
    let mut specs = w::series(4);
    specs[2].ipp[2] += 0.02; // gaps 2.52 and 2.48 around a 2.5 median: within 1%
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let s = read_ok(&files);
    assert!((s.slice_gap_mm - 2.5).abs() < 1e-9);
}

// ------------------------------------------------------------------------------ errors

#[test]
fn error_when_no_file_is_ct() {
    let dir = tmp();
    let mut mr = SliceSpec::ct(0);
    mr.modality = "MR".into();
    mr.sop_class_uid = "1.2.840.10008.5.1.4.1.1.4".into();
    let mr_path = dir.path().join("mr.dcm");
    w::write_slice(&mr_path, &mr);
    let txt = dir.path().join("notes.txt");
    std::fs::write(&txt, "hello").unwrap();
    let msg = read_err(&[mr_path, txt]);
    assert_mentions(
        &msg,
        &[
            "no CT image slices",
            "2 file(s)",
            "1 not DICOM",
            "1 DICOM but not CT",
            "mr.dcm",
            "'MR'",
            "Modality (0008,0060)",
            "SOPClassUID (0008,0016)",
        ],
    );
    assert!(matches!(read_ct_series(&[], DEFAULT_GAP_TOLERANCE), Err(DicomError::NoCtSlices { examined: 0, .. })));
}

#[test]
fn error_on_mixed_series() {
    let dir = tmp();
    let mut specs = w::series(5);
    for s in &mut specs[3..] {
        s.series_uid = "1.2.3.4.5.6".into();
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let msg = read_err(&files);
    assert_mentions(
        &msg,
        &[
            "2 different series",
            "SeriesInstanceUID (0020,000E)",
            &format!("{} (3 slices", w::SERIES_UID),
            "1.2.3.4.5.6 (2 slices",
            "slice_3.dcm",
            "one CT series per patient folder",
        ],
    );
}

#[test]
fn error_on_each_missing_required_tag() {
    let cases = [
        (tags::PIXEL_SPACING, "PixelSpacing (0028,0030)"),
        (tags::IMAGE_POSITION_PATIENT, "ImagePositionPatient (0020,0032)"),
        (tags::IMAGE_ORIENTATION_PATIENT, "ImageOrientationPatient (0020,0037)"),
        (tags::ROWS, "Rows (0028,0010)"),
        (tags::COLUMNS, "Columns (0028,0011)"),
        (tags::PIXEL_DATA, "PixelData (7FE0,0010)"),
        (tags::BITS_ALLOCATED, "BitsAllocated (0028,0100)"),
        (tags::PIXEL_REPRESENTATION, "PixelRepresentation (0028,0103)"),
    ];
    for (tag, label) in cases {
        let dir = tmp();
        let mut specs = w::series(3);
        specs[1].omit.push(tag);
        let files = w::write_series(dir.path(), &specs, w::default_name);
        let msg = read_err(&files);
        assert_mentions(&msg, &["slice_1.dcm", label, "is missing", "re-export"]);
    }
}

#[test]
fn error_on_malformed_geometry_values() {
    let dir = tmp();
    let mut specs = w::series(2);
    specs[1].pixel_spacing = [0.0, 0.6];
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(&read_err(&files), &["slice_1.dcm", "PixelSpacing (0028,0030)", "'0\\0.6'", "positive"]);
}

#[test]
fn error_on_compressed_transfer_syntax() {
    let dir = tmp();
    let mut specs = w::series(3);
    specs[2].transfer_syntax = w::JPEG2000_LOSSLESS.into();
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let msg = read_err(&files);
    assert_mentions(
        &msg,
        &[
            "slice_2.dcm",
            "TransferSyntaxUID (0002,0010)",
            "1.2.840.10008.1.2.4.90",
            "JPEG 2000 Image Compression (Lossless Only)",
            "not supported",
            "gdcmconv --raw",
            "dcmdjpeg",
        ],
    );
}

#[test]
fn compressed_non_ct_file_is_skipped_not_an_error() {
    let dir = tmp();
    let mut files = w::write_series(dir.path(), &w::series(2), w::default_name);
    let mut cr = SliceSpec::ct(5);
    cr.modality = "CR".into();
    cr.sop_class_uid = "1.2.840.10008.5.1.4.1.1.1".into();
    cr.transfer_syntax = w::JPEG2000_LOSSLESS.into();
    let cr_path = dir.path().join("cr_j2k.dcm");
    w::write_slice(&cr_path, &cr);
    files.push(cr_path);
    let s = read_ok(&files);
    assert_eq!(s.skipped.len(), 1);
    assert_mentions(&s.skipped[0].1, &["not a CT image", "'CR'"]);
}

#[test]
fn error_on_unknown_private_transfer_syntax() {
    let dir = tmp();
    let files = w::write_series(dir.path(), &w::series(2), w::default_name);
    // Same-length swap of the meta's TransferSyntaxUID: "1.2.840.10008.1.2.1\0" → "...2.9\0".
    let bytes = std::fs::read(&files[1]).unwrap();
    let needle = b"1.2.840.10008.1.2.1\0";
    let at = bytes.windows(needle.len()).position(|win| win == needle).unwrap();
    let mut patched = bytes.clone();
    patched[at..at + needle.len()].copy_from_slice(b"1.2.840.10008.1.2.9\0");
    std::fs::write(&files[1], patched).unwrap();
    assert_mentions(
        &read_err(&files),
        &["slice_1.dcm", "TransferSyntaxUID (0002,0010)", "1.2.840.10008.1.2.9", "unknown or private"],
    );
}

#[test]
fn error_on_multi_frame_file() {
    let dir = tmp();
    let mut specs = w::series(2);
    specs[0].number_of_frames = Some(2);
    specs[0].sop_class_uid = "1.2.840.10008.5.1.4.1.1.2.1".into(); // Enhanced CT
    specs[0].omit.push(tags::PIXEL_SPACING); // lives in functional groups in Enhanced CT
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &["slice_0.dcm", "multi-frame", "NumberOfFrames (0028,0008) = 2", "not supported", "one file per slice"],
    );
}

#[test]
fn error_on_inconsistent_slices() {
    type Edit = fn(&mut SliceSpec);
    let cases: [(Edit, &str, &str); 4] = [
        (
            |s| {
                s.rows = 5;
                s.stored.truncate(40)
            },
            "Rows (0028,0010) = 5",
            "from 6",
        ),
        (
            |s| {
                s.cols = 6;
                s.stored.truncate(36)
            },
            "Columns (0028,0011) = 6",
            "from 8",
        ),
        (|s| s.pixel_spacing = [0.7, 0.65], "PixelSpacing (0028,0030) = 0.7\\0.65", "from 0.7\\0.6"),
        (
            |s| s.iop = [1.0, 0.0, 0.0, 0.0, 0.0, -1.0],
            "ImageOrientationPatient (0020,0037) = 1\\0\\0\\0\\0\\-1",
            "from 1\\0\\0\\0\\1\\0",
        ),
    ];
    for (edit, value, reference) in cases {
        let dir = tmp();
        let mut specs = w::series(3);
        edit(&mut specs[2]);
        let files = w::write_series(dir.path(), &specs, w::default_name);
        let msg = read_err(&files);
        assert_mentions(&msg, &["slice_2.dcm", value, reference, "slice_0.dcm", "one series per patient folder"]);
    }
}

#[test]
fn error_on_duplicate_slice_positions() {
    let dir = tmp();
    let mut specs = w::series(4);
    specs[3].ipp = specs[1].ipp; // e.g. the same slice exported twice
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &[
            "slice_1.dcm",
            "slice_3.dcm",
            "same slice position 12.500 mm",
            "ImagePositionPatient (0020,0032)",
            "remove the duplicate",
        ],
    );
}

#[test]
fn error_on_non_uniform_spacing() {
    let dir = tmp();
    let mut specs = w::series(6);
    specs.remove(3); // a missing slice: gaps 2.5, 2.5, 5, 2.5
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &[
            "non-uniform slice spacing",
            "slice_2.dcm and ",
            "slice_3.dcm is 5.0000 mm",
            "median gap is 2.5000 mm",
            "1 of 4 gaps differ",
            "ImagePositionPatient (0020,0032)",
            "Slices are missing",
        ],
    );
}

#[test]
fn error_on_gantry_tilt() {
    let dir = tmp();
    let mut specs = w::series(4);
    let tilt = 15f64.to_radians();
    for (k, s) in specs.iter_mut().enumerate() {
        s.ipp[1] = -80.0 + 2.5 * k as f64 * tilt.tan();
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &[
            "slice_1.dcm",
            "slice_0.dcm",
            "tilted 15.00°",
            "ImagePositionPatient (0020,0032)",
            "ImageOrientationPatient (0020,0037)",
            "gantry tilt",
        ],
    );
}

#[test]
fn error_on_non_orthogonal_orientation() {
    let dir = tmp();
    let mut specs = w::series(3);
    for s in &mut specs {
        s.iop = [1.0, 0.0, 0.0, 0.1, 0.995, 0.0];
    }
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &["slice_0.dcm", "ImageOrientationPatient (0020,0037)", "not orthogonal unit vectors", "angle 84.26"],
    );
}

#[test]
fn error_on_unsupported_pixel_encoding() {
    type Edit = fn(&mut SliceSpec);
    let cases: [(Edit, &str); 4] = [
        (
            |s| {
                s.bits_allocated = 32;
                s.bits_stored = 32
            },
            "BitsAllocated (0028,0100) = 32",
        ),
        (|s| s.samples_per_pixel = 3, "SamplesPerPixel (0028,0002) = 3"),
        (|s| s.photometric = "PALETTE COLOR".into(), "PhotometricInterpretation (0028,0004) = PALETTE COLOR"),
        (|s| s.bits_stored = 17, "BitsStored (0028,0101) = 17"),
    ];
    for (edit, label) in cases {
        let dir = tmp();
        let mut specs = w::series(2);
        edit(&mut specs[1]);
        let files = w::write_series(dir.path(), &specs, w::default_name);
        assert_mentions(&read_err(&files), &["slice_1.dcm", label, "not supported", "supported:"]);
    }
}

#[test]
fn error_on_short_pixel_data() {
    let dir = tmp();
    let mut specs = w::series(2);
    specs[0].stored.truncate(40);
    let files = w::write_series(dir.path(), &specs, w::default_name);
    assert_mentions(
        &read_err(&files),
        &["slice_0.dcm", "PixelData (7FE0,0010) holds 80 bytes", "needs 96", "truncated"],
    );
}

#[test]
fn error_on_truncated_dicom_file() {
    let dir = tmp();
    let files = w::write_series(dir.path(), &w::series(2), w::default_name);
    let bytes = std::fs::read(&files[1]).unwrap();
    std::fs::write(&files[1], &bytes[..200]).unwrap();
    assert_mentions(&read_err(&files), &["slice_1.dcm", "cannot be parsed", "truncated or damaged"]);
}

#[test]
fn damaged_non_ct_file_is_skipped_but_a_damaged_ct_slice_is_not() {
    let dir = tmp();
    let mut files = w::write_series(dir.path(), &w::series(2), w::default_name);
    let mut cr = SliceSpec::ct(5);
    cr.modality = "CR".into();
    cr.sop_class_uid = "1.2.840.10008.5.1.4.1.1.1".into();
    let cr_path = dir.path().join("cr.dcm");
    w::write_slice(&cr_path, &cr);
    let bytes = std::fs::read(&cr_path).unwrap();
    std::fs::write(&cr_path, &bytes[..bytes.len() - 10]).unwrap();
    files.push(cr_path);
    let s = read_ok(&files);
    assert_eq!(s.skipped.len(), 1);
    assert_mentions(&s.skipped[0].1, &["damaged DICOM file", "not a CT image", "1.2.840.10008.5.1.4.1.1.1"]);
}

#[test]
fn error_on_unreadable_file() {
    let dir = tmp();
    let missing = dir.path().join("gone.dcm");
    assert_mentions(&read_err(&[missing]), &["gone.dcm", "cannot read the file"]);
}

/// Truncations and byte flips anywhere in a valid file: always Ok or Err, never a panic.
#[test]
fn damaged_files_never_panic() {
    let dir = tmp();
    let files = w::write_series(dir.path(), &w::series(2), w::default_name);
    let good = std::fs::read(&files[0]).unwrap();
    let victim = dir.path().join("victim.dcm");
    let inputs = [victim.clone(), files[1].clone()];
    let mut seed = 0x2545_f491_4f6c_dd1d_u64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    for cut in (0..good.len()).step_by(7) {
        std::fs::write(&victim, &good[..cut]).unwrap();
        let _ = read_ct_series(&inputs, DEFAULT_GAP_TOLERANCE);
    }
    for _ in 0..400 {
        let mut bytes = good.clone();
        for _ in 0..1 + next() % 4 {
            let at = (next() % bytes.len() as u64) as usize;
            bytes[at] = next() as u8;
        }
        std::fs::write(&victim, &bytes).unwrap();
        let _ = read_ct_series(&inputs, DEFAULT_GAP_TOLERANCE);
    }
}

#[test]
fn no_patient_identifiers_in_results_or_errors() {
    let dir = tmp();
    let plant = |s: &mut SliceSpec| s.patient = Some(("Doe^Jane".into(), "SECRET-ID-42".into()));
    let leaks = |text: &str| text.contains("Doe") || text.contains("SECRET-ID-42");

    let mut specs = w::series(3);
    specs.iter_mut().for_each(plant);
    let mut mr = SliceSpec::ct(9);
    plant(&mut mr);
    mr.modality = "MR".into();
    mr.sop_class_uid = "1.2.840.10008.5.1.4.1.1.4".into();
    specs.push(mr);
    let files = w::write_series(dir.path(), &specs, w::default_name);
    let ok = read_ok(&files);
    assert!(!leaks(&format!("{ok:?}")));

    let mut broken = w::series(3);
    broken.iter_mut().for_each(plant);
    broken[1].omit.push(tags::PIXEL_SPACING);
    broken[2].series_uid = "9.9".into();
    let sub = tmp();
    let files = w::write_series(sub.path(), &broken, w::default_name);
    // A file cut inside the PatientName value: the parse error must not quote it.
    let cut = sub.path().join("cut.dcm");
    let bytes = std::fs::read(&files[0]).unwrap();
    let at = bytes.windows(8).position(|win| win == b"Doe^Jane").unwrap();
    std::fs::write(&cut, &bytes[..at + 4]).unwrap();
    let errors = [
        read_err(&files),                                // missing PixelSpacing
        read_err(&[files[0].clone(), files[2].clone()]), // mixed series
        read_err(&[cut]),                                // corrupt
    ];
    for error in errors {
        assert!(!leaks(&error), "{error}");
    }
}
