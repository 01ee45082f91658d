//! DICOM CT series → one Hounsfield-unit volume in patient space (LPS, mm).
//!
//! This module owns everything between "a patient folder's file list" and "an `i16` HU
//! volume with its geometry": telling CT slices apart from other files, decoding native
//! (uncompressed) pixel data the way pydicom's `pixel_array` does, applying each slice's own
//! rescale, sorting slices along the slice normal, and refusing — with a message that names
//! the file, the tag and a remedy — every series we cannot place in 3-D without guessing.
//!
//! Geometry conventions (SPEC): index axis 0 (columns) runs along the row direction cosine
//! `ImageOrientationPatient[0..3]` with step `PixelSpacing[1]`; axis 1 (rows) along the column
//! cosine `ImageOrientationPatient[3..6]` with step `PixelSpacing[0]`; axis 2 along
//! `normal = row × col`, slices sorted by `ImagePositionPatient · normal` ascending, step =
//! the median gap. The origin is the first sorted slice's `ImagePositionPatient`.
//!
//! A single-slice series is valid. Its slice spacing (`spacing_mm[2]` and `slice_gap_mm`) is
//! SliceThickness (0018,0050) if present and positive, else SpacingBetweenSlices (0018,0088),
//! else 1.0 mm: there is no gap to measure, and downstream stages need a positive spacing.
//!
//! Skip or fail: a file is skipped (and counted) only when it clearly is something else: a
//! DICOM file that is not a CT image (Modality (0008,0060) ≠ CT and SOPClassUID ≠ CT Image
//! Storage), or a file without the "DICM" marker that is neither named like a DICOM file
//! (`.dcm`, `.dicom`, `.dic`, `.ima`) nor too short to be one while named like one could be
//! (no extension). Anything that may be a CT slice but cannot be used is an error naming the
//! file: empty or truncated (shorter than the 132-byte Part 10 header) and unnamed or named
//! `.dcm`, named `.dcm` without the marker, compressed, damaged, multi-frame, or with pixel data
//! that does not match its pixel-format tags. Skipping any of these could silently shorten the
//! volume at an end, where no slice gap shows the loss.
//!
//! Pixel decoding follows pydicom 3's `pixel_array`: unsigned data is masked to BitsStored
//! (junk in the unused high bits is dropped), signed data is sign-extended from BitsStored.
//!
//! Privacy: no patient-identifying attribute is ever read, so none can leak into what we
//! return or into an error message. Values quoted in errors come only from geometry and
//! pixel-format tags.

use crate::volume::{Geometry, Volume};
use dicom_core::value::{PrimitiveValue, Value};
use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_object::file::ReadPreamble;
use dicom_object::{FileMetaTable, InMemDicomObject, OpenFileOptions, ReadError};
use glam::DVec3;
use rayon::prelude::*;
use std::borrow::Cow;
use std::fmt;
use std::path::{Path, PathBuf};

mod length_guard;

/// A CT series read into Hounsfield units.
#[derive(Debug, Clone)]
pub struct CtSeries {
    /// HU = stored × RescaleSlope + RescaleIntercept of each slice, rounded to nearest
    /// (half away from zero) and saturated to `i16`.
    pub hu: Volume<i16>,
    /// Position of each sorted slice along the slice normal (IPP · normal), ascending, mm.
    pub slice_positions_mm: Vec<f64>,
    /// Median gap between consecutive slice positions, mm (single slice: see module doc).
    pub slice_gap_mm: f64,
    /// SliceThickness (0018,0050) of the first sorted slice, if present. Informative only.
    pub slice_thickness_mm: Option<f64>,
    /// Largest |HU as float − HU as i16| over all voxels: rounding and saturation loss.
    pub hu_rounding_max_abs: f64,
    /// Transfer syntax UID of the first sorted slice.
    pub transfer_syntax: String,
    /// Files ignored (not DICOM, or DICOM but not a CT image), with the reason.
    pub skipped: Vec<(PathBuf, String)>,
}

/// How every skip reason for a file without the DICOM marker starts.
const NOT_DICOM: &str = "not a DICOM file";

impl CtSeries {
    /// How many of [`Self::skipped`] are not DICOM at all (the rest are DICOM but not CT).
    pub fn skipped_not_dicom(&self) -> usize {
        self.skipped.iter().filter(|(_, reason)| reason.starts_with(NOT_DICOM)).count()
    }
}

/// A DICOM attribute named the way users look it up: keyword and (gggg,eeee).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TagRef {
    pub keyword: &'static str,
    pub tag: Tag,
}

impl fmt::Display for TagRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({:04X},{:04X})", self.keyword, self.tag.0, self.tag.1)
    }
}

/// The attributes this reader looks at, named once so every message spells them the same.
pub mod attr {
    use super::TagRef;
    use dicom_dictionary_std::tags;

    macro_rules! tag_refs {
        ($($name:ident = $keyword:literal),* $(,)?) => {
            $(pub const $name: TagRef = TagRef { keyword: $keyword, tag: tags::$name };)*
        };
    }

    tag_refs! {
        TRANSFER_SYNTAX_UID = "TransferSyntaxUID",
        SOP_CLASS_UID = "SOPClassUID",
        MODALITY = "Modality",
        SLICE_THICKNESS = "SliceThickness",
        SPACING_BETWEEN_SLICES = "SpacingBetweenSlices",
        SERIES_INSTANCE_UID = "SeriesInstanceUID",
        IMAGE_POSITION_PATIENT = "ImagePositionPatient",
        IMAGE_ORIENTATION_PATIENT = "ImageOrientationPatient",
        SAMPLES_PER_PIXEL = "SamplesPerPixel",
        PHOTOMETRIC_INTERPRETATION = "PhotometricInterpretation",
        NUMBER_OF_FRAMES = "NumberOfFrames",
        ROWS = "Rows",
        COLUMNS = "Columns",
        PIXEL_SPACING = "PixelSpacing",
        BITS_ALLOCATED = "BitsAllocated",
        BITS_STORED = "BitsStored",
        HIGH_BIT = "HighBit",
        PIXEL_REPRESENTATION = "PixelRepresentation",
        RESCALE_INTERCEPT = "RescaleIntercept",
        RESCALE_SLOPE = "RescaleSlope",
        MODALITY_LUT_SEQUENCE = "ModalityLUTSequence",
        PIXEL_DATA = "PixelData",
    }
}

/// Why a CT series could not be read. Every message names the file(s), the tag and a remedy.
#[derive(Debug, thiserror::Error)]
pub enum DicomError {
    #[error("{}: cannot read the file ({source}); check that it exists and is readable", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error(
        "{}: {len} bytes without the DICOM 'DICM' marker (at byte 128, or 0), yet {}: it may be a \
         truncated or damaged CT slice, and skipping it could silently shorten the volume; \
         re-copy or re-export the series, or remove this file from the folder",
        path.display(),
        if *named_dicom { "named like a DICOM file" } else { "too short for a DICOM header and without an extension" }
    )]
    NotPart10 { path: PathBuf, len: usize, named_dicom: bool },

    #[error(
        "{}: has the DICOM 'DICM' marker but cannot be parsed ({detail}); the file is truncated \
         or damaged: re-export the series, or remove this file from the folder",
        path.display()
    )]
    Corrupt { path: PathBuf, detail: String },

    #[error(
        "no CT image slices among the {examined} file(s) looked at ({not_dicom} not DICOM, {not_ct} \
         DICOM but not CT{example}): none has {} = CT or {} = {}; put the patient's CT series \
         (one DICOM file per slice) in this folder",
        attr::MODALITY,
        attr::SOP_CLASS_UID,
        uids::CT_IMAGE_STORAGE
    )]
    NoCtSlices {
        examined: usize,
        not_dicom: usize,
        not_ct: usize,
        /// `", e.g. FILE: REASON"` for the first skipped file, or empty.
        example: String,
    },

    #[error(
        "the CT slices belong to {} different series by {}: {}; keep exactly one CT series per \
         patient folder (move the other series' files elsewhere)",
        series.len(), attr::SERIES_INSTANCE_UID, describe_series(series)
    )]
    MixedSeries {
        /// (SeriesInstanceUID, number of slices, one file of that series), largest first.
        series: Vec<(String, usize, PathBuf)>,
    },

    #[error(
        "{}: required tag {tag} is missing, so this CT slice cannot be placed or decoded; \
         re-export the series with complete image attributes, or remove this file",
        path.display()
    )]
    MissingTag { path: PathBuf, tag: TagRef },

    #[error(
        "{}: tag {tag} has value '{value}', expected {expected}; fix or re-export this file",
        path.display()
    )]
    BadValue { path: PathBuf, tag: TagRef, value: String, expected: &'static str },

    #[error(
        "{}: {} = {uid} ({name}) is not supported: only uncompressed native encodings are \
         (Implicit VR Little Endian, Explicit VR Little Endian, Deflated Explicit VR Little \
         Endian, Explicit VR Big Endian); decompress the series first, e.g. `gdcmconv --raw IN OUT` \
         or `dcmdjpeg IN OUT` (JPEG) / `dcmdrle IN OUT` (RLE)",
        path.display(), attr::TRANSFER_SYNTAX_UID
    )]
    UnsupportedTransferSyntax { path: PathBuf, uid: String, name: &'static str },

    #[error(
        "{}: multi-frame image ({} = {frames}, e.g. Enhanced CT) is not supported; convert it \
         to one file per slice first, e.g. with dcm4che `emf2sf` or dcmtk/gdcm equivalents",
        path.display(), attr::NUMBER_OF_FRAMES
    )]
    MultiFrame { path: PathBuf, frames: u32 },

    #[error(
        "{}: {tag} = {value} differs from {reference_value} in {}; all slices of one series must \
         share it, so the folder probably mixes reconstructions: keep one series per patient folder",
        path.display(), reference.display()
    )]
    Inconsistent { path: PathBuf, reference: PathBuf, tag: TagRef, value: String, reference_value: String },

    #[error(
        "{} and {} lie at the same slice position {position_mm:.3} mm along the slice normal \
         ({}); remove the duplicate file (a slice exported twice, or two series sharing one {})",
        first.display(), second.display(), attr::IMAGE_POSITION_PATIENT, attr::SERIES_INSTANCE_UID
    )]
    DuplicatePosition { first: PathBuf, second: PathBuf, position_mm: f64 },

    #[error(
        "non-uniform slice spacing (from {}): the gap between {} and {} is {gap_mm:.4} mm but \
         the median gap is {median_mm:.4} mm; {n_bad} of {n_gaps} gaps differ from the median by \
         more than 1%. Slices are missing or the series has variable spacing: re-export the \
         complete series or resample it to uniform spacing",
        attr::IMAGE_POSITION_PATIENT, before.display(), after.display()
    )]
    NonUniformSpacing { before: PathBuf, after: PathBuf, gap_mm: f64, median_mm: f64, n_bad: usize, n_gaps: usize },

    #[error(
        "{}: {} row and column cosines are not orthogonal unit vectors (angle {angle_deg:.3}° \
         instead of 90°, lengths {row_len:.4} and {col_len:.4}); the image geometry is invalid: \
         re-export the series",
        path.display(), attr::IMAGE_ORIENTATION_PATIENT
    )]
    NonOrthogonalOrientation { path: PathBuf, angle_deg: f64, row_len: f64, col_len: f64 },

    #[error(
        "{}: the step from {} ({}) is tilted {angle_deg:.2}° away from the slice normal given by \
         {} (gantry tilt or sheared stack); tilted series are not supported: resample to an \
         orthogonal grid first, e.g. `dcm2niix` gantry-tilt correction or 3D Slicer's \
         'Acquisition transform' (harden)",
        path.display(), previous.display(), attr::IMAGE_POSITION_PATIENT,
        attr::IMAGE_ORIENTATION_PATIENT
    )]
    GantryTilt { path: PathBuf, previous: PathBuf, angle_deg: f64 },

    #[error(
        "{}: {tag} = {value} is not supported (supported: {supported}); convert the series to \
         single-sample 8- or 16-bit grayscale, e.g. `gdcmconv --raw`",
        path.display()
    )]
    UnsupportedPixelEncoding { path: PathBuf, tag: TagRef, value: String, supported: &'static str },

    #[error(
        "{}: {} holds {found} bytes but {} × {} × {} × {}/8 = {rows} × {cols} × 1 × {bits_allocated}/8 \
         needs {expected}{}; {}",
        path.display(), attr::PIXEL_DATA, attr::ROWS, attr::COLUMNS, attr::SAMPLES_PER_PIXEL,
        attr::BITS_ALLOCATED,
        if expected % 2 == 1 { " (one more with the even-length pad byte)" } else { "" },
        if found < expected {
            "the file is truncated, or the pixel-format tags are wrong: re-export it"
        } else {
            "the pixel-format tags do not describe the pixel data (e.g. BitsAllocated 8 over 16-bit \
             data), which would decode as garbage: fix or re-export this file"
        }
    )]
    PixelDataLength { path: PathBuf, found: usize, expected: usize, rows: u32, cols: u32, bits_allocated: u32 },
}

fn describe_series(series: &[(String, usize, PathBuf)]) -> String {
    series
        .iter()
        .map(|(uid, n, example)| format!("{uid} ({n} slices, e.g. {})", example.display()))
        .collect::<Vec<_>>()
        .join(", ")
}

// Tolerances. Orientation cosines are written as decimal strings (DS) with ~6 digits, so
// "equal" must allow for text rounding but stay far below anything geometrically visible.
/// Row/column cosines: unit length and orthogonality, as |len − 1| and |cos angle|.
const ORTHO_TOL: f64 = 1e-3;
/// Same orientation / pixel spacing across slices (absolute for cosines, relative for mm).
const SAME_TOL: f64 = 1e-4;
/// Two slices closer than this along the normal are the same slice.
const DUPLICATE_TOL_MM: f64 = 1e-3;
/// Default allowed deviation of any gap from the median gap, and of the in-plane drift per
/// gap, as a fraction of the gap (SPEC: 1%).
pub const DEFAULT_GAP_TOLERANCE: f64 = 0.01;

/// Read the CT series among `files` (a patient folder's listing, any order).
///
/// Non-DICOM files and DICOM files that are not CT images are skipped and listed in
/// [`CtSeries::skipped`]; anything that would make the volume wrong is an error.
pub fn read_ct_series(files: &[PathBuf], gap_tolerance: f64) -> Result<CtSeries, DicomError> {
    // Path order makes "the first slice" in messages (and error choice) deterministic,
    // whatever order the caller listed the folder in.
    let mut files = files.to_vec();
    files.sort();

    // Files decode independently: read them in parallel, then keep path order (the first
    // error in path order wins, so messages do not depend on thread timing).
    let kinds: Vec<Result<FileKind, DicomError>> = files.par_iter().map(|path| read_file(path)).collect();
    let mut skipped = Vec::new();
    let mut slices = Vec::new();
    for (path, kind) in files.iter().zip(kinds) {
        match kind? {
            FileKind::Skipped(reason) => skipped.push((path.clone(), reason)),
            FileKind::Ct(slice) => slices.push(*slice),
        }
    }
    if slices.is_empty() {
        return Err(no_ct_slices(files.len(), &skipped));
    }
    check_single_series(&slices)?;
    check_consistent(&slices)?;
    let axes = Axes::from_iop(&slices[0].iop);
    let (slices, positions) = sort_along_normal(slices, &axes);
    check_no_duplicates(&slices, &positions)?;
    check_no_tilt(&slices, &axes, gap_tolerance)?;
    let gap = slice_gap(&slices, &positions, gap_tolerance)?;
    Ok(assemble(slices, positions, gap, &axes, skipped))
}

// ---------------------------------------------------------------------------------------
// One file

/// What one file turned out to be.
enum FileKind {
    Skipped(String),
    Ct(Box<CtSlice>),
}

/// One CT slice, already converted to HU (rescale is per slice, so it is applied here).
struct CtSlice {
    path: PathBuf,
    series_uid: String,
    transfer_syntax: String,
    rows: u32,
    cols: u32,
    /// As in DICOM: `[row spacing (between rows), column spacing (between columns)]`.
    pixel_spacing: [f64; 2],
    ipp: [f64; 3],
    iop: [f64; 6],
    slice_thickness: Option<f64>,
    spacing_between_slices: Option<f64>,
    hu: Vec<i16>,
    rounding_max_abs: f64,
}

/// Explicit VR Big Endian: retired from the standard (hence deprecated in the dictionary
/// crate) but still found in old archives, and the SPEC supports it.
const EXPLICIT_VR_BIG_ENDIAN: &str = "1.2.840.10008.1.2.2";

/// Native (uncompressed) transfer syntaxes: the only ones whose pixel data we decode.
const NATIVE_TRANSFER_SYNTAXES: [&str; 4] = [
    uids::IMPLICIT_VR_LITTLE_ENDIAN,
    uids::EXPLICIT_VR_LITTLE_ENDIAN,
    uids::DEFLATED_EXPLICIT_VR_LITTLE_ENDIAN,
    EXPLICIT_VR_BIG_ENDIAN,
];

fn read_file(path: &Path) -> Result<FileKind, DicomError> {
    let bytes = std::fs::read(path).map_err(|source| DicomError::Io { path: path.to_path_buf(), source })?;
    // Part 10 files start with "DICM" after a 128-byte preamble; some writers omit the
    // preamble. Without the marker it is not a DICOM file we can trust (README, XML, ...).
    let Some(start) = dicm_offset(&bytes) else {
        return without_marker(path, bytes.len());
    };
    let bytes = &bytes[start..];
    // The meta group reader trusts length fields too (see `length_guard`).
    length_guard::check(bytes, None).map_err(|detail| corrupt(path, &detail))?;
    let meta = FileMetaTable::from_reader(bytes).map_err(|e| corrupt(path, &error_chain(&e)))?;
    let ts = meta.transfer_syntax().to_string();

    if !NATIVE_TRANSFER_SYNTAXES.contains(&ts.as_str()) {
        return classify_undecodable(path, bytes, &meta, ts);
    }
    let obj = match parse(path, bytes, None, &ts) {
        Ok(obj) => obj,
        // A damaged file that its meta group says is not a CT image (a truncated RT plan,
        // a broken DICOMDIR) cannot make the CT volume wrong: skip it. One that may be a CT
        // slice is an error, since skipping it could silently shorten the volume.
        Err(DicomError::Corrupt { detail, .. }) if !meta_says_ct(&meta) => {
            return Ok(FileKind::Skipped(format!(
                "damaged DICOM file, not a CT image by its MediaStorageSOPClassUID (0002,0002) \
                 '{}': {detail}",
                printable(meta.media_storage_sop_class_uid())
            )));
        }
        Err(e) => return Err(e),
    };
    if let Some(reason) = not_ct_reason(&obj, &meta) {
        return Ok(FileKind::Skipped(reason));
    }
    ct_slice(path, &obj, ts).map(|s| FileKind::Ct(Box::new(s)))
}

/// Extensions that say "a DICOM file" (compared ignoring case).
const DICOM_EXTENSIONS: [&str; 4] = ["dcm", "dicom", "dic", "ima"];
/// The 128-byte preamble and the 4-byte "DICM" marker.
const PART10_HEADER_BYTES: usize = 132;

/// A file without the "DICM" marker: skipped when it clearly is something else, an error when
/// it may be a damaged slice (see the module doc).
fn without_marker(path: &Path, len: usize) -> Result<FileKind, DicomError> {
    let extension = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
    let named_dicom = extension.as_deref().is_some_and(|e| DICOM_EXTENSIONS.contains(&e));
    let too_short = len < PART10_HEADER_BYTES;
    if named_dicom || (too_short && extension.is_none()) {
        return Err(DicomError::NotPart10 { path: path.to_path_buf(), len, named_dicom });
    }
    Ok(FileKind::Skipped(format!("{NOT_DICOM} (no 'DICM' marker at byte 128 or 0)")))
}

/// Byte offset of the "DICM" magic, if the file has it where Part 10 puts it.
fn dicm_offset(bytes: &[u8]) -> Option<usize> {
    if bytes.get(128..132) == Some(b"DICM") {
        Some(128)
    } else if bytes.get(0..4) == Some(b"DICM") {
        Some(0)
    } else {
        None
    }
}

/// A file in a transfer syntax we cannot decode: an error if it is a CT slice (the series
/// would have a hole), skipped otherwise (e.g. a JPEG-compressed CR in the same folder).
fn classify_undecodable(path: &Path, bytes: &[u8], meta: &FileMetaTable, ts: String) -> Result<FileKind, DicomError> {
    let unsupported = || DicomError::UnsupportedTransferSyntax {
        path: path.to_path_buf(),
        name: transfer_syntax_name(&ts),
        uid: ts.clone(),
    };
    // Encapsulated syntaxes still encode the header as explicit VR LE, so the attributes
    // before PixelData are readable; an unknown (private) syntax is not, and then the
    // file meta's SOP class is all we have.
    match parse(path, bytes, Some(tags::PIXEL_DATA), &ts) {
        Ok(obj) => {
            if let Some(reason) = not_ct_reason(&obj, meta) {
                return Ok(FileKind::Skipped(reason));
            }
            // "Multi-frame" is the more fundamental problem: decompressing would not fix it.
            check_single_frame(path, &obj)?;
            Err(unsupported())
        }
        Err(_) if meta_says_ct(meta) => Err(unsupported()),
        Err(_) => Ok(FileKind::Skipped(format!(
            "unreadable transfer syntax {ts} and not a CT image by its \
             MediaStorageSOPClassUID (0002,0002) '{}'",
            printable(meta.media_storage_sop_class_uid())
        ))),
    }
}

/// Whether the file meta group allows this file to be a CT image (an empty SOP class
/// could be anything, so it counts as CT: we would rather stop than drop a slice).
fn meta_says_ct(meta: &FileMetaTable) -> bool {
    let sop = meta.media_storage_sop_class_uid();
    sop.is_empty() || sop == uids::CT_IMAGE_STORAGE || sop == uids::ENHANCED_CT_IMAGE_STORAGE
}

/// Parse the data set (after the "DICM" magic), optionally stopping before `until`.
fn parse(path: &Path, bytes: &[u8], until: Option<Tag>, ts: &str) -> Result<InMemDicomObject, DicomError> {
    // The parser sizes (and zero-fills) a buffer from each element's declared length before
    // reading it: one damaged length field costs seconds and gigabytes. Check first.
    if let Some(encoding) = length_guard::encoding_of(ts) {
        length_guard::check(bytes, Some(encoding)).map_err(|detail| corrupt(path, &detail))?;
    }
    let mut options = OpenFileOptions::new().read_preamble(ReadPreamble::Never);
    if let Some(tag) = until {
        options = options.read_until(tag);
    }
    // The parser is third-party code fed with arbitrary bytes: a panic in it must become
    // an error for this file, not abort the whole pipeline.
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| options.from_reader(bytes)));
    match result {
        Ok(Ok(file)) => Ok(file.into_inner()),
        Ok(Err(e)) => Err(corrupt(path, &read_error_detail(&e))),
        Err(_) => Err(corrupt(path, "the DICOM parser crashed on it")),
    }
}

fn corrupt(path: &Path, detail: &str) -> DicomError {
    DicomError::Corrupt { path: path.to_path_buf(), detail: detail.to_string() }
}

/// A parse error's description without data values: `UnexpectedToken` prints the token,
/// which can hold any element's value (a patient name, say), so it is summarised instead.
fn read_error_detail(e: &ReadError) -> String {
    if matches!(e, ReadError::UnexpectedToken { .. }) {
        "unexpected data element structure".into()
    } else {
        error_chain(e)
    }
}

/// "outer: cause: root cause", capped so a pathological message stays one line.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(": ");
        text.push_str(&s.to_string());
        source = s.source();
    }
    truncate(&text, 300)
}

/// `None` if the object is a CT image (Modality CT, or CT Image Storage SOP class),
/// otherwise why it is skipped.
fn not_ct_reason(obj: &InMemDicomObject, meta: &FileMetaTable) -> Option<String> {
    let modality = text(obj, tags::MODALITY);
    let sop_class = text(obj, tags::SOP_CLASS_UID).unwrap_or_else(|| meta.media_storage_sop_class_uid().to_string());
    if modality.as_deref() == Some("CT") || sop_class == uids::CT_IMAGE_STORAGE {
        return None;
    }
    let modality = match modality {
        Some(m) => format!("is '{}'", printable(&m)),
        None => "is missing".into(),
    };
    Some(format!(
        "not a CT image: {} {modality}, {} is '{}'",
        attr::MODALITY,
        attr::SOP_CLASS_UID,
        printable(&sop_class)
    ))
}

/// Everything we need from one CT slice, validated, with pixels converted to HU.
fn ct_slice(path: &Path, obj: &InMemDicomObject, ts: String) -> Result<CtSlice, DicomError> {
    // Multi-frame first: Enhanced CT keeps its geometry in functional groups, so checking
    // it for PixelSpacing etc. would give a misleading "missing tag" error.
    check_single_frame(path, obj)?;
    let format = pixel_format(path, obj)?;
    let rows = required_u32(path, obj, attr::ROWS)?;
    let cols = required_u32(path, obj, attr::COLUMNS)?;
    let pixel_spacing = required_f64s::<2>(path, obj, attr::PIXEL_SPACING)?;
    if pixel_spacing.iter().any(|&s| s <= 0.0) {
        return Err(bad_value(path, obj, attr::PIXEL_SPACING, "two positive numbers (mm)"));
    }
    let ipp = required_f64s::<3>(path, obj, attr::IMAGE_POSITION_PATIENT)?;
    let iop = required_f64s::<6>(path, obj, attr::IMAGE_ORIENTATION_PATIENT)?;
    check_orthonormal(path, &iop)?;
    let rescale = rescale(path, obj)?;

    let big_endian = ts == EXPLICIT_VR_BIG_ENDIAN;
    let stored = stored_values(path, obj, &format, big_endian, [rows, cols])?;
    let (hu, rounding_max_abs) = to_hu(&stored, rescale);

    Ok(CtSlice {
        path: path.to_path_buf(),
        series_uid: text(obj, tags::SERIES_INSTANCE_UID).unwrap_or_else(|| "(missing)".into()),
        transfer_syntax: ts,
        rows,
        cols,
        pixel_spacing,
        ipp,
        iop,
        slice_thickness: optional_positive(path, obj, attr::SLICE_THICKNESS),
        spacing_between_slices: optional_positive(path, obj, attr::SPACING_BETWEEN_SLICES),
        hu,
        rounding_max_abs,
    })
}

fn check_single_frame(path: &Path, obj: &InMemDicomObject) -> Result<(), DicomError> {
    // NumberOfFrames absent or empty means one frame.
    match text(obj, tags::NUMBER_OF_FRAMES) {
        None => Ok(()),
        Some(s) => match s.trim().parse::<u32>() {
            Ok(0 | 1) => Ok(()),
            Ok(frames) => Err(DicomError::MultiFrame { path: path.to_path_buf(), frames }),
            Err(_) => Err(bad_value(path, obj, attr::NUMBER_OF_FRAMES, "an integer")),
        },
    }
}

/// How stored pixel values are laid out.
struct PixelFormat {
    bits_allocated: u32,
    bits_stored: u32,
    signed: bool,
}

fn pixel_format(path: &Path, obj: &InMemDicomObject) -> Result<PixelFormat, DicomError> {
    let unsupported = |tag: TagRef, value: String, supported: &'static str| DicomError::UnsupportedPixelEncoding {
        path: path.to_path_buf(),
        tag,
        value,
        supported,
    };
    // SamplesPerPixel and PhotometricInterpretation are Type 1, but when absent the only
    // sensible reading of a CT slice is single-sample grayscale, so we assume it.
    let samples = optional_u32(path, obj, attr::SAMPLES_PER_PIXEL)?.unwrap_or(1);
    if samples != 1 {
        return Err(unsupported(attr::SAMPLES_PER_PIXEL, samples.to_string(), "1"));
    }
    // MONOCHROME1 only inverts the *display*; HU come from the stored values either way
    // (pydicom's pixel_array does not invert it either).
    if let Some(pi) = text(obj, tags::PHOTOMETRIC_INTERPRETATION) {
        if pi != "MONOCHROME1" && pi != "MONOCHROME2" {
            return Err(unsupported(attr::PHOTOMETRIC_INTERPRETATION, printable(&pi), "MONOCHROME1, MONOCHROME2"));
        }
    }
    let bits_allocated = required_u32(path, obj, attr::BITS_ALLOCATED)?;
    if bits_allocated != 8 && bits_allocated != 16 {
        return Err(unsupported(attr::BITS_ALLOCATED, bits_allocated.to_string(), "8, 16"));
    }
    let bits_stored = optional_u32(path, obj, attr::BITS_STORED)?.unwrap_or(bits_allocated);
    if bits_stored == 0 || bits_stored > bits_allocated {
        return Err(unsupported(attr::BITS_STORED, bits_stored.to_string(), "1 to BitsAllocated"));
    }
    // CT images store their bits from bit 0 up (HighBit = BitsStored − 1); any other HighBit
    // means the stored value sits elsewhere in the word, which this decoder does not do.
    if let Some(high_bit) = optional_u32(path, obj, attr::HIGH_BIT)? {
        if high_bit + 1 != bits_stored {
            return Err(unsupported(attr::HIGH_BIT, high_bit.to_string(), "BitsStored − 1"));
        }
    }
    let signed = match required_u32(path, obj, attr::PIXEL_REPRESENTATION)? {
        0 => false,
        1 => true,
        other => return Err(unsupported(attr::PIXEL_REPRESENTATION, other.to_string(), "0 (unsigned), 1 (signed)")),
    };
    Ok(PixelFormat { bits_allocated, bits_stored, signed })
}

/// RescaleSlope and RescaleIntercept, defaulting to 1 and 0 (SPEC).
#[derive(Clone, Copy)]
struct Rescale {
    slope: f64,
    intercept: f64,
}

fn rescale(path: &Path, obj: &InMemDicomObject) -> Result<Rescale, DicomError> {
    let slope = optional_f64(path, obj, attr::RESCALE_SLOPE)?;
    // A Modality LUT instead of a linear rescale would silently give wrong HU.
    if slope.is_none() && obj.get(tags::MODALITY_LUT_SEQUENCE).is_some() {
        return Err(DicomError::UnsupportedPixelEncoding {
            path: path.to_path_buf(),
            tag: attr::MODALITY_LUT_SEQUENCE,
            value: "present (no RescaleSlope)".into(),
            supported: "a linear RescaleSlope/RescaleIntercept",
        });
    }
    let slope = slope.unwrap_or(1.0);
    if slope == 0.0 {
        return Err(bad_value(path, obj, attr::RESCALE_SLOPE, "a non-zero number"));
    }
    let intercept = optional_f64(path, obj, attr::RESCALE_INTERCEPT)?.unwrap_or(0.0);
    Ok(Rescale { slope, intercept })
}

/// Stored pixel values as pydicom's `pixel_array` gives them, after checking that PixelData
/// holds exactly Rows × Columns × BitsAllocated/8 bytes (one sample per pixel, one frame).
fn stored_values(
    path: &Path,
    obj: &InMemDicomObject,
    format: &PixelFormat,
    big_endian: bool,
    [rows, cols]: [u32; 2],
) -> Result<Vec<i32>, DicomError> {
    let element = obj
        .get(tags::PIXEL_DATA)
        .ok_or_else(|| DicomError::MissingTag { path: path.to_path_buf(), tag: attr::PIXEL_DATA })?;
    let raw = match element.value() {
        Value::Primitive(p) => file_order_bytes(p, big_endian).ok_or_else(|| DicomError::BadValue {
            path: path.to_path_buf(),
            tag: attr::PIXEL_DATA,
            value: "a non-binary value".into(),
            expected: "binary pixel data (OB/OW)",
        })?,
        // Cannot happen with a native transfer syntax unless the file lies about it.
        _ => {
            return Err(DicomError::BadValue {
                path: path.to_path_buf(),
                tag: attr::PIXEL_DATA,
                value: "encapsulated (compressed) fragments".into(),
                expected: "native pixel data, as the transfer syntax declares",
            })
        }
    };
    let bytes_per_pixel = format.bits_allocated as usize / 8;
    let expected = rows as usize * cols as usize * bytes_per_pixel;
    // Values have even length, so an odd pixel count of 8-bit data carries one pad byte.
    let padded = expected + expected % 2;
    if raw.len() != expected && raw.len() != padded {
        return Err(DicomError::PixelDataLength {
            path: path.to_path_buf(),
            found: raw.len(),
            expected,
            rows,
            cols,
            bits_allocated: format.bits_allocated,
        });
    }
    Ok(decode_pixels(&raw[..expected], format, big_endian))
}

/// The pixel data bytes as they were in the file. The parser turns OW into `u16` values
/// (already swapped to host order); pydicom works on the file's bytes, so we go back to
/// those and decode once, in the transfer syntax's byte order, whatever VR was used.
fn file_order_bytes(value: &PrimitiveValue, big_endian: bool) -> Option<Cow<'_, [u8]>> {
    let words = |iter: &mut dyn Iterator<Item = [u8; 2]>| -> Cow<'_, [u8]> { Cow::Owned(iter.flatten().collect()) };
    match value {
        PrimitiveValue::Empty => Some(Cow::Borrowed(&[])),
        PrimitiveValue::U8(bytes) => Some(Cow::Borrowed(&bytes[..])),
        PrimitiveValue::U16(values) => {
            Some(words(&mut values.iter().map(|v| if big_endian { v.to_be_bytes() } else { v.to_le_bytes() })))
        }
        PrimitiveValue::I16(values) => {
            Some(words(&mut values.iter().map(|v| if big_endian { v.to_be_bytes() } else { v.to_le_bytes() })))
        }
        _ => None,
    }
}

/// Decode `bits_allocated`-bit samples. Signed data with BitsStored < BitsAllocated is
/// sign-extended from bit BitsStored−1 (shift left, arithmetic shift right); unsigned data
/// is masked to its BitsStored low bits. Both as pydicom 3 does.
fn decode_pixels(raw: &[u8], format: &PixelFormat, big_endian: bool) -> Vec<i32> {
    let unused_bits = format.bits_allocated - format.bits_stored;
    match (format.bits_allocated, format.signed) {
        (8, false) => raw.iter().map(|&b| i32::from(b & (0xFF >> unused_bits))).collect(),
        (8, true) => raw.iter().map(|&b| i32::from(((b as i8) << unused_bits) >> unused_bits)).collect(),
        (_, signed) => raw
            .chunks_exact(2)
            .map(|pair| {
                let bytes = [pair[0], pair[1]];
                let word = if big_endian { u16::from_be_bytes(bytes) } else { u16::from_le_bytes(bytes) };
                if signed {
                    i32::from(((word as i16) << unused_bits) >> unused_bits)
                } else {
                    i32::from(word & (0xFFFF >> unused_bits))
                }
            })
            .collect(),
    }
}

/// HU per voxel (rounded, saturated) and the largest loss that rounding/saturation caused.
fn to_hu(stored: &[i32], rescale: Rescale) -> (Vec<i16>, f64) {
    let mut max_loss = 0.0_f64;
    let hu = stored
        .iter()
        .map(|&v| {
            let exact = f64::from(v) * rescale.slope + rescale.intercept;
            let rounded = exact.round().clamp(f64::from(i16::MIN), f64::from(i16::MAX));
            max_loss = max_loss.max((exact - rounded).abs());
            rounded as i16
        })
        .collect();
    (hu, max_loss)
}

// ---------------------------------------------------------------------------------------
// Attribute access. Everything goes through the value's text form: it is what DS/IS
// attributes are, and the parser renders binary US/UL the same way, so one parser serves.

/// The attribute's value as trimmed text; `None` if absent, empty or not a primitive.
fn text(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let value = obj.get(tag)?.value().to_str().ok()?;
    let value = value.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!value.is_empty()).then(|| value.to_string())
}

fn bad_value(path: &Path, obj: &InMemDicomObject, tag: TagRef, expected: &'static str) -> DicomError {
    DicomError::BadValue {
        path: path.to_path_buf(),
        tag,
        value: printable(&text(obj, tag.tag).unwrap_or_default()),
        expected,
    }
}

fn missing(path: &Path, tag: TagRef) -> DicomError {
    DicomError::MissingTag { path: path.to_path_buf(), tag }
}

/// Finite numbers of a multi-valued attribute (`a\b\c`).
fn numbers(s: &str) -> Option<Vec<f64>> {
    s.split('\\').map(|part| part.trim().parse::<f64>().ok().filter(|v| v.is_finite())).collect()
}

fn optional_u32(path: &Path, obj: &InMemDicomObject, tag: TagRef) -> Result<Option<u32>, DicomError> {
    match text(obj, tag.tag) {
        None => Ok(None),
        Some(s) => s
            .split('\\')
            .next()
            .and_then(|v| v.trim().parse::<u32>().ok())
            .map(Some)
            .ok_or_else(|| bad_value(path, obj, tag, "a non-negative integer")),
    }
}

fn required_u32(path: &Path, obj: &InMemDicomObject, tag: TagRef) -> Result<u32, DicomError> {
    let v = optional_u32(path, obj, tag)?.ok_or_else(|| missing(path, tag))?;
    // Rows/Columns of 0 cannot hold an image; BitsAllocated etc. are checked by the caller.
    if v == 0 && (tag == attr::ROWS || tag == attr::COLUMNS) {
        return Err(bad_value(path, obj, tag, "a positive integer"));
    }
    Ok(v)
}

fn optional_f64(path: &Path, obj: &InMemDicomObject, tag: TagRef) -> Result<Option<f64>, DicomError> {
    match text(obj, tag.tag) {
        None => Ok(None),
        Some(s) => match numbers(&s).as_deref() {
            Some([v]) => Ok(Some(*v)),
            _ => Err(bad_value(path, obj, tag, "one finite number")),
        },
    }
}

/// An informative positive number: zero, negative (seen in the wild on reformats) or
/// unparsable counts as absent rather than failing the whole series.
fn optional_positive(path: &Path, obj: &InMemDicomObject, tag: TagRef) -> Option<f64> {
    optional_f64(path, obj, tag).ok().flatten().filter(|&v| v > 0.0)
}

fn required_f64s<const N: usize>(path: &Path, obj: &InMemDicomObject, tag: TagRef) -> Result<[f64; N], DicomError> {
    let s = text(obj, tag.tag).ok_or_else(|| missing(path, tag))?;
    let expected = match N {
        2 => "2 finite numbers separated by '\\'",
        3 => "3 finite numbers separated by '\\'",
        _ => "6 finite numbers separated by '\\'",
    };
    numbers(&s).and_then(|v| <[f64; N]>::try_from(v).ok()).ok_or_else(|| bad_value(path, obj, tag, expected))
}

/// Keep only plain printable ASCII and cap the length: values go into one-line messages.
fn printable(s: &str) -> String {
    let clean: String = s.chars().map(|c| if c.is_ascii_graphic() || c == ' ' { c } else { '?' }).collect();
    truncate(&clean, 80)
}

fn truncate(s: &str, max_chars: usize) -> String {
    if s.chars().count() <= max_chars {
        s.to_string()
    } else {
        let cut: String = s.chars().take(max_chars).collect();
        format!("{cut}...")
    }
}

/// Human name of a transfer syntax for the "unsupported" message (dicom-dictionary-std
/// only exposes the names behind a feature we do not enable).
fn transfer_syntax_name(uid: &str) -> &'static str {
    match uid {
        "1.2.840.10008.1.2.1.98" => "Encapsulated Uncompressed Explicit VR Little Endian",
        "1.2.840.10008.1.2.4.50" => "JPEG Baseline (Process 1)",
        "1.2.840.10008.1.2.4.51" => "JPEG Extended (Process 2 & 4)",
        "1.2.840.10008.1.2.4.57" => "JPEG Lossless, Non-Hierarchical (Process 14)",
        "1.2.840.10008.1.2.4.70" => "JPEG Lossless, Non-Hierarchical, First-Order Prediction",
        "1.2.840.10008.1.2.4.80" => "JPEG-LS Lossless Image Compression",
        "1.2.840.10008.1.2.4.81" => "JPEG-LS Lossy (Near-Lossless) Image Compression",
        "1.2.840.10008.1.2.4.90" => "JPEG 2000 Image Compression (Lossless Only)",
        "1.2.840.10008.1.2.4.91" => "JPEG 2000 Image Compression",
        "1.2.840.10008.1.2.4.92" => "JPEG 2000 Part 2 Multi-component Image Compression (Lossless Only)",
        "1.2.840.10008.1.2.4.93" => "JPEG 2000 Part 2 Multi-component Image Compression",
        "1.2.840.10008.1.2.4.110" => "JPEG XL Lossless",
        "1.2.840.10008.1.2.4.111" => "JPEG XL JPEG Recompression",
        "1.2.840.10008.1.2.4.112" => "JPEG XL",
        "1.2.840.10008.1.2.4.201" => "High-Throughput JPEG 2000 Image Compression (Lossless Only)",
        "1.2.840.10008.1.2.4.202" => "High-Throughput JPEG 2000 with RPCL Options Image Compression (Lossless Only)",
        "1.2.840.10008.1.2.4.203" => "High-Throughput JPEG 2000 Image Compression",
        "1.2.840.10008.1.2.5" => "RLE Lossless",
        "1.2.840.10008.1.2.8.1" => "Deflated Image Frame Compression",
        _ => "unknown or private transfer syntax",
    }
}

// ---------------------------------------------------------------------------------------
// Geometry

/// `a` over its length (itself when it has none).
fn unit(a: DVec3) -> DVec3 {
    let n = a.length();
    if n > 0.0 {
        a / n
    } else {
        a
    }
}

fn row_col(iop: &[f64; 6]) -> (DVec3, DVec3) {
    (DVec3::new(iop[0], iop[1], iop[2]), DVec3::new(iop[3], iop[4], iop[5]))
}

/// Index-axis directions in patient space: columns step along `row`, rows along `col`.
struct Axes {
    row: [f64; 3],
    col: [f64; 3],
    normal: [f64; 3],
}

impl Axes {
    /// From an orientation already checked by [`check_orthonormal`]; renormalised because
    /// DS text rounding leaves lengths like 0.999999.
    fn from_iop(iop: &[f64; 6]) -> Axes {
        let (row, col) = row_col(iop);
        let (row, col) = (unit(row), unit(col));
        Axes { row: row.to_array(), col: col.to_array(), normal: unit(row.cross(col)).to_array() }
    }
}

fn check_orthonormal(path: &Path, iop: &[f64; 6]) -> Result<(), DicomError> {
    let (row, col) = row_col(iop);
    let (row_len, col_len) = (row.length(), col.length());
    let cos = if row_len > 0.0 && col_len > 0.0 {
        row.dot(col) / (row_len * col_len)
    } else {
        1.0 // degenerate: report as parallel
    };
    if (row_len - 1.0).abs() > ORTHO_TOL || (col_len - 1.0).abs() > ORTHO_TOL || cos.abs() > ORTHO_TOL {
        return Err(DicomError::NonOrthogonalOrientation {
            path: path.to_path_buf(),
            angle_deg: cos.clamp(-1.0, 1.0).acos().to_degrees(),
            row_len,
            col_len,
        });
    }
    Ok(())
}

fn no_ct_slices(examined: usize, skipped: &[(PathBuf, String)]) -> DicomError {
    let not_dicom = skipped.iter().filter(|(_, reason)| reason.starts_with(NOT_DICOM)).count();
    let example = skipped
        .iter()
        .find(|(_, reason)| !reason.starts_with(NOT_DICOM))
        .or(skipped.first())
        .map(|(path, reason)| format!(", e.g. {}: {reason}", path.display()))
        .unwrap_or_default();
    DicomError::NoCtSlices { examined, not_dicom, not_ct: skipped.len() - not_dicom, example }
}

fn check_single_series(slices: &[CtSlice]) -> Result<(), DicomError> {
    let mut series: Vec<(String, usize, PathBuf)> = Vec::new();
    for s in slices {
        match series.iter_mut().find(|(uid, _, _)| *uid == s.series_uid) {
            Some(entry) => entry.1 += 1,
            None => series.push((s.series_uid.clone(), 1, s.path.clone())),
        }
    }
    if series.len() > 1 {
        series.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
        return Err(DicomError::MixedSeries { series });
    }
    Ok(())
}

/// Every slice must share the first slice's matrix size, pixel spacing and orientation:
/// the volume has one of each.
fn check_consistent(slices: &[CtSlice]) -> Result<(), DicomError> {
    let reference = &slices[0];
    let fmt_list = |v: &[f64]| v.iter().map(|x| format!("{x}")).collect::<Vec<_>>().join("\\");
    for s in &slices[1..] {
        let differs = |tag: TagRef, value: String, reference_value: String| DicomError::Inconsistent {
            path: s.path.clone(),
            reference: reference.path.clone(),
            tag,
            value,
            reference_value,
        };
        if s.rows != reference.rows {
            return Err(differs(attr::ROWS, s.rows.to_string(), reference.rows.to_string()));
        }
        if s.cols != reference.cols {
            return Err(differs(attr::COLUMNS, s.cols.to_string(), reference.cols.to_string()));
        }
        let spacing_differs =
            s.pixel_spacing.iter().zip(&reference.pixel_spacing).any(|(a, b)| (a - b).abs() > SAME_TOL * b.abs());
        if spacing_differs {
            return Err(differs(attr::PIXEL_SPACING, fmt_list(&s.pixel_spacing), fmt_list(&reference.pixel_spacing)));
        }
        let orientation_differs = s.iop.iter().zip(&reference.iop).any(|(a, b)| (a - b).abs() > SAME_TOL);
        if orientation_differs {
            return Err(differs(attr::IMAGE_ORIENTATION_PATIENT, fmt_list(&s.iop), fmt_list(&reference.iop)));
        }
    }
    Ok(())
}

/// Slices sorted by position along the normal (ascending), with those positions.
fn sort_along_normal(slices: Vec<CtSlice>, axes: &Axes) -> (Vec<CtSlice>, Vec<f64>) {
    let mut keyed: Vec<(f64, CtSlice)> =
        slices.into_iter().map(|s| (DVec3::from(s.ipp).dot(DVec3::from(axes.normal)), s)).collect();
    // Stable, so equal positions keep path order and the duplicate message is deterministic.
    keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
    let positions = keyed.iter().map(|(p, _)| *p).collect();
    (keyed.into_iter().map(|(_, s)| s).collect(), positions)
}

fn check_no_duplicates(slices: &[CtSlice], positions: &[f64]) -> Result<(), DicomError> {
    for k in 1..slices.len() {
        if positions[k] - positions[k - 1] < DUPLICATE_TOL_MM {
            return Err(DicomError::DuplicatePosition {
                first: slices[k - 1].path.clone(),
                second: slices[k].path.clone(),
                position_mm: positions[k],
            });
        }
    }
    Ok(())
}

/// Consecutive slices must be offset along the normal only: a sideways drift means a
/// gantry-tilted (sheared) stack, which a rectilinear volume would misplace.
fn check_no_tilt(slices: &[CtSlice], axes: &Axes, gap_tolerance: f64) -> Result<(), DicomError> {
    for pair in slices.windows(2) {
        let (step, normal) = (DVec3::from(pair[1].ipp) - DVec3::from(pair[0].ipp), DVec3::from(axes.normal));
        let along = step.dot(normal);
        let lateral = (step - normal * along).length();
        if lateral > gap_tolerance * along.abs() {
            return Err(DicomError::GantryTilt {
                path: pair[1].path.clone(),
                previous: pair[0].path.clone(),
                angle_deg: lateral.atan2(along.abs()).to_degrees(),
            });
        }
    }
    Ok(())
}

/// The median gap between consecutive slices, after checking every gap is within
/// `gap_tolerance` of it; for a single slice, the fallback described in the module doc.
fn slice_gap(slices: &[CtSlice], positions: &[f64], gap_tolerance: f64) -> Result<f64, DicomError> {
    if slices.len() == 1 {
        let s = &slices[0];
        return Ok(s.slice_thickness.or(s.spacing_between_slices).unwrap_or(1.0));
    }
    let gaps: Vec<f64> = positions.windows(2).map(|w| w[1] - w[0]).collect();
    let median = crate::kernels::stats::median(&gaps);
    let off = |g: f64| (g - median).abs() > gap_tolerance * median;
    let n_bad = gaps.iter().filter(|&&g| off(g)).count();
    if let Some(k) = gaps.iter().position(|&g| off(g)) {
        return Err(DicomError::NonUniformSpacing {
            before: slices[k].path.clone(),
            after: slices[k + 1].path.clone(),
            gap_mm: gaps[k],
            median_mm: median,
            n_bad,
            n_gaps: gaps.len(),
        });
    }
    Ok(median)
}

fn assemble(
    slices: Vec<CtSlice>,
    positions: Vec<f64>,
    gap: f64,
    axes: &Axes,
    skipped: Vec<(PathBuf, String)>,
) -> CtSeries {
    let first = &slices[0];
    let geometry = Geometry {
        dims: [first.cols as usize, first.rows as usize, slices.len()],
        // PixelSpacing is [between rows, between columns]: axis 0 (columns) uses [1].
        spacing_mm: [first.pixel_spacing[1], first.pixel_spacing[0], gap],
        origin_mm: first.ipp,
        direction: [axes.row, axes.col, axes.normal],
    };
    let slice_thickness_mm = first.slice_thickness;
    let transfer_syntax = first.transfer_syntax.clone();
    let hu_rounding_max_abs = slices.iter().map(|s| s.rounding_max_abs).fold(0.0, f64::max);
    let mut data = Vec::with_capacity(geometry.len());
    for s in slices {
        data.extend_from_slice(&s.hu);
    }
    CtSeries {
        hu: Volume { geometry, data },
        slice_positions_mm: positions,
        slice_gap_mm: gap,
        slice_thickness_mm,
        hu_rounding_max_abs,
        transfer_syntax,
        skipped,
    }
}
