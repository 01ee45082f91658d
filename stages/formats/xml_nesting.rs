//! How deeply an XML text nests its elements, found in one linear pass before a tree parser
//! sees it.
//!
//! roxmltree, which reads the LIDC XML, descends one Rust call per open element, so a document
//! nested a few thousand deep overflows the thread's stack and aborts the whole process (no
//! error, no `catch_unwind`). This pass counts the nesting the same way the parser recurses —
//! one level per start tag that ends in `>` rather than `/>`, one level back per `</` — skipping
//! comments, CDATA sections, processing instructions and quoted attribute values, so that a
//! caller can refuse a document deeper than its limit before parsing it.
//!
//! It never under-counts a document the parser would read: on a well-formed prefix the two agree,
//! and where the text stops being XML the parser stops with an error at that point. Where this
//! pass is unsure (a `<!` that is neither a comment nor CDATA: a DOCTYPE, which the parser
//! refuses), it stops counting.

/// Where a document first nests deeper than `limit`: the byte offset of the start tag that does,
/// or `None` when it stays within the limit.
pub fn first_deeper_than(text: &str, limit: usize) -> Option<usize> {
    let bytes = text.as_bytes();
    let mut depth = 0usize;
    let mut pos = 0;
    while let Some(found) = find_byte(bytes, pos, b'<') {
        let rest = &bytes[found..];
        pos = if rest.starts_with(b"<!--") {
            skip_past(bytes, found + 4, b"-->")
        } else if rest.starts_with(b"<![CDATA[") {
            skip_past(bytes, found + 9, b"]]>")
        } else if rest.starts_with(b"<?") {
            skip_past(bytes, found + 2, b"?>")
        } else if rest.starts_with(b"<!") {
            return None;
        } else if rest.starts_with(b"</") {
            depth = depth.saturating_sub(1);
            skip_past(bytes, found + 2, b">")
        } else {
            let (end, empty) = start_tag_end(bytes, found + 1);
            if !empty {
                depth += 1;
                if depth > limit {
                    return Some(found);
                }
            }
            end
        };
    }
    None
}

fn find_byte(bytes: &[u8], from: usize, wanted: u8) -> Option<usize> {
    bytes.get(from..)?.iter().position(|&b| b == wanted).map(|at| from + at)
}

/// The offset just past the first `marker` at or after `from` (the text's end if none).
fn skip_past(bytes: &[u8], from: usize, marker: &[u8]) -> usize {
    let tail = bytes.get(from..).unwrap_or(&[]);
    match tail.windows(marker.len()).position(|w| w == marker) {
        Some(at) => from + at + marker.len(),
        None => bytes.len(),
    }
}

/// The offset past a start tag whose name begins at `from`, and whether it is empty (`/>`).
/// Quoted attribute values may hold `>` and `/`, so quotes are skipped whole.
fn start_tag_end(bytes: &[u8], from: usize) -> (usize, bool) {
    let mut pos = from;
    while pos < bytes.len() {
        match bytes[pos] {
            quote @ (b'"' | b'\'') => pos = find_byte(bytes, pos + 1, quote).map_or(bytes.len(), |q| q + 1),
            b'/' if bytes.get(pos + 1) == Some(&b'>') => return (pos + 2, true),
            b'>' => return (pos + 1, false),
            _ => pos += 1,
        }
    }
    (pos, false)
}

#[cfg(test)]
mod tests {
    use super::first_deeper_than;

    fn nested(depth: usize) -> String {
        format!("{}{}", "<a>".repeat(depth), "</a>".repeat(depth))
    }

    #[test]
    fn counts_open_elements_and_not_empty_ones() {
        assert_eq!(first_deeper_than(&nested(3), 3), None);
        assert_eq!(first_deeper_than(&nested(4), 3), Some(9));
        let flat = "<r>".to_string() + &"<e/><e x='1'/>".repeat(1000) + "</r>";
        assert_eq!(first_deeper_than(&flat, 1), None);
        let siblings = "<r>".to_string() + &"<e>1</e>".repeat(1000) + "</r>";
        assert_eq!(first_deeper_than(&siblings, 2), None);
        assert_eq!(first_deeper_than(&siblings, 1), Some(3));
    }

    #[test]
    fn markup_inside_comments_cdata_pis_and_quotes_does_not_count() {
        let text = "<?xml version=\"1.0\"?><r a=\"<b>/\" c='>'><!-- <x><x><x> --><![CDATA[<y><y>]]><?p <z>?></r>";
        assert_eq!(first_deeper_than(text, 1), None);
        // The same nesting outside them does count.
        assert_eq!(first_deeper_than("<r><x><x></x></x></r>", 2), Some(6));
    }

    #[test]
    fn a_start_tag_with_a_slash_inside_still_opens_a_level() {
        assert_eq!(first_deeper_than("<r><a href='x/'><b/></a></r>", 1), Some(3));
    }
}
