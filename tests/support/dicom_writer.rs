//! Writes small synthetic CT series with dicom-object, for tests of the DICOM reader and of
//! the ingest stage. Start from [`SliceSpec::ct`] or [`series`], change the fields a test is
//! about, then [`write_slice`] / [`write_series`]. [`SliceSpec::expected_hu`] gives the HU
//! the reader must produce for a slice.
//!
//! The files carry no real patient data; `patient` lets a test plant identifying values to
//! check they never leak into messages.
#![allow(dead_code)] // shared by several test crates; each uses a subset

use dicom_core::value::{PixelFragmentSequence, PrimitiveValue, Value};
use dicom_core::{DataElement, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use std::path::{Path, PathBuf};

pub const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
pub const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
pub const EXPLICIT_BE: &str = "1.2.840.10008.1.2.2";
pub const DEFLATED_LE: &str = "1.2.840.10008.1.2.1.99";
pub const JPEG2000_LOSSLESS: &str = "1.2.840.10008.1.2.4.90";
pub const SERIES_UID: &str = "1.2.826.0.1.3680043.8.498.1";
pub const AXIAL: [f64; 6] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// Everything a synthetic slice file contains. Optional attributes are written only when
/// `Some`; `omit` drops any attribute (e.g. to test a missing tag).
#[derive(Debug, Clone)]
pub struct SliceSpec {
    pub rows: u16,
    pub cols: u16,
    /// DICOM order: [between rows, between columns], mm.
    pub pixel_spacing: [f64; 2],
    pub ipp: [f64; 3],
    pub iop: [f64; 6],
    pub slope: Option<f64>,
    pub intercept: Option<f64>,
    /// Stored values, row-major (`rows × cols`); written as BitsAllocated-wide words. For
    /// 16-bit data, `word = value as u16`; if `mask_to_bits_stored`, bits above BitsStored
    /// are cleared first (what most signed 12-bit writers do).
    pub stored: Vec<i32>,
    pub bits_allocated: u16,
    pub bits_stored: u16,
    pub signed: bool,
    pub mask_to_bits_stored: bool,
    pub samples_per_pixel: u16,
    pub photometric: String,
    pub modality: String,
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub series_uid: String,
    pub transfer_syntax: String,
    pub instance_number: i32,
    pub slice_thickness: Option<f64>,
    pub spacing_between_slices: Option<f64>,
    pub number_of_frames: Option<u32>,
    /// (PatientName, PatientID), for leak checks.
    pub patient: Option<(String, String)>,
    pub omit: Vec<Tag>,
    /// Write the 128-byte preamble before "DICM" (standard); `false` starts with "DICM".
    pub preamble: bool,
}

impl SliceSpec {
    /// Slice `k` of an 8×6 axial signed 16-bit CT series: z = 10 + 2.5·k mm, slope 1,
    /// intercept −1024, stored values distinct per voxel and slice (some below 1024, so
    /// HU go negative).
    pub fn ct(k: usize) -> SliceSpec {
        let (rows, cols) = (6u16, 8u16);
        let stored = (0..rows as i32 * cols as i32).map(|p| 900 + 37 * p + 100 * k as i32).collect();
        SliceSpec {
            rows,
            cols,
            pixel_spacing: [0.7, 0.6],
            ipp: [-100.0, -80.0, 10.0 + 2.5 * k as f64],
            iop: AXIAL,
            slope: Some(1.0),
            intercept: Some(-1024.0),
            stored,
            bits_allocated: 16,
            bits_stored: 16,
            signed: true,
            mask_to_bits_stored: false,
            samples_per_pixel: 1,
            photometric: "MONOCHROME2".into(),
            modality: "CT".into(),
            sop_class_uid: uids::CT_IMAGE_STORAGE.into(),
            sop_instance_uid: format!("{SERIES_UID}.{}", k + 1),
            series_uid: SERIES_UID.into(),
            transfer_syntax: EXPLICIT_LE.into(),
            instance_number: k as i32 + 1,
            slice_thickness: Some(2.5),
            spacing_between_slices: None,
            number_of_frames: None,
            patient: None,
            omit: Vec::new(),
            preamble: true,
        }
    }

    /// HU the reader must give: stored (as decoded) × slope + intercept, rounded half away
    /// from zero, saturated.
    pub fn expected_hu(&self) -> Vec<i16> {
        let slope = self.slope.unwrap_or(1.0);
        let intercept = self.intercept.unwrap_or(0.0);
        self.stored
            .iter()
            .map(|&v| {
                let hu = (f64::from(self.decoded(v)) * slope + intercept).round();
                hu.clamp(-32768.0, 32767.0) as i16
            })
            .collect()
    }

    /// What a pydicom-compatible decoder reads back for stored value `v`.
    fn decoded(&self, v: i32) -> i32 {
        let word = self.word(v) as u32;
        if self.signed {
            let shift = 32 - u32::from(self.bits_stored);
            ((word << shift) as i32) >> shift
        } else {
            (word & ((1u32 << self.bits_stored) - 1)) as i32
        }
    }

    /// The bits written for stored value `v`.
    fn word(&self, v: i32) -> u16 {
        let width_mask: u32 = if self.bits_allocated == 8 { 0xFF } else { 0xFFFF };
        let mut w = (v as u32) & width_mask;
        if self.mask_to_bits_stored {
            w &= (1u32 << self.bits_stored) - 1;
        }
        w as u16
    }
}

/// `n` slices of [`SliceSpec::ct`].
pub fn series(n: usize) -> Vec<SliceSpec> {
    (0..n).map(SliceSpec::ct).collect()
}

/// DS text: short, exact for the decimal values tests use.
fn ds(values: &[f64]) -> String {
    values
        .iter()
        .map(|v| {
            let s = format!("{v:.6}");
            let s = s.trim_end_matches('0').trim_end_matches('.');
            if s == "-0" {
                "0".to_string()
            } else {
                s.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\\")
}

fn build_object(spec: &SliceSpec) -> InMemDicomObject {
    let mut elements: Vec<DataElement<InMemDicomObject>> = vec![
        DataElement::new(tags::SOP_CLASS_UID, VR::UI, spec.sop_class_uid.as_str()),
        DataElement::new(tags::SOP_INSTANCE_UID, VR::UI, spec.sop_instance_uid.as_str()),
        DataElement::new(tags::MODALITY, VR::CS, spec.modality.as_str()),
        DataElement::new(tags::SERIES_INSTANCE_UID, VR::UI, spec.series_uid.as_str()),
        DataElement::new(tags::INSTANCE_NUMBER, VR::IS, spec.instance_number.to_string().as_str()),
        DataElement::new(tags::IMAGE_POSITION_PATIENT, VR::DS, ds(&spec.ipp).as_str()),
        DataElement::new(tags::IMAGE_ORIENTATION_PATIENT, VR::DS, ds(&spec.iop).as_str()),
        DataElement::new(tags::SAMPLES_PER_PIXEL, VR::US, PrimitiveValue::from(spec.samples_per_pixel)),
        DataElement::new(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, spec.photometric.as_str()),
        DataElement::new(tags::ROWS, VR::US, PrimitiveValue::from(spec.rows)),
        DataElement::new(tags::COLUMNS, VR::US, PrimitiveValue::from(spec.cols)),
        DataElement::new(tags::PIXEL_SPACING, VR::DS, ds(&spec.pixel_spacing).as_str()),
        DataElement::new(tags::BITS_ALLOCATED, VR::US, PrimitiveValue::from(spec.bits_allocated)),
        DataElement::new(tags::BITS_STORED, VR::US, PrimitiveValue::from(spec.bits_stored)),
        DataElement::new(tags::HIGH_BIT, VR::US, PrimitiveValue::from(spec.bits_stored - 1)),
        DataElement::new(tags::PIXEL_REPRESENTATION, VR::US, PrimitiveValue::from(u16::from(spec.signed))),
    ];
    let optional_ds = [
        (tags::RESCALE_SLOPE, spec.slope),
        (tags::RESCALE_INTERCEPT, spec.intercept),
        (tags::SLICE_THICKNESS, spec.slice_thickness),
        (tags::SPACING_BETWEEN_SLICES, spec.spacing_between_slices),
    ];
    for (tag, value) in optional_ds {
        if let Some(v) = value {
            elements.push(DataElement::new(tag, VR::DS, ds(&[v]).as_str()));
        }
    }
    if let Some(frames) = spec.number_of_frames {
        elements.push(DataElement::new(tags::NUMBER_OF_FRAMES, VR::IS, frames.to_string().as_str()));
    }
    if let Some((name, id)) = &spec.patient {
        elements.push(DataElement::new(tags::PATIENT_NAME, VR::PN, name.as_str()));
        elements.push(DataElement::new(tags::PATIENT_ID, VR::LO, id.as_str()));
    }
    elements.push(pixel_data(spec));
    let mut obj = InMemDicomObject::from_element_iter(elements);
    for &tag in &spec.omit {
        obj.remove_element(tag);
    }
    obj
}

fn pixel_data(spec: &SliceSpec) -> DataElement<InMemDicomObject> {
    let words: Vec<u16> = spec.stored.iter().map(|&v| spec.word(v)).collect();
    if spec.transfer_syntax == JPEG2000_LOSSLESS {
        // Not a real codestream: the reader must refuse the syntax before decoding.
        let fragment: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let seq = PixelFragmentSequence::new(Vec::<u32>::new(), vec![fragment]);
        return DataElement::new(tags::PIXEL_DATA, VR::OB, Value::PixelSequence(seq));
    }
    if spec.bits_allocated == 8 {
        let bytes: Vec<u8> = words.iter().map(|&w| w as u8).collect();
        DataElement::new(tags::PIXEL_DATA, VR::OB, PrimitiveValue::U8(bytes.into()))
    } else {
        // OW values: the writer encodes them in the transfer syntax's byte order.
        DataElement::new(tags::PIXEL_DATA, VR::OW, PrimitiveValue::U16(words.into()))
    }
}

/// Write one slice file.
pub fn write_slice(path: &Path, spec: &SliceSpec) {
    let meta = FileMetaTableBuilder::new().transfer_syntax(spec.transfer_syntax.as_str());
    let file = build_object(spec).with_meta(meta).expect("file meta table");
    if spec.preamble {
        file.write_to_file(path).expect("write DICOM file");
    } else {
        let out = std::fs::File::create(path).expect("create DICOM file");
        file.write_all(std::io::BufWriter::new(out)).expect("write DICOM file");
    }
}

/// Write `specs` into `dir` as `name(k)` for slice `k`; returns the paths in spec order.
pub fn write_series(dir: &Path, specs: &[SliceSpec], name: impl Fn(usize) -> String) -> Vec<PathBuf> {
    specs
        .iter()
        .enumerate()
        .map(|(k, spec)| {
            let path = dir.join(name(k));
            write_slice(&path, spec);
            path
        })
        .collect()
}

/// `slice_{k}.dcm`.
pub fn default_name(k: usize) -> String {
    format!("slice_{k}.dcm")
}
