//! Content hashes and cache keys.
//!
//! A stage's cache key is a blake3 hash over its name, its version constant, the canonical
//! serialisation of its own parameters, the unit it runs for (a patient or the cohort), and the
//! content hashes of its inputs. Nothing else: editing another stage's parameters cannot change it.

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt;

/// A blake3 content hash, shown and stored as 64 hex digits.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Hash(pub [u8; 32]);

impl Hash {
    pub fn of(bytes: &[u8]) -> Hash {
        Hash(*blake3::hash(bytes).as_bytes())
    }

    pub fn hex(&self) -> String {
        blake3::Hash::from(self.0).to_hex().to_string()
    }

    pub fn from_hex(s: &str) -> Option<Hash> {
        blake3::Hash::from_hex(s).ok().map(|h| Hash(*h.as_bytes()))
    }

    /// The first 12 hex digits, for humans.
    pub fn short(&self) -> String {
        self.hex()[..12].to_string()
    }
}

impl fmt::Debug for Hash {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Hash({})", self.short())
    }
}

impl fmt::Display for Hash {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.hex())
    }
}

impl Serialize for Hash {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.hex())
    }
}

impl<'de> Deserialize<'de> for Hash {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Hash, D::Error> {
        let s = String::deserialize(d)?;
        Hash::from_hex(&s).ok_or_else(|| serde::de::Error::custom(format!("not a blake3 hex hash: {s}")))
    }
}

/// Canonical JSON: object keys sorted (serde_json's default map is ordered), no whitespace,
/// floats in their shortest round-trip form.
pub fn canonical_json(value: &serde_json::Value) -> String {
    serde_json::to_string(value).expect("a JSON value always serialises")
}

/// What a cache key is computed from. Inputs are `(stage, output name, content hash)` triples.
pub struct KeyParts<'a> {
    pub stage: &'a str,
    pub version: u32,
    pub params: &'a serde_json::Value,
    pub unit: &'a str,
    pub inputs: &'a [(String, String, Hash)],
}

impl KeyParts<'_> {
    pub fn key(&self) -> Hash {
        let mut h = blake3::Hasher::new();
        // Every field is length-prefixed so no two different part lists hash alike.
        let mut field = |bytes: &[u8]| {
            h.update(&(bytes.len() as u64).to_le_bytes());
            h.update(bytes);
        };
        field(b"aret-pipe cache key v1");
        field(self.stage.as_bytes());
        field(&self.version.to_le_bytes());
        field(canonical_json(self.params).as_bytes());
        field(self.unit.as_bytes());
        for (stage, name, hash) in self.inputs {
            field(stage.as_bytes());
            field(name.as_bytes());
            field(&hash.0);
        }
        Hash(*h.finalize().as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn canonical_json_sorts_keys() {
        let a: serde_json::Value = serde_json::from_str(r#"{"b":1,"a":2.5}"#).unwrap();
        assert_eq!(canonical_json(&a), r#"{"a":2.5,"b":1}"#);
    }

    #[test]
    fn key_changes_with_each_part() {
        let p = json!({"x": 1});
        let inputs = vec![("up".to_string(), "a.raw".to_string(), Hash::of(b"a"))];
        let base = KeyParts { stage: "s", version: 1, params: &p, unit: "P1", inputs: &inputs };
        let k = base.key();
        let p2 = json!({"x": 2});
        assert_ne!(k, KeyParts { params: &p2, ..base }.key());
        assert_ne!(k, KeyParts { version: 2, ..base }.key());
        assert_ne!(k, KeyParts { unit: "P2", ..base }.key());
        assert_ne!(k, KeyParts { stage: "t", ..base }.key());
        let inputs2 = vec![("up".to_string(), "a.raw".to_string(), Hash::of(b"b"))];
        assert_ne!(k, KeyParts { inputs: &inputs2, ..base }.key());
        assert_eq!(k, KeyParts { ..base }.key());
    }

    #[test]
    fn hash_hex_round_trip() {
        let h = Hash::of(b"hello");
        assert_eq!(Hash::from_hex(&h.hex()), Some(h));
        assert_eq!(Hash::from_hex("zz"), None);
    }
}
