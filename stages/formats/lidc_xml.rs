//! LIDC-IDRI radiologist annotations (`LidcReadMessage` XML, SPEC §3 ingest).
//!
//! This module owns reading the XML into plain data; the geometry (z → slice index), masks,
//! clustering and consensus live in [`crate::kernels::consensus`].
//!
//! Elements are matched by their *local* name, so the default namespace `http://www.nih.gov`,
//! other namespace URIs found in TCIA files, and no namespace at all are read alike.
//!
//! # Which reads are kept
//! `ReadingSession::reads` holds exactly the reads that pylidc 0.2.3 stores as `Annotation`s
//! (its `_populate_db/populate.py`), so that clusters and consensus masks match pylidc:
//! 1. ROIs with fewer than two `edgeMap` points are dropped from every read: a single point is a
//!    stray mark or the centre mark of a < 3 mm nodule, not a contour. They are counted in
//!    `ReadingSession::single_point_rois`.
//! 2. An `unblindedReadNodule` left with no ROI is a **small nodule** (real LIDC marks nodules
//!    < 3 mm by one point per slice): counted in `small_nodules`, not kept.
//! 3. A read with contours but without a complete rating (no `characteristics`, or one of the nine
//!    ratings missing, blank or `0`) is not a ≥ 3 mm nodule read for pylidc either: counted in
//!    `unrated_reads`, not kept.
//! 4. `nonNodule` marks are counted in `non_nodules` and never kept.
//!
//! # Limits
//! A document larger than [`MAX_FILE_BYTES`] or nesting elements deeper than [`MAX_DEPTH`] is
//! refused before it is parsed, and one with more than [`MAX_READS`] nodule reads, or contours
//! whose bounding rectangles cover more than [`MAX_CONTOUR_PIXELS`], while it is read. Real
//! LIDC files are under 2 MB, nest 6 deep and hold a few dozen reads of small contours; the limits keep a hostile file
//! from exhausting memory or overflowing the parser's stack (which would abort the whole run,
//! not just this patient). Parsing time is linear in the file's size.

use super::xml_nesting;
use roxmltree::{Document, Node};
use std::path::Path;

/// Largest LIDC XML file read, in bytes (16 MiB).
pub const MAX_FILE_BYTES: u64 = 16 << 20;
/// Deepest element nesting read (the LIDC schema nests 6 deep).
pub const MAX_DEPTH: usize = 64;
/// Most `unblindedReadNodule` reads in one file, over all its reading sessions (real files
/// have a few dozen). Clustering compares every pair of reads, so this bounds its table.
pub const MAX_READS: usize = 1_000;
/// Most pixels the contours' bounding rectangles cover together, summed over every contour of
/// two or more points (real files: under 10⁶). Each contour is filled over its rectangle, so
/// this bounds the ground truth's work (about half a second at the limit).
pub const MAX_CONTOUR_PIXELS: u64 = 100_000_000;

/// A whole `LidcReadMessage`: one CT series read by up to four radiologists.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadMessage {
    pub series_instance_uid: Option<String>,
    pub study_instance_uid: Option<String>,
    pub sessions: Vec<ReadingSession>,
}

/// One radiologist's reading of the series.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadingSession {
    /// `servicingRadiologistID`, if present.
    pub radiologist: Option<String>,
    /// Rated nodule reads with contours, in document order (see the module doc).
    pub reads: Vec<NoduleRead>,
    /// Reads with no contour of two or more points (nodules < 3 mm).
    pub small_nodules: usize,
    /// Reads with contours but an incomplete or zero `characteristics` block.
    pub unrated_reads: usize,
    /// `nonNodule` marks.
    pub non_nodules: usize,
    /// Single-point ROIs dropped from any read, kept or not.
    pub single_point_rois: usize,
}

/// One radiologist's outline of one nodule (pylidc's `Annotation`).
#[derive(Debug, Clone, PartialEq)]
pub struct NoduleRead {
    pub nodule_id: String,
    pub characteristics: Characteristics,
    /// Contours in document order; pylidc paints them in this order, which matters where two
    /// inclusion contours share a slice.
    pub rois: Vec<Roi>,
}

/// The radiologist's nine ratings (LIDC scales, each ≥ 1; malignancy 1–5, calcification 1–6 …).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Characteristics {
    pub subtlety: u8,
    pub internal_structure: u8,
    pub calcification: u8,
    pub sphericity: u8,
    pub margin: u8,
    pub lobulation: u8,
    pub spiculation: u8,
    pub texture: u8,
    pub malignancy: u8,
}

/// One contour on one slice.
#[derive(Debug, Clone, PartialEq)]
pub struct Roi {
    /// `imageZposition`: the slice's z (patient space, mm).
    pub z_mm: f64,
    pub sop_uid: Option<String>,
    /// `true`: the contour encloses nodule; `false`: it cuts a hole out of it.
    pub inclusion: bool,
    /// `(x = column, y = row)` pixel indices, in drawing order.
    pub points: Vec<(i32, i32)>,
}

#[derive(Debug, thiserror::Error)]
pub enum LidcError {
    #[error("cannot read the LIDC XML file: {0}")]
    Io(#[from] std::io::Error),
    #[error("LIDC XML of {bytes} bytes exceeds the limit of {limit} bytes (MAX_FILE_BYTES); no real LIDC file comes near it")]
    TooLarge { bytes: u64, limit: u64 },
    #[error("LIDC XML line {line}: elements nest deeper than the limit of {limit} levels (MAX_DEPTH); the LIDC schema nests 6 deep")]
    TooDeep { line: u32, limit: usize },
    #[error("LIDC XML line {line}: more than {limit} <unblindedReadNodule> reads (MAX_READS); real LIDC files have a few dozen")]
    TooManyReads { line: u32, limit: usize },
    #[error("LIDC XML line {line}: with this <roi>, the contours' bounding rectangles cover more than {limit} pixels (MAX_CONTOUR_PIXELS); real LIDC files cover under a million")]
    ContoursTooLarge { line: u32, limit: u64 },
    #[error("LIDC XML is not well-formed: {0}")]
    Xml(#[from] roxmltree::Error),
    #[error("LIDC XML line {line}: root element is <{found}>, expected <LidcReadMessage>")]
    WrongRoot { found: String, line: u32 },
    #[error("LIDC XML line {line}: <{parent}> has no <{child}>")]
    Missing { parent: String, child: &'static str, line: u32 },
    #[error("LIDC XML line {line}: <{element}> holds {value:?}, expected {expected}")]
    BadValue { element: String, value: String, expected: &'static str, line: u32 },
}

/// Read and parse the `LidcReadMessage` file at `path`, refusing one larger than
/// [`MAX_FILE_BYTES`] before reading it. Errors do not name the file: callers add it.
pub fn read(path: &Path) -> Result<ReadMessage, LidcError> {
    let bytes = std::fs::metadata(path)?.len();
    if bytes > MAX_FILE_BYTES {
        return Err(LidcError::TooLarge { bytes, limit: MAX_FILE_BYTES });
    }
    let text = std::fs::read(path)?;
    let text = String::from_utf8(text).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))?;
    parse(&text)
}

/// Parse a `LidcReadMessage` document. Never panics; errors name the element and its line.
/// Documents over [`MAX_FILE_BYTES`] or nested deeper than [`MAX_DEPTH`] are refused unparsed.
pub fn parse(xml: &str) -> Result<ReadMessage, LidcError> {
    if xml.len() as u64 > MAX_FILE_BYTES {
        return Err(LidcError::TooLarge { bytes: xml.len() as u64, limit: MAX_FILE_BYTES });
    }
    if let Some(at) = xml_nesting::first_deeper_than(xml, MAX_DEPTH) {
        let line = xml[..at].bytes().filter(|&b| b == b'\n').count() as u32 + 1;
        return Err(LidcError::TooDeep { line, limit: MAX_DEPTH });
    }
    let doc = Document::parse(xml)?;
    let root = doc.root_element();
    if root.tag_name().name() != "LidcReadMessage" {
        return Err(LidcError::WrongRoot { found: root.tag_name().name().to_string(), line: line_of(root) });
    }
    let header = child(root, "ResponseHeader");
    let header_text = |name| header.and_then(|h| child(h, name)).and_then(trimmed_text);
    let reads = || children(root, "readingSession").flat_map(|s| children(s, "unblindedReadNodule"));
    if let Some(past_the_limit) = reads().nth(MAX_READS) {
        return Err(LidcError::TooManyReads { line: line_of(past_the_limit), limit: MAX_READS });
    }
    let mut contour_pixels = 0;
    let sessions =
        children(root, "readingSession").map(|s| parse_session(s, &mut contour_pixels)).collect::<Result<_, _>>()?;
    Ok(ReadMessage {
        series_instance_uid: header_text("SeriesInstanceUid"),
        study_instance_uid: header_text("StudyInstanceUID"),
        sessions,
    })
}

/// `contour_pixels` carries the running total checked against [`MAX_CONTOUR_PIXELS`].
fn parse_session(session: Node, contour_pixels: &mut u64) -> Result<ReadingSession, LidcError> {
    let mut out = ReadingSession {
        radiologist: child(session, "servicingRadiologistID").and_then(trimmed_text),
        reads: Vec::new(),
        small_nodules: 0,
        unrated_reads: 0,
        non_nodules: children(session, "nonNodule").count(),
        single_point_rois: 0,
    };
    for read in children(session, "unblindedReadNodule") {
        let nodule_id = required_text(read, "noduleID")?;
        let (rois, single_point_rois) = parse_rois(read, contour_pixels)?;
        out.single_point_rois += single_point_rois;
        if rois.is_empty() {
            out.small_nodules += 1;
            continue;
        }
        match parse_characteristics(read)? {
            Some(characteristics) => out.reads.push(NoduleRead { nodule_id, characteristics, rois }),
            None => out.unrated_reads += 1,
        }
    }
    Ok(out)
}

/// The read's contours (two or more points) and how many single-point ROIs were dropped.
fn parse_rois(read: Node, contour_pixels: &mut u64) -> Result<(Vec<Roi>, usize), LidcError> {
    let mut rois = Vec::new();
    let mut single_point = 0;
    for node in children(read, "roi") {
        let roi = parse_roi(node)?;
        if roi.points.len() < 2 {
            single_point += 1;
        } else {
            *contour_pixels = contour_pixels.saturating_add(bounding_pixels(&roi.points));
            if *contour_pixels > MAX_CONTOUR_PIXELS {
                return Err(LidcError::ContoursTooLarge { line: line_of(node), limit: MAX_CONTOUR_PIXELS });
            }
            rois.push(roi);
        }
    }
    Ok((rois, single_point))
}

/// Pixels of the points' bounding rectangle (edges included).
fn bounding_pixels(points: &[(i32, i32)]) -> u64 {
    let span = |values: &mut dyn Iterator<Item = i32>| {
        let (lo, hi) = values.fold((i32::MAX, i32::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)));
        (i64::from(hi) - i64::from(lo) + 1) as u64
    };
    span(&mut points.iter().map(|p| p.0)) * span(&mut points.iter().map(|p| p.1))
}

fn parse_roi(roi: Node) -> Result<Roi, LidcError> {
    let z_mm = parse_number::<f64>(required(roi, "imageZposition")?, "a number (mm)")?;
    if !z_mm.is_finite() {
        return Err(bad_value(required(roi, "imageZposition")?, "a finite number (mm)"));
    }
    let inclusion_node = required(roi, "inclusion")?;
    let inclusion = match trimmed_text(inclusion_node).as_deref() {
        Some(t) if t.eq_ignore_ascii_case("true") => true,
        Some(t) if t.eq_ignore_ascii_case("false") => false,
        _ => return Err(bad_value(inclusion_node, "TRUE or FALSE")),
    };
    let points = children(roi, "edgeMap").map(parse_point).collect::<Result<_, _>>()?;
    Ok(Roi { z_mm, sop_uid: child(roi, "imageSOP_UID").and_then(trimmed_text), inclusion, points })
}

fn parse_point(edge_map: Node) -> Result<(i32, i32), LidcError> {
    let x = parse_number(required(edge_map, "xCoord")?, "an integer pixel index")?;
    let y = parse_number(required(edge_map, "yCoord")?, "an integer pixel index")?;
    Ok((x, y))
}

/// The nine ratings, or `None` when pylidc would not count the read as rated: the block is
/// absent, or any rating is missing, blank or `0`.
fn parse_characteristics(read: Node) -> Result<Option<Characteristics>, LidcError> {
    let Some(block) = child(read, "characteristics") else {
        return Ok(None);
    };
    let r = |name| rating(block, name);
    let (
        Some(subtlety),
        Some(internal_structure),
        Some(calcification),
        Some(sphericity),
        Some(margin),
        Some(lobulation),
        Some(spiculation),
        Some(texture),
        Some(malignancy),
    ) = (
        r("subtlety")?,
        r("internalStructure")?,
        r("calcification")?,
        r("sphericity")?,
        r("margin")?,
        r("lobulation")?,
        r("spiculation")?,
        r("texture")?,
        r("malignancy")?,
    )
    else {
        return Ok(None);
    };
    Ok(Some(Characteristics {
        subtlety,
        internal_structure,
        calcification,
        sphericity,
        margin,
        lobulation,
        spiculation,
        texture,
        malignancy,
    }))
}

/// One rating: `None` when missing, blank or `0`; an error when it is not a small integer.
fn rating(block: Node, name: &'static str) -> Result<Option<u8>, LidcError> {
    let Some(node) = child(block, name) else {
        return Ok(None);
    };
    if trimmed_text(node).is_none() {
        return Ok(None);
    }
    let value: u8 = parse_number(node, "a rating 0–255")?;
    Ok((value != 0).then_some(value))
}

// ---- small XML helpers: local-name matching, trimmed text, errors with lines ----

fn children<'a, 'i>(node: Node<'a, 'i>, name: &'static str) -> impl Iterator<Item = Node<'a, 'i>> {
    node.children().filter(move |c| c.is_element() && c.tag_name().name() == name)
}

fn child<'a, 'i>(node: Node<'a, 'i>, name: &'static str) -> Option<Node<'a, 'i>> {
    children(node, name).next()
}

fn required<'a, 'i>(node: Node<'a, 'i>, name: &'static str) -> Result<Node<'a, 'i>, LidcError> {
    child(node, name).ok_or_else(|| LidcError::Missing {
        parent: node.tag_name().name().to_string(),
        child: name,
        line: line_of(node),
    })
}

fn required_text(node: Node, name: &'static str) -> Result<String, LidcError> {
    let element = required(node, name)?;
    trimmed_text(element).ok_or_else(|| bad_value(element, "text"))
}

/// The element's text with surrounding whitespace removed; `None` when empty.
fn trimmed_text(node: Node) -> Option<String> {
    let text = node.text()?.trim();
    (!text.is_empty()).then(|| text.to_string())
}

fn parse_number<T: std::str::FromStr>(node: Node, expected: &'static str) -> Result<T, LidcError> {
    trimmed_text(node).and_then(|t| t.parse().ok()).ok_or_else(|| bad_value(node, expected))
}

fn bad_value(node: Node, expected: &'static str) -> LidcError {
    LidcError::BadValue {
        element: node.tag_name().name().to_string(),
        value: node.text().unwrap_or("").trim().to_string(),
        expected,
        line: line_of(node),
    }
}

fn line_of(node: Node) -> u32 {
    node.document().text_pos_at(node.range().start).row
}

#[cfg(test)]
mod tests {
    use super::*;

    const RATINGS: &str = "<characteristics><subtlety>5</subtlety><internalStructure>1</internalStructure>\
        <calcification>6</calcification><sphericity>3</sphericity><margin>3</margin>\
        <lobulation>3</lobulation><spiculation>4</spiculation><texture>5</texture>\
        <malignancy>5</malignancy></characteristics>";

    fn roi(z: &str, inclusion: &str, points: &[(i32, i32)]) -> String {
        let edges: String = points
            .iter()
            .map(|(x, y)| format!("<edgeMap><xCoord>{x}</xCoord><yCoord>{y}</yCoord></edgeMap>"))
            .collect();
        format!(
            "<roi><imageZposition>{z}</imageZposition><imageSOP_UID>1.2.3</imageSOP_UID>\
             <inclusion>{inclusion}</inclusion>{edges}</roi>"
        )
    }

    fn message(open_root: &str, close_root: &str, sessions: &str) -> String {
        format!(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n{open_root}\n<ResponseHeader>\
             <SeriesInstanceUid>1.2.840.1</SeriesInstanceUid>\
             <StudyInstanceUID>1.2.840.2</StudyInstanceUID></ResponseHeader>\n{sessions}\n{close_root}"
        )
    }

    fn square() -> Vec<(i32, i32)> {
        vec![(10, 10), (12, 10), (12, 12), (10, 12)]
    }

    fn one_nodule_session() -> String {
        format!(
            "<readingSession><servicingRadiologistID>r1</servicingRadiologistID>\
             <unblindedReadNodule><noduleID>N1</noduleID>{RATINGS}{}</unblindedReadNodule>\
             </readingSession>",
            roi("-125.0", "TRUE", &square())
        )
    }

    #[test]
    fn reads_default_other_and_no_namespace_alike() {
        let body = one_nodule_session();
        let roots = [
            ("<LidcReadMessage xmlns=\"http://www.nih.gov\">", "</LidcReadMessage>"),
            ("<LidcReadMessage xmlns=\"http://www.nih.gov/idri\">", "</LidcReadMessage>"),
            ("<LidcReadMessage>", "</LidcReadMessage>"),
            ("<l:LidcReadMessage xmlns:l=\"urn:x\">", "</l:LidcReadMessage>"),
        ];
        for (open, close) in roots {
            let parsed = parse(&message(open, close, &body)).unwrap();
            assert_eq!(parsed.series_instance_uid.as_deref(), Some("1.2.840.1"));
            assert_eq!(parsed.study_instance_uid.as_deref(), Some("1.2.840.2"));
            assert_eq!(parsed.sessions.len(), 1, "{open}");
            let session = &parsed.sessions[0];
            assert_eq!(session.radiologist.as_deref(), Some("r1"));
            assert_eq!(session.reads.len(), 1);
            let read = &session.reads[0];
            assert_eq!(read.nodule_id, "N1");
            assert_eq!(read.characteristics.malignancy, 5);
            assert_eq!(read.characteristics.internal_structure, 1);
            assert_eq!(read.rois.len(), 1);
            assert_eq!(read.rois[0].z_mm, -125.0);
            assert!(read.rois[0].inclusion);
            assert_eq!(read.rois[0].points, square());
            assert_eq!(read.rois[0].sop_uid.as_deref(), Some("1.2.3"));
        }
    }

    #[test]
    fn small_nodules_non_nodules_and_unrated_reads_are_counted_not_kept() {
        let session = format!(
            "<readingSession>\
             <unblindedReadNodule><noduleID>small</noduleID>{}{}</unblindedReadNodule>\
             <nonNodule><nonNoduleID>x</nonNoduleID><imageZposition>1</imageZposition>\
               <locus><xCoord>1</xCoord><yCoord>2</yCoord></locus></nonNodule>\
             <unblindedReadNodule><noduleID>unrated</noduleID>{}</unblindedReadNodule>\
             <unblindedReadNodule><noduleID>zero</noduleID>{}{}</unblindedReadNodule>\
             <unblindedReadNodule><noduleID>big</noduleID>{RATINGS}{}{}</unblindedReadNodule>\
             </readingSession>",
            roi("1.0", "TRUE", &[(5, 5)]),
            roi("2.0", "TRUE", &[(6, 5)]),
            roi("1.0", "TRUE", &square()),
            RATINGS.replace("<margin>3</margin>", "<margin>0</margin>"),
            roi("1.0", "TRUE", &square()),
            roi("1.0", "TRUE", &square()),
            roi("2.0", "TRUE", &[(11, 11)]),
        );
        let parsed = parse(&message("<LidcReadMessage>", "</LidcReadMessage>", &session)).unwrap();
        let s = &parsed.sessions[0];
        assert_eq!(s.small_nodules, 1);
        assert_eq!(s.non_nodules, 1);
        assert_eq!(s.unrated_reads, 2);
        assert_eq!(s.single_point_rois, 3);
        assert_eq!(s.reads.len(), 1);
        assert_eq!(s.reads[0].nodule_id, "big");
        assert_eq!(s.reads[0].rois.len(), 1, "the single-point ROI is dropped");
    }

    #[test]
    fn exclusion_roi_keeps_its_flag_and_order() {
        let session = format!(
            "<readingSession><unblindedReadNodule><noduleID>N</noduleID>{RATINGS}{}{}\
             </unblindedReadNodule></readingSession>",
            roi("3.5", "TRUE", &[(0, 0), (20, 0), (20, 20), (0, 20)]),
            roi("3.5", " false ", &square()),
        );
        let parsed = parse(&message("<LidcReadMessage>", "</LidcReadMessage>", &session)).unwrap();
        let rois = &parsed.sessions[0].reads[0].rois;
        assert_eq!(rois.len(), 2);
        assert!(rois[0].inclusion);
        assert!(!rois[1].inclusion);
        assert_eq!(rois[1].points, square());
    }

    #[test]
    fn malformed_xml_names_the_line() {
        let xml = "<LidcReadMessage>\n<readingSession>\n<oops>\n</readingSession>\n</LidcReadMessage>";
        let err = parse(xml).unwrap_err().to_string();
        assert!(err.contains("not well-formed") && err.contains("4:"), "{err}");
    }

    #[test]
    fn bad_coordinate_names_element_and_line() {
        let session = format!(
            "<readingSession><unblindedReadNodule><noduleID>N</noduleID>{RATINGS}\n{}\n\
             </unblindedReadNodule></readingSession>",
            roi("1.0", "TRUE", &square()).replace("<xCoord>12</xCoord>", "<xCoord>1.5e</xCoord>")
        );
        let xml = message("<LidcReadMessage>", "</LidcReadMessage>", &session);
        let err = parse(&xml).unwrap_err().to_string();
        assert_eq!(err, "LIDC XML line 5: <xCoord> holds \"1.5e\", expected an integer pixel index");
    }

    #[test]
    fn missing_z_and_bad_inclusion_and_wrong_root_are_errors() {
        let no_z = format!(
            "<readingSession><unblindedReadNodule><noduleID>N</noduleID>{RATINGS}{}\
             </unblindedReadNodule></readingSession>",
            roi("1.0", "TRUE", &square()).replace("<imageZposition>1.0</imageZposition>", "")
        );
        let err = parse(&message("<LidcReadMessage>", "</LidcReadMessage>", &no_z)).unwrap_err();
        assert_eq!(err.to_string(), "LIDC XML line 4: <roi> has no <imageZposition>");

        let bad_incl = one_nodule_session().replace(">TRUE<", ">maybe<");
        let err = parse(&message("<LidcReadMessage>", "</LidcReadMessage>", &bad_incl)).unwrap_err();
        assert!(err.to_string().contains("<inclusion> holds \"maybe\""), "{err}");

        let err = parse("<IdriReadMessage/>").unwrap_err();
        assert_eq!(err.to_string(), "LIDC XML line 1: root element is <IdriReadMessage>, expected <LidcReadMessage>");
    }
}
