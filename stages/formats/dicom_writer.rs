//! CT series → DICOM files (in memory). Owns the encoding of an HU volume as a standard
//! single-frame CT Image Storage series that our reader ([`super::dicom`]), pydicom and
//! viewers read back to the same HU and geometry.
//!
//! Encoding: explicit VR little endian; MONOCHROME2, 16 bits allocated and stored, signed
//! (PixelRepresentation 1); stored value = round(HU) + 1024, saturated to int16, with
//! RescaleSlope 1 and RescaleIntercept −1024 (so air at −1000 HU is stored as 24, and HU down
//! to −33792 survive). One file per slice, InstanceNumber 1… in slice order, named
//! `000001.dcm`….
//!
//! Geometry: ImagePositionPatient is the patient position of voxel (0, 0, k);
//! ImageOrientationPatient the directions of the column and row index axes; PixelSpacing
//! `[row spacing, column spacing]` = `[spacing_mm[1], spacing_mm[0]]` (conventions.md).
//! The slice axis must be row × column (as the reader sorts along it).
//!
//! Privacy: the only patient attributes written are PatientName and PatientID, both set to
//! the pseudonymous ID given (e.g. `LIDC-IDRI-0001`); everything else identifying is empty.

use crate::volume::Volume;
use dicom_core::value::PrimitiveValue;
use dicom_core::{DataElement, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use glam::DVec3;

/// HU = stored + this (RescaleSlope 1).
pub const RESCALE_INTERCEPT: f64 = -1024.0;

/// What a series carries besides its pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesMeta {
    /// Pseudonymous patient ID, written as PatientID and PatientName.
    pub patient_id: String,
    pub study_instance_uid: String,
    pub series_instance_uid: String,
    /// SOPInstanceUID of each slice, in slice order; empty: derived from the series UID
    /// ([`derived_uid`] of `"<series uid>/<k>"`).
    pub sop_instance_uids: Vec<String>,
    /// SliceThickness; `None`: the slice spacing.
    pub slice_thickness_mm: Option<f64>,
    pub series_description: String,
}

/// Why a series could not be written.
#[derive(Debug, thiserror::Error)]
pub enum DicomWriteError {
    #[error("{given} SOP instance UIDs for {slices} slices: give one per slice, or none to derive them")]
    SopUidCount { given: usize, slices: usize },
    #[error("{what} {uid:?} is not a valid DICOM UID (digits and dots, at most 64 characters)")]
    InvalidUid { what: &'static str, uid: String },
    #[error("a {cols}×{rows}-pixel slice cannot be written: Rows and Columns must be 1–65535")]
    SliceSize { cols: usize, rows: usize },
    #[error("the slice axis is not row × column (a mirrored volume): readers would flip it; reorder the slices")]
    LeftHanded,
    #[error("building the DICOM file meta group: {0}")]
    Meta(String),
    #[error("encoding slice {k}: {message}")]
    Encode { k: usize, message: String },
}

/// Stored pixel value of `hu`: rounded half away from zero, minus the intercept, saturated.
pub fn stored_value(hu: f64) -> i16 {
    (hu.round() - RESCALE_INTERCEPT).clamp(f64::from(i16::MIN), f64::from(i16::MAX)) as i16
}

/// A valid UID derived from `text`: `2.25.` and the decimal of the first 16 bytes of its
/// BLAKE3 hash (the ISO/IEC 9834-8 UUID-derived form).
pub fn derived_uid(text: &str) -> String {
    let hash = blake3::hash(text.as_bytes());
    let mut bytes = [0u8; 16];
    bytes.copy_from_slice(&hash.as_bytes()[..16]);
    format!("2.25.{}", u128::from_be_bytes(bytes))
}

/// Encode `hu` (any HU sample type: `i16`, `f32`, …) as one DICOM file per slice:
/// `(file name, bytes)` in slice order.
pub fn write_ct_series<T: Copy + Into<f64>>(
    hu: &Volume<T>,
    meta: &SeriesMeta,
) -> Result<Vec<(String, Vec<u8>)>, DicomWriteError> {
    let g = &hu.geometry;
    let [cols, rows, slices] = g.dims;
    let (Ok(cols16), Ok(rows16)) = (u16::try_from(cols), u16::try_from(rows)) else {
        return Err(DicomWriteError::SliceSize { cols, rows });
    };
    if cols16 == 0 || rows16 == 0 {
        return Err(DicomWriteError::SliceSize { cols, rows });
    }
    let normal = DVec3::from(g.direction[0]).cross(DVec3::from(g.direction[1]));
    if slices > 1 && normal.dot(DVec3::from(g.direction[2])) <= 0.0 {
        return Err(DicomWriteError::LeftHanded);
    }
    let sop_uids: Vec<String> = match meta.sop_instance_uids.len() {
        0 => (0..slices).map(|k| derived_uid(&format!("{}/{k}", meta.series_instance_uid))).collect(),
        n if n == slices => meta.sop_instance_uids.clone(),
        given => return Err(DicomWriteError::SopUidCount { given, slices }),
    };
    check_uid("StudyInstanceUID", &meta.study_instance_uid)?;
    check_uid("SeriesInstanceUID", &meta.series_instance_uid)?;
    for uid in &sop_uids {
        check_uid("SOPInstanceUID", uid)?;
    }
    let frame_of_reference = derived_uid(&format!("{}/frame of reference", meta.series_instance_uid));
    let thickness = meta.slice_thickness_mm.unwrap_or(g.spacing_mm[2]);
    let iop = [g.direction[0], g.direction[1]].concat();

    let mut files = Vec::with_capacity(slices);
    for (k, sop_uid) in sop_uids.iter().enumerate() {
        let ipp = g.voxel_to_patient_mm([0.0, 0.0, k as f64]);
        let slice = &hu.data[k * cols * rows..(k + 1) * cols * rows];
        let words: Vec<u16> = slice.iter().map(|&v| stored_value(v.into()) as u16).collect();
        let text = |tag: Tag, vr: VR, value: &str| DataElement::new(tag, vr, value);
        let us = |tag: Tag, value: u16| DataElement::new(tag, VR::US, PrimitiveValue::from(value));
        let elements: Vec<DataElement<InMemDicomObject>> = vec![
            text(tags::SPECIFIC_CHARACTER_SET, VR::CS, "ISO_IR 100"),
            text(tags::IMAGE_TYPE, VR::CS, "DERIVED\\SECONDARY\\AXIAL"),
            text(tags::SOP_CLASS_UID, VR::UI, uids::CT_IMAGE_STORAGE),
            text(tags::SOP_INSTANCE_UID, VR::UI, sop_uid),
            text(tags::STUDY_DATE, VR::DA, ""),
            text(tags::STUDY_TIME, VR::TM, ""),
            text(tags::ACCESSION_NUMBER, VR::SH, ""),
            text(tags::MODALITY, VR::CS, "CT"),
            text(tags::MANUFACTURER, VR::LO, "aret-pipe"),
            text(tags::REFERRING_PHYSICIAN_NAME, VR::PN, ""),
            text(tags::SERIES_DESCRIPTION, VR::LO, &meta.series_description),
            text(tags::PATIENT_NAME, VR::PN, &meta.patient_id),
            text(tags::PATIENT_ID, VR::LO, &meta.patient_id),
            text(tags::PATIENT_BIRTH_DATE, VR::DA, ""),
            text(tags::PATIENT_SEX, VR::CS, ""),
            text(tags::SLICE_THICKNESS, VR::DS, &ds(&[thickness])),
            // The series are of a supine patient entering head first, as the phantom's anatomy is.
            text(tags::PATIENT_POSITION, VR::CS, "HFS"),
            text(tags::STUDY_INSTANCE_UID, VR::UI, &meta.study_instance_uid),
            text(tags::SERIES_INSTANCE_UID, VR::UI, &meta.series_instance_uid),
            text(tags::STUDY_ID, VR::SH, ""),
            text(tags::SERIES_NUMBER, VR::IS, "1"),
            text(tags::INSTANCE_NUMBER, VR::IS, &(k + 1).to_string()),
            text(tags::IMAGE_POSITION_PATIENT, VR::DS, &ds(&ipp)),
            text(tags::IMAGE_ORIENTATION_PATIENT, VR::DS, &ds(&iop)),
            text(tags::FRAME_OF_REFERENCE_UID, VR::UI, &frame_of_reference),
            text(tags::POSITION_REFERENCE_INDICATOR, VR::LO, ""),
            text(tags::SLICE_LOCATION, VR::DS, &ds(&[DVec3::from(ipp).dot(normal)])),
            us(tags::SAMPLES_PER_PIXEL, 1),
            text(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, "MONOCHROME2"),
            us(tags::ROWS, rows16),
            us(tags::COLUMNS, cols16),
            text(tags::PIXEL_SPACING, VR::DS, &ds(&[g.spacing_mm[1], g.spacing_mm[0]])),
            us(tags::BITS_ALLOCATED, 16),
            us(tags::BITS_STORED, 16),
            us(tags::HIGH_BIT, 15),
            us(tags::PIXEL_REPRESENTATION, 1),
            text(tags::WINDOW_CENTER, VR::DS, "-600"),
            text(tags::WINDOW_WIDTH, VR::DS, "1500"),
            text(tags::RESCALE_INTERCEPT, VR::DS, &ds(&[RESCALE_INTERCEPT])),
            text(tags::RESCALE_SLOPE, VR::DS, "1"),
            text(tags::RESCALE_TYPE, VR::LO, "HU"),
            // OW values: the writer encodes them little-endian (the transfer syntax's order).
            DataElement::new(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(words.into())),
        ];
        let file = InMemDicomObject::from_element_iter(elements)
            .with_meta(FileMetaTableBuilder::new().transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN))
            .map_err(|e| DicomWriteError::Meta(e.to_string()))?;
        let mut bytes = Vec::new();
        file.write_all(&mut bytes).map_err(|e| DicomWriteError::Encode { k, message: e.to_string() })?;
        files.push((format!("{:06}.dcm", k + 1), bytes));
    }
    Ok(files)
}

fn check_uid(what: &'static str, uid: &str) -> Result<(), DicomWriteError> {
    let valid = !uid.is_empty()
        && uid.len() <= 64
        && uid.split('.').all(|part| {
            !part.is_empty() && part.bytes().all(|b| b.is_ascii_digit()) && (part == "0" || !part.starts_with('0'))
        });
    if valid {
        Ok(())
    } else {
        Err(DicomWriteError::InvalidUid { what, uid: uid.to_string() })
    }
}

/// Decimal String values: the shortest text within 16 characters each.
fn ds(values: &[f64]) -> String {
    values.iter().map(|&v| ds_value(v)).collect::<Vec<_>>().join("\\")
}

fn ds_value(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v }; // no "-0"
    let plain = format!("{v}");
    if plain.len() <= 16 {
        return plain;
    }
    // Too many digits: round to the most decimals that fit.
    for decimals in (0..=15).rev() {
        let s = format!("{v:.decimals$}");
        let s = if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s };
        if s.len() <= 16 {
            return s;
        }
    }
    format!("{v:.6e}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ds_values_fit_sixteen_characters() {
        assert_eq!(ds_value(0.703125), "0.703125");
        assert_eq!(ds_value(-0.0), "0");
        assert_eq!(ds_value(-1024.0), "-1024");
        let long = ds_value(0.1 + 0.2);
        assert!(long.len() <= 16 && (long.parse::<f64>().unwrap() - 0.3).abs() < 1e-12);
        let big = ds_value(-179.64843750000003);
        assert!(big.len() <= 16, "{big}");
    }

    #[test]
    fn stored_values_round_and_saturate() {
        assert_eq!(stored_value(-1000.0), 24);
        assert_eq!(stored_value(-0.5), 1023); // half away from zero: −1
        assert_eq!(stored_value(1e9), i16::MAX);
        assert_eq!(stored_value(-1e9), i16::MIN);
    }

    #[test]
    fn derived_uids_are_valid_and_distinct() {
        let a = derived_uid("x/0");
        assert!(check_uid("test", &a).is_ok(), "{a}");
        assert_ne!(a, derived_uid("x/1"));
        assert!(check_uid("test", "1.2.03").is_err());
        assert!(check_uid("test", "1.2.a").is_err());
    }
}
