//! MetaImage (`.mhd` header + `.raw` little-endian data), as read by ITK, VTK/ParaView and
//! 3D Slicer. The header carries spacing, origin and direction, so the volume lands in
//! patient millimetres (LPS) in those tools.
//!
//! `TransformMatrix` follows MetaIO: the first three numbers are the patient-space direction
//! of index axis 0, the next three of axis 1, the last three of axis 2.

use crate::volume::{Geometry, Volume};
use std::fmt::Write as _;

/// Element types we write and read, with their MetaIO names.
pub trait MetaElement: Copy + Sized {
    const MET_TYPE: &'static str;
    const SIZE: usize;
    fn write_le(self, out: &mut Vec<u8>);
    fn read_le(bytes: &[u8]) -> Self;
}

macro_rules! meta_element {
    ($t:ty, $name:literal) => {
        impl MetaElement for $t {
            const MET_TYPE: &'static str = $name;
            const SIZE: usize = std::mem::size_of::<$t>();
            fn write_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            fn read_le(bytes: &[u8]) -> Self {
                <$t>::from_le_bytes(bytes.try_into().expect("slice of element size"))
            }
        }
    };
}
meta_element!(u8, "MET_UCHAR");
meta_element!(i16, "MET_SHORT");
meta_element!(u32, "MET_UINT");
meta_element!(f32, "MET_FLOAT");
meta_element!(f64, "MET_DOUBLE");

#[derive(Debug, thiserror::Error)]
pub enum MhdError {
    #[error("MetaImage header line {line}: {message}")]
    Header { line: usize, message: String },
    #[error("MetaImage header is missing `{0}`")]
    Missing(&'static str),
    #[error("MetaImage element type is {found}, expected {expected}")]
    ElementType { found: String, expected: &'static str },
    #[error("MetaImage data holds {found} bytes, the header's DimSize needs {expected}")]
    DataSize { found: usize, expected: usize },
}

/// The header text for `volume`, pointing at `data_file_name` (a sibling file name).
pub fn header<T: MetaElement>(geometry: &Geometry, data_file_name: &str) -> String {
    let g = geometry;
    let mut s = String::new();
    let nums = |v: &[f64]| v.iter().map(|x| format_num(*x)).collect::<Vec<_>>().join(" ");
    let _ = writeln!(s, "ObjectType = Image");
    let _ = writeln!(s, "NDims = 3");
    let _ = writeln!(s, "BinaryData = True");
    let _ = writeln!(s, "BinaryDataByteOrderMSB = False");
    let _ = writeln!(s, "CompressedData = False");
    let flat: Vec<f64> = g.direction.iter().flatten().copied().collect();
    let _ = writeln!(s, "TransformMatrix = {}", nums(&flat));
    let _ = writeln!(s, "Offset = {}", nums(&g.origin_mm));
    let _ = writeln!(s, "CenterOfRotation = 0 0 0");
    let _ = writeln!(s, "AnatomicalOrientation = {}", anatomical_orientation(&g.direction));
    let _ = writeln!(s, "ElementSpacing = {}", nums(&g.spacing_mm));
    let _ = writeln!(s, "DimSize = {} {} {}", g.dims[0], g.dims[1], g.dims[2]);
    let _ = writeln!(s, "ElementType = {}", T::MET_TYPE);
    let _ = writeln!(s, "ElementDataFile = {data_file_name}");
    s
}

/// Header text and raw bytes of `volume`.
pub fn encode<T: MetaElement>(volume: &Volume<T>, data_file_name: &str) -> (String, Vec<u8>) {
    let mut raw = Vec::with_capacity(volume.data.len() * T::SIZE);
    for &v in &volume.data {
        v.write_le(&mut raw);
    }
    (header::<T>(&volume.geometry, data_file_name), raw)
}

/// Parse a header we (or ITK) wrote and decode its little-endian raw data.
pub fn decode<T: MetaElement>(header_text: &str, raw: &[u8]) -> Result<Volume<T>, MhdError> {
    let mut dims = None;
    let mut spacing = None;
    let mut origin = None;
    let mut direction = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let mut element_type = None;
    for (n, line) in header_text.lines().enumerate() {
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let (key, value) = (key.trim(), value.trim());
        let err = |message: String| MhdError::Header { line: n + 1, message };
        let floats = || -> Result<Vec<f64>, MhdError> {
            value
                .split_whitespace()
                .map(|t| t.parse::<f64>().map_err(|_| err(format!("`{key}` has a non-number `{t}`"))))
                .collect()
        };
        let three = |v: Vec<f64>| -> Result<[f64; 3], MhdError> {
            v.try_into().map_err(|_| err(format!("`{key}` needs 3 numbers")))
        };
        match key {
            "NDims" if value != "3" => return Err(err(format!("NDims = {value}, only 3 is supported"))),
            "BinaryDataByteOrderMSB" | "ElementByteOrderMSB" if value.eq_ignore_ascii_case("true") => {
                return Err(err("big-endian data is not supported".into()))
            }
            "CompressedData" if value.eq_ignore_ascii_case("true") => {
                return Err(err("compressed data is not supported".into()))
            }
            "DimSize" => {
                let v = three(floats()?)?;
                dims = Some([v[0] as usize, v[1] as usize, v[2] as usize]);
            }
            "ElementSpacing" => spacing = Some(three(floats()?)?),
            "Offset" | "Origin" | "Position" => origin = Some(three(floats()?)?),
            "TransformMatrix" | "Rotation" | "Orientation" => {
                let v = floats()?;
                if v.len() != 9 {
                    return Err(err(format!("`{key}` needs 9 numbers")));
                }
                for a in 0..3 {
                    direction[a] = [v[3 * a], v[3 * a + 1], v[3 * a + 2]];
                }
            }
            "ElementType" => element_type = Some(value.to_string()),
            _ => {}
        }
    }
    let dims = dims.ok_or(MhdError::Missing("DimSize"))?;
    let element_type = element_type.ok_or(MhdError::Missing("ElementType"))?;
    if element_type != T::MET_TYPE {
        return Err(MhdError::ElementType { found: element_type, expected: T::MET_TYPE });
    }
    let geometry =
        Geometry { dims, spacing_mm: spacing.unwrap_or([1.0; 3]), origin_mm: origin.unwrap_or([0.0; 3]), direction };
    let expected = geometry.len() * T::SIZE;
    if raw.len() != expected {
        return Err(MhdError::DataSize { found: raw.len(), expected });
    }
    let data = raw.chunks_exact(T::SIZE).map(T::read_le).collect();
    Ok(Volume { geometry, data })
}

/// The value of `key` in a header's `key = value` lines (trimmed), e.g. `ElementType` to choose
/// the element type before decoding, or `ElementDataFile` to find the raw data.
pub fn header_field<'a>(header_text: &'a str, key: &str) -> Option<&'a str> {
    header_text.lines().find_map(|line| {
        let (k, v) = line.split_once('=')?;
        (k.trim() == key).then(|| v.trim())
    })
}

/// Shortest text that parses back to the same f64 (Rust's `Display` for floats).
fn format_num(x: f64) -> String {
    if x == 0.0 {
        "0".into() // also folds -0
    } else {
        format!("{x}")
    }
}

/// ITK's three-letter code: for each axis, the patient side it points *from* (LPS +x = from R).
fn anatomical_orientation(direction: &[[f64; 3]; 3]) -> String {
    direction
        .iter()
        .map(|d| {
            let (c, v) = d.iter().enumerate().max_by(|a, b| a.1.abs().total_cmp(&b.1.abs())).expect("three components");
            match (c, *v >= 0.0) {
                (0, true) => 'R',
                (0, false) => 'L',
                (1, true) => 'A',
                (1, false) => 'P',
                (_, true) => 'I',
                (_, false) => 'S',
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_geometry_and_values() {
        let geometry = Geometry {
            dims: [3, 2, 2],
            spacing_mm: [0.7, 0.7, 2.5],
            origin_mm: [-170.5, -160.25, -310.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let volume = Volume { geometry, data: (0..12).map(|v| v as i16 - 1000).collect::<Vec<i16>>() };
        let (hdr, raw) = encode(&volume, "x.raw");
        assert!(hdr.contains("AnatomicalOrientation = RAI"));
        assert_eq!(header_field(&hdr, "ElementDataFile"), Some("x.raw"));
        let back: Volume<i16> = decode(&hdr, &raw).unwrap();
        assert_eq!(back, volume);
        assert!(matches!(decode::<f32>(&hdr, &raw), Err(MhdError::ElementType { .. })));
        assert!(matches!(decode::<i16>(&hdr, &raw[1..]), Err(MhdError::DataSize { .. })));
        assert_eq!(header_field(&hdr, "ElementType"), Some("MET_SHORT"));
        assert_eq!(header_field(&hdr, "ElementDataFile"), Some("x.raw"));
        assert_eq!(header_field(&hdr, "Element"), None);
    }
}
