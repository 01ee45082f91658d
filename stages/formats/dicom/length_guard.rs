//! A walk over element *headers* (never values) checking that every declared length fits in
//! the bytes that remain, and that nesting stays shallow, before the real parser runs.
//!
//! Why: dicom-parser allocates and zero-fills a buffer of the declared length before
//! reading the value, so a single flipped bit in a length field made it fill up to 4 GiB
//! (seconds, and a possible out-of-memory abort) before noticing the file is short; and
//! deeply nested sequences could overflow its recursion. Both are found here in one cheap
//! pass and reported as a damaged file. The walk must see the elements the parser will see,
//! so it also refuses what would make the two part ways: a value representation outside the
//! standard (the parser guesses a length layout for it), and a file meta group that does not
//! end where its group length (0002,0000) says (the parser starts the data set there).

use dicom_core::dictionary::{DataDictionary, DataDictionaryEntry};
use dicom_core::{Tag, VR};
use dicom_dictionary_std::StandardDataDictionary;

const UNDEFINED: u32 = 0xFFFF_FFFF;
const ITEM: (u16, u16) = (0xFFFE, 0xE000);
const ITEM_END: (u16, u16) = (0xFFFE, 0xE00D);
const SEQUENCE_END: (u16, u16) = (0xFFFE, 0xE0DD);
const GROUP_LENGTH: (u16, u16) = (0x0002, 0x0000);
/// Far deeper than any real CT header (2–4 levels), far shallower than a stack overflow.
const MAX_DEPTH: usize = 32;

/// How the data set after the file meta group is encoded.
#[derive(Clone, Copy)]
pub struct Encoding {
    explicit_vr: bool,
    big_endian: bool,
}

/// `None` where the bytes cannot be walked: deflated data sets (compressed as a whole)
/// and transfer syntaxes we do not know.
pub fn encoding_of(ts: &str) -> Option<Encoding> {
    match ts {
        "1.2.840.10008.1.2" => Some(Encoding { explicit_vr: false, big_endian: false }),
        "1.2.840.10008.1.2.2" => Some(Encoding { explicit_vr: true, big_endian: true }),
        "1.2.840.10008.1.2.1.99" | "1.2.840.10008.1.2.4.95" | "1.2.840.10008.1.2.4.205" => None,
        // Explicit VR LE and every encapsulated syntax we can name use explicit VR LE.
        ts if ts == "1.2.840.10008.1.2.1"
            || super::transfer_syntax_name(ts) != "unknown or private transfer syntax" =>
        {
            Some(Encoding { explicit_vr: true, big_endian: false })
        }
        _ => None,
    }
}

/// `bytes` start at the "DICM" magic. With `None`, only the file meta group is checked
/// (its encoding is fixed; the data set's is only known once the meta group is read).
pub fn check(bytes: &[u8], encoding: Option<Encoding>) -> Result<(), String> {
    let meta_only = encoding.is_none();
    let encoding = encoding.unwrap_or(Encoding { explicit_vr: true, big_endian: false });
    let mut walker = Walker {
        bytes,
        pos: 4,
        // The file meta group (0002,xxxx) is always explicit VR little endian.
        encoding: Encoding { explicit_vr: true, big_endian: false },
        data_set_encoding: encoding,
        in_meta: true,
        meta_only,
        meta_end: None,
    };
    walker.elements(None, 0)
}

struct Walker<'a> {
    bytes: &'a [u8],
    pos: usize,
    encoding: Encoding,
    data_set_encoding: Encoding,
    in_meta: bool,
    meta_only: bool,
    /// Where the file meta group ends by its group length (0002,0000): the meta reader
    /// stops there, whatever follows, so the data set must start exactly there too.
    meta_end: Option<usize>,
}

impl Walker<'_> {
    fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }

    fn take<const N: usize>(&mut self) -> Result<[u8; N], String> {
        let out = self
            .bytes
            .get(self.pos..self.pos + N)
            .and_then(|s| <[u8; N]>::try_from(s).ok())
            .ok_or_else(|| format!("file ends inside an element header at byte {}", self.pos))?;
        self.pos += N;
        Ok(out)
    }

    fn u16(&mut self) -> Result<u16, String> {
        let b = self.take::<2>()?;
        Ok(if self.encoding.big_endian { u16::from_be_bytes(b) } else { u16::from_le_bytes(b) })
    }

    fn u32(&mut self) -> Result<u32, String> {
        let b = self.take::<4>()?;
        Ok(if self.encoding.big_endian { u32::from_be_bytes(b) } else { u32::from_le_bytes(b) })
    }

    fn skip(&mut self, tag: (u16, u16), len: u32) -> Result<(), String> {
        let len = len as usize;
        if len > self.remaining() {
            return Err(format!(
                "element ({:04X},{:04X}) declares {len} bytes but only {} remain in the file",
                tag.0,
                tag.1,
                self.remaining()
            ));
        }
        self.pos += len;
        Ok(())
    }

    /// Data elements until `end` (a defined-length item), an item delimiter, or the end
    /// of the file (top level).
    fn elements(&mut self, end: Option<usize>, depth: usize) -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("sequences nested deeper than {MAX_DEPTH} levels"));
        }
        loop {
            if end.is_some_and(|e| self.pos >= e) || self.remaining() == 0 {
                return Ok(());
            }
            if self.in_meta {
                // The first element outside group 0002 starts the data set proper, in
                // its own encoding (a big-endian 0008 reads as 0x0800 here: also "not 2").
                let group = self.bytes.get(self.pos..self.pos + 2);
                if group != Some(&[0x02, 0x00][..]) {
                    self.check_meta_end()?;
                    if self.meta_only {
                        return Ok(());
                    }
                    self.in_meta = false;
                    self.encoding = self.data_set_encoding;
                }
            }
            let tag = (self.u16()?, self.u16()?);
            if tag == ITEM_END || tag == SEQUENCE_END {
                self.u32()?;
                return Ok(());
            }
            let (len, is_sequence) = self.element_length(tag)?;
            if self.in_meta && tag == GROUP_LENGTH && len == 4 && self.meta_end.is_none() {
                let group_length = self.u32()? as usize;
                self.meta_end = Some(self.pos.saturating_add(group_length));
                continue;
            }
            if len == UNDEFINED {
                if tag == (0x7FE0, 0x0010) {
                    self.fragments()?;
                } else {
                    self.items(None, depth + 1)?;
                }
            } else if is_sequence {
                let len_usize = len as usize;
                if len_usize > self.remaining() {
                    return self.skip(tag, len);
                }
                self.items(Some(self.pos + len_usize), depth + 1)?;
            } else {
                self.skip(tag, len)?;
            }
        }
    }

    /// The data set (or the file's end) must begin where the group length says the meta
    /// group ends: elsewhere, the parser would read the data set from another offset than
    /// the one whose lengths were checked here.
    fn check_meta_end(&self) -> Result<(), String> {
        match self.meta_end {
            Some(end) if end == self.pos => Ok(()),
            Some(end) => Err(format!(
                "the file meta group length (0002,0000) puts the data set at byte {end}, but the \
                 group ends at byte {}",
                self.pos
            )),
            None => Err("the file meta group has no group length (0002,0000)".into()),
        }
    }

    /// The value length of the element whose tag was just read, and whether it is a
    /// sequence (whose items must be walked, not skipped).
    fn element_length(&mut self, tag: (u16, u16)) -> Result<(u32, bool), String> {
        if !self.encoding.explicit_vr || tag.0 == 0xFFFE {
            let len = self.u32()?;
            let is_sequence =
                StandardDataDictionary.by_tag(Tag(tag.0, tag.1)).is_some_and(|e| e.vr().relaxed() == VR::SQ);
            return Ok((len, is_sequence));
        }
        let vr = self.take::<2>()?;
        // Only the standard's VRs: for any other two letters the parser guesses a length
        // layout of its own, and the lengths checked here would not be the ones it reads.
        const SHORT: [&[u8; 2]; 21] = [
            b"AE", b"AS", b"AT", b"CS", b"DA", b"DS", b"DT", b"FD", b"FL", b"IS", b"LO", b"LT", b"PN", b"SH", b"SL",
            b"SS", b"ST", b"TM", b"UI", b"UL", b"US",
        ];
        const LONG: [&[u8; 2]; 13] =
            [b"OB", b"OD", b"OF", b"OL", b"OV", b"OW", b"SQ", b"SV", b"UC", b"UN", b"UR", b"UT", b"UV"];
        if !SHORT.contains(&&vr) && !LONG.contains(&&vr) {
            return Err(format!("element ({:04X},{:04X}) has an invalid value representation", tag.0, tag.1));
        }
        if LONG.contains(&&vr) {
            self.take::<2>()?; // reserved
            Ok((self.u32()?, &vr == b"SQ"))
        } else {
            Ok((u32::from(self.u16()?), false))
        }
    }

    /// Items of a sequence until `end` or the sequence delimiter.
    fn items(&mut self, end: Option<usize>, depth: usize) -> Result<(), String> {
        loop {
            if end.is_some_and(|e| self.pos >= e) || self.remaining() == 0 {
                return Ok(());
            }
            let tag = (self.u16()?, self.u16()?);
            let len = self.u32()?;
            match tag {
                SEQUENCE_END => return Ok(()),
                ITEM if len == UNDEFINED => self.elements(None, depth)?,
                ITEM => {
                    if len as usize > self.remaining() {
                        return self.skip(tag, len);
                    }
                    self.elements(Some(self.pos + len as usize), depth)?;
                }
                _ => return Err(format!("({:04X},{:04X}) where a sequence item was expected", tag.0, tag.1)),
            }
        }
    }

    /// Encapsulated pixel data: byte fragments (never walked into) until the delimiter.
    fn fragments(&mut self) -> Result<(), String> {
        loop {
            if self.remaining() == 0 {
                return Ok(());
            }
            let tag = (self.u16()?, self.u16()?);
            let len = self.u32()?;
            match tag {
                SEQUENCE_END => return Ok(()),
                ITEM => self.skip(tag, len)?,
                _ => return Err(format!("({:04X},{:04X}) where a pixel data fragment was expected", tag.0, tag.1)),
            }
        }
    }
}
