//! How a node's values are stored: OpenVDB's `io::writeCompressedValues` for a tree whose
//! inactive values all equal the background (0), as ours do.
//!
//! Per node: the metadata byte `NO_MASK_OR_INACTIVE_VALS` (every inactive value is the
//! background, so none is stored), then the active values in mask bit order as float32, as one
//! chunk. Under zip the chunk is one zlib stream prefixed by its byte count as an i64; when
//! deflating does not make it smaller, the count is negated and the values follow raw, which is
//! what OpenVDB's `zipToStream` does (an empty chunk is the count 0 and nothing else).

use super::leaves::Leaf;
use super::Out;
use rayon::prelude::*;

/// `io::COMPRESS_ZIP`: each chunk of values deflated with zlib.
const COMPRESS_ZIP: u32 = 0x1;
/// `io::COMPRESS_ACTIVE_MASK`: nodes store their active values only.
const COMPRESS_ACTIVE_MASK: u32 = 0x2;
/// Per-node metadata `NO_MASK_OR_INACTIVE_VALS`: every inactive value equals the background.
const NO_MASK_OR_INACTIVE_VALS: u8 = 0;
/// zlib level 1, the fastest: on a 512×512×133 CT it deflates two to three times as fast as
/// OpenVDB's own level 6, for a file 5–10 % larger (docs/conventions.md). Readers accept any
/// level.
const ZIP_LEVEL: u32 = 1;
/// Leaves per parallel task when encoding the leaf buffers.
const LEAVES_PER_TASK: usize = 256;

/// How a grid's node values are stored. Both keep inactive voxels out of the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compression {
    /// Active values only, each node's values deflated with zlib (flags zip + active mask):
    /// what every OpenVDB build reads (zlib is one of its required dependencies).
    #[default]
    Zip,
    /// Active values only, as raw float32 (flag active mask): for a reader without zlib.
    ActiveValuesOnly,
}

impl Compression {
    /// The grid's compression flags (`io::COMPRESS_*`), written right after its descriptor.
    pub(super) fn flags(self) -> u32 {
        match self {
            Compression::Zip => COMPRESS_ZIP | COMPRESS_ACTIVE_MASK,
            Compression::ActiveValuesOnly => COMPRESS_ACTIVE_MASK,
        }
    }

    /// The flags as OpenVDB's `io::compressionToString` names them: the grid's
    /// `file_compression` metadata.
    pub(super) fn description(self) -> &'static str {
        match self {
            Compression::Zip => "zip + active values",
            Compression::ActiveValuesOnly => "active values",
        }
    }
}

/// Writes nodes' values under one `Compression`, reusing one zlib stream and its buffers.
pub(super) struct ValueWriter {
    compression: Compression,
    deflate: flate2::Compress,
    raw: Vec<u8>,
    zipped: Vec<u8>,
}

impl ValueWriter {
    pub fn new(compression: Compression) -> Self {
        ValueWriter {
            compression,
            deflate: flate2::Compress::new(flate2::Compression::new(ZIP_LEVEL), true),
            raw: Vec::new(),
            zipped: Vec::new(),
        }
    }

    /// One node's values: the metadata byte, then `active` (the active values, in bit order).
    pub fn write(&mut self, out: &mut Out, active: impl Iterator<Item = f32>) {
        out.u8(NO_MASK_OR_INACTIVE_VALS);
        self.raw.clear();
        active.for_each(|v| self.raw.extend_from_slice(&v.to_le_bytes()));
        match self.compression {
            Compression::ActiveValuesOnly => out.bytes(&self.raw),
            Compression::Zip => self.write_zip_chunk(out),
        }
    }

    /// `self.raw` as OpenVDB's `zipToStream` writes it: the zlib stream if it is shorter than
    /// the raw bytes, with its length; otherwise the negated raw length and the raw bytes.
    fn write_zip_chunk(&mut self, out: &mut Out) {
        if !self.raw.is_empty() {
            self.zipped.clear();
            self.zipped.reserve(self.raw.len());
            self.deflate.reset();
            // Output beyond the buffer's spare capacity would not be shorter than the raw
            // bytes; the stream then stays unfinished and the raw bytes are stored.
            let done = self.deflate.compress_vec(&self.raw, &mut self.zipped, flate2::FlushCompress::Finish);
            if matches!(done, Ok(flate2::Status::StreamEnd)) && self.zipped.len() < self.raw.len() {
                out.i64(self.zipped.len() as i64);
                out.bytes(&self.zipped);
                return;
            }
        }
        out.i64(-(self.raw.len() as i64));
        out.bytes(&self.raw);
    }
}

/// The grid's leaf buffers, in tree order: per leaf its value mask and its values. Leaves are
/// encoded in parallel, independently, so the bytes do not depend on the thread count.
pub(super) fn leaf_buffers(leaves: &[Leaf], compression: Compression) -> Vec<u8> {
    let parts: Vec<Vec<u8>> = leaves
        .par_chunks(LEAVES_PER_TASK)
        .map(|task| {
            let mut writer = ValueWriter::new(compression);
            let mut out = Out::default();
            for leaf in task {
                out.mask(&leaf.mask);
                writer.write(&mut out, leaf.active_values());
            }
            out.0
        })
        .collect();
    parts.concat()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Read;

    fn chunk(compression: Compression, values: &[f32]) -> Vec<u8> {
        let mut out = Out::default();
        ValueWriter::new(compression).write(&mut out, values.iter().copied());
        out.0
    }

    #[test]
    fn zip_chunk_is_a_counted_zlib_stream_of_the_values() {
        let values: Vec<f32> = (0..512).map(|n| (n % 9) as f32 * 0.25).collect();
        let bytes = chunk(Compression::Zip, &values);
        assert_eq!(bytes[0], NO_MASK_OR_INACTIVE_VALS);
        let count = i64::from_le_bytes(bytes[1..9].try_into().unwrap());
        assert_eq!(count as usize, bytes.len() - 9);
        assert!(count > 0 && (count as usize) < values.len(), "repetitive values deflate to < 1/4: {count} bytes");
        let mut inflated = Vec::new();
        flate2::read::ZlibDecoder::new(&bytes[9..]).read_to_end(&mut inflated).unwrap();
        let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(inflated, raw);
    }

    #[test]
    fn incompressible_and_empty_chunks_are_stored_raw_with_a_negative_count() {
        // One value: 4 bytes cannot deflate below 4 (zlib's header and checksum alone are 6).
        let bytes = chunk(Compression::Zip, &[1.5]);
        assert_eq!(bytes.len(), 1 + 8 + 4);
        assert_eq!(i64::from_le_bytes(bytes[1..9].try_into().unwrap()), -4);
        assert_eq!(&bytes[9..], &1.5f32.to_le_bytes());
        // No active value (an internal node without tiles): the count 0 and nothing else.
        assert_eq!(chunk(Compression::Zip, &[]), [NO_MASK_OR_INACTIVE_VALS, 0, 0, 0, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn active_values_only_stores_the_values_raw() {
        let bytes = chunk(Compression::ActiveValuesOnly, &[1.0, -2.0]);
        let want: Vec<u8> =
            [NO_MASK_OR_INACTIVE_VALS].into_iter().chain([1.0f32, -2.0].iter().flat_map(|v| v.to_le_bytes())).collect();
        assert_eq!(bytes, want);
        assert!(chunk(Compression::ActiveValuesOnly, &[]) == [NO_MASK_OR_INACTIVE_VALS]);
    }

    #[test]
    fn a_writer_reused_across_nodes_gives_each_node_its_own_stream() {
        let a: Vec<f32> = vec![3.0; 300];
        let b: Vec<f32> = (0..300).map(|n| (n % 5) as f32).collect();
        let mut writer = ValueWriter::new(Compression::Zip);
        let mut out = Out::default();
        writer.write(&mut out, a.iter().copied());
        writer.write(&mut out, b.iter().copied());
        assert_eq!(out.0, [chunk(Compression::Zip, &a), chunk(Compression::Zip, &b)].concat());
    }
}
