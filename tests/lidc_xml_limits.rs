//! The LIDC XML reader's limits (file size, nesting depth, reads) and contours of forty thousand
//! points read end to end: parsed, filled, measured and clustered to the values a square gives.

use aret_pipe::formats::lidc_xml::{self, LidcError, MAX_CONTOUR_PIXELS, MAX_DEPTH, MAX_FILE_BYTES, MAX_READS};
use aret_pipe::kernels::consensus::{scan_truth, GroundTruthParams, ScanGeometry, MAX_NODULE_BOX_VOXELS};
use std::time::Instant;

const RATINGS: &str = "<characteristics><subtlety>5</subtlety><internalStructure>1</internalStructure>\
    <calcification>6</calcification><sphericity>3</sphericity><margin>3</margin><lobulation>3</lobulation>\
    <spiculation>4</spiculation><texture>5</texture><malignancy>5</malignancy></characteristics>";

/// `readers` reading sessions, each with one read of one contour through `points`.
fn message(readers: usize, z_mm: f64, points: &[(i64, i64)]) -> String {
    let mut edges = String::with_capacity(points.len() * 64);
    for (x, y) in points {
        edges.push_str(&format!("<edgeMap><xCoord>{x}</xCoord><yCoord>{y}</yCoord></edgeMap>\n"));
    }
    let session = format!(
        "<readingSession><unblindedReadNodule><noduleID>N1</noduleID>{RATINGS}<roi><imageZposition>{z_mm}\
         </imageZposition><inclusion>TRUE</inclusion>\n{edges}</roi></unblindedReadNodule></readingSession>\n"
    );
    format!("<?xml version=\"1.0\"?>\n<LidcReadMessage>\n{}</LidcReadMessage>\n", session.repeat(readers))
}

/// `<LidcReadMessage>` holding `inner` more levels of `<a>`.
fn nested(inner: usize) -> String {
    format!("<LidcReadMessage>\n{}{}</LidcReadMessage>", "<a>".repeat(inner), "</a>".repeat(inner))
}

/// 5,000 levels in 35 KB once overflowed the parser's stack: a process abort, not an error.
#[test]
fn nesting_past_the_limit_is_an_error_naming_line_and_limit() {
    let message = lidc_xml::parse(&nested(MAX_DEPTH - 1)).expect("the limit itself is accepted");
    assert!(message.sessions.is_empty());
    for inner in [MAX_DEPTH, 5_000, 100_000] {
        let err = lidc_xml::parse(&nested(inner)).unwrap_err();
        assert!(matches!(err, LidcError::TooDeep { line: 2, limit: 64 }), "{err}");
        assert!(err.to_string().contains("deeper than the limit of 64 levels (MAX_DEPTH)"), "{err}");
    }
}

#[test]
fn a_file_over_the_size_limit_is_refused_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.xml");
    let body = message(1, 1.0, &[(1, 1), (2, 2)]);
    let padding = " ".repeat(MAX_FILE_BYTES as usize + 1 - body.len());
    std::fs::write(&path, format!("{body}{padding}")).unwrap();
    let err = lidc_xml::read(&path).unwrap_err().to_string();
    assert!(
        err.contains(&format!("{} bytes exceeds the limit of {MAX_FILE_BYTES} bytes", MAX_FILE_BYTES + 1)),
        "{err}"
    );
    // One byte less is read.
    std::fs::write(&path, format!("{body}{}", &padding[1..])).unwrap();
    assert_eq!(lidc_xml::read(&path).unwrap().sessions.len(), 1);
}

#[test]
fn more_reads_than_the_limit_are_refused_naming_the_first_one_past_it() {
    let read = "<unblindedReadNodule><noduleID>n</noduleID></unblindedReadNodule>\n";
    let with = |reads: usize| {
        format!("<LidcReadMessage>\n<readingSession>\n{}</readingSession></LidcReadMessage>", read.repeat(reads))
    };
    assert_eq!(lidc_xml::parse(&with(MAX_READS)).unwrap().sessions[0].small_nodules, MAX_READS);
    let err = lidc_xml::parse(&with(MAX_READS + 1)).unwrap_err().to_string();
    assert_eq!(
        err,
        "LIDC XML line 1003: more than 1000 <unblindedReadNodule> reads (MAX_READS); real LIDC files have a few dozen"
    );
}

/// Full-image triangles, each filled over its 512 × 512 bounding square: 10,000 of them once
/// took 12 s; the contour budget stops the file at the 382nd, and 381 are read.
#[test]
fn contours_covering_more_than_the_pixel_budget_are_refused_and_the_budget_itself_is_read() {
    let roi = "<roi><imageZposition>-100</imageZposition><inclusion>TRUE</inclusion><edgeMap><xCoord>0</xCoord>\
        <yCoord>0</yCoord></edgeMap><edgeMap><xCoord>511</xCoord><yCoord>0</yCoord></edgeMap><edgeMap>\
        <xCoord>511</xCoord><yCoord>511</yCoord></edgeMap></roi>\n";
    let with = |rois: usize| {
        format!(
            "<LidcReadMessage>\n<readingSession><unblindedReadNodule><noduleID>N</noduleID>{RATINGS}\n{}\
             </unblindedReadNodule></readingSession></LidcReadMessage>",
            roi.repeat(rois)
        )
    };
    let fitting = (MAX_CONTOUR_PIXELS / (512 * 512)) as usize;
    assert_eq!(fitting, 381);
    let err = lidc_xml::parse(&with(10_000)).unwrap_err().to_string();
    assert!(
        err.starts_with(
            "LIDC XML line 384: with this <roi>, the contours' bounding rectangles cover more than 100000000 pixels"
        ),
        "{err}"
    );
    let geometry = ScanGeometry::new((0..8).map(|k| -110.0 + 2.5 * k as f64).collect(), 0.7, 512, 512).unwrap();
    let voxels = |rois: usize| {
        let started = Instant::now();
        let truth = scan_truth(&lidc_xml::parse(&with(rois)).unwrap(), &geometry, 2.5, &GroundTruthParams::default());
        eprintln!("{rois} full-image contours: parsed and measured in {:?}", started.elapsed());
        truth.unwrap().nodules[0].consensus_voxels
    };
    // The same triangle drawn 381 times on one slice fills what it fills once.
    assert_eq!(voxels(fitting), voxels(1));
}

/// Two readers outlining the boundary of a 200-pixel square, each of its 800 pixels given 50
/// times: 40,000 points a contour (4.8 MB). Filling, measuring and clustering them once cost
/// time quadratic in the points (seconds); the result must be the square's: 199 × 199 pixels
/// inside once the contour's own are switched off, the diagonal as diameter, one nodule.
#[test]
fn a_contour_of_forty_thousand_points_is_filled_and_measured_as_its_shape() {
    let (lo, side) = (100i64, 200i64);
    let boundary = (0..side)
        .map(|t| (lo + t, lo))
        .chain((0..side).map(|t| (lo + side, lo + t)))
        .chain((0..side).map(|t| (lo + side - t, lo + side)))
        .chain((0..side).map(|t| (lo, lo + side - t)));
    let points: Vec<(i64, i64)> = boundary.flat_map(|p| std::iter::repeat_n(p, 50)).collect();
    assert_eq!(points.len(), 40_000);
    let xml = message(2, -102.5, &points);
    assert!(xml.len() > 4_800_000);

    let started = Instant::now();
    let parsed_message = lidc_xml::parse(&xml).unwrap();
    let parsed = started.elapsed();
    assert_eq!(parsed_message.sessions[1].reads[0].rois[0].points.len(), 40_000);
    let geometry = ScanGeometry::new((0..8).map(|k| -110.0 + 2.5 * k as f64).collect(), 0.7, 512, 512).unwrap();
    let truth = scan_truth(&parsed_message, &geometry, 2.5, &GroundTruthParams::default()).unwrap();
    eprintln!("{} bytes: parsed in {parsed:?}, parsed and measured in {:?}", xml.len(), started.elapsed());

    assert_eq!(truth.nodules.len(), 1);
    let nodule = &truth.nodules[0];
    assert_eq!(nodule.annotation_count(), 2);
    assert_eq!(nodule.consensus_voxels, 199 * 199);
    let diagonal = (side as f64 * 0.7).hypot(side as f64 * 0.7);
    assert!((nodule.annotated_diameter_mm - diagonal).abs() < 1e-9, "{}", nodule.annotated_diameter_mm);
}

/// Two short lines, on the first and the last of 200 slices, at opposite corners: a read of
/// tiny contours whose box is the whole scan (52 million voxels, and several masks over it).
#[test]
fn a_read_spanning_far_more_of_the_scan_than_a_nodule_is_refused() {
    let line = |z: f64, from: (i32, i32), to: (i32, i32)| {
        format!(
            "<roi><imageZposition>{z}</imageZposition><inclusion>TRUE</inclusion>\
             <edgeMap><xCoord>{}</xCoord><yCoord>{}</yCoord></edgeMap>\
             <edgeMap><xCoord>{}</xCoord><yCoord>{}</yCoord></edgeMap></roi>",
            from.0, from.1, to.0, to.1
        )
    };
    let xml = format!(
        "<LidcReadMessage><readingSession><unblindedReadNodule><noduleID>N</noduleID>{RATINGS}{}{}\
         </unblindedReadNodule></readingSession></LidcReadMessage>",
        line(0.0, (0, 0), (1, 0)),
        line(199.0 * 2.5, (511, 510), (511, 511))
    );
    let geometry = ScanGeometry::new((0..200).map(|k| 2.5 * k as f64).collect(), 0.7, 512, 512).unwrap();
    let message = lidc_xml::parse(&xml).unwrap();
    let err = scan_truth(&message, &geometry, 2.5, &GroundTruthParams::default()).unwrap_err().to_string();
    assert!(
        err.contains(&format!("hold 52428800 voxels together, more than the limit of {MAX_NODULE_BOX_VOXELS}")),
        "{err}"
    );
}
