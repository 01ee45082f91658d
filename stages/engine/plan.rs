//! Deciding, for one (unit, stage), whether the cache serves it, and if not, why not.
//!
//! Shared by `run` (which acts on it), `run --dry-run` and `status` (which print it).

use super::key::{Hash, KeyParts};
use super::source::SourceFile;
use super::stage::{Finished, Stage, SOURCE};
use super::store::{Expected, Lookup, Manifest, Store};
use std::collections::BTreeMap;

/// The key of a stage for a unit, with what it was computed from.
pub struct Keyed {
    pub key: Hash,
    pub params: serde_json::Value,
    pub inputs: Vec<(String, String, Hash)>,
}

/// The `(stage, output, hash)` triples a per-patient stage reads.
pub fn patient_inputs(stage: &dyn Stage, sources: &[SourceFile], finished: &Finished) -> Vec<(String, String, Hash)> {
    let mut out = Vec::new();
    for &input in stage.inputs() {
        if input == SOURCE {
            out.extend(sources.iter().map(|f| (SOURCE.to_string(), f.rel.clone(), f.hash)));
        } else if let Some(outputs) = finished.get(input) {
            let read = outputs.iter().filter(|o| stage.reads(input, &o.name));
            out.extend(read.map(|o| (input.to_string(), o.name.clone(), o.hash)));
        }
    }
    out
}

/// The triples a gathering stage reads: those of the stages before the fan-out (in `base`),
/// then each replica's own, under `<replica>/<stage>`.
pub fn gathered_inputs(
    stage: &dyn Stage,
    sources: &[SourceFile],
    base: &Finished,
    replicas: &[Finished],
    names: &[String],
) -> Vec<(String, String, Hash)> {
    let mut out = patient_inputs(stage, sources, base);
    for (finished, name) in replicas.iter().zip(names) {
        let own = patient_inputs(stage, &[], finished).into_iter().filter(|t| !base.contains_key(t.0.as_str()));
        out.extend(own.map(|(s, n, h)| (format!("{name}/{s}"), n, h)));
    }
    out
}

/// Each patient's replicas' outputs (patients not fanned out: none), with the replicas' names.
pub struct CohortReplicas<'a> {
    pub finished: &'a BTreeMap<String, Vec<Finished>>,
    pub names: &'a [String],
}

/// The triples a cohort stage reads: every patient's outputs of its input stages (a fanned-out
/// patient's under `<patient>/<replica>/<stage>`), and the patients that failed (so a newly
/// failing patient changes the key).
pub fn cohort_inputs(
    stage: &dyn Stage,
    patients: &BTreeMap<String, Finished>,
    replicas: &CohortReplicas,
    cohort_finished: &Finished,
    failed: &[String],
) -> Vec<(String, String, Hash)> {
    let mut out = patient_inputs(stage, &[], cohort_finished);
    for (patient, finished) in patients {
        let own = replicas.finished.get(patient).map_or(&[][..], |r| &r[..]);
        for triple in gathered_inputs(stage, &[], finished, own, replicas.names) {
            out.push((format!("{patient}/{}", triple.0), triple.1, triple.2));
        }
    }
    out.extend(failed.iter().map(|p| ("failed".to_string(), p.clone(), Hash::of(b""))));
    out
}

pub fn key(stage: &dyn Stage, unit: &str, inputs: Vec<(String, String, Hash)>) -> Keyed {
    let params = stage.params();
    let key = KeyParts { stage: stage.name(), version: stage.version(), params: &params, unit, inputs: &inputs }.key();
    Keyed { key, params, inputs }
}

/// Cached (with its manifest), or to be computed (with the reasons).
pub enum Decision {
    Cached(Box<Manifest>),
    /// Served by the remote cache (see [`Lookup::Fetched`]).
    Fetched(Box<Manifest>),
    Compute(Vec<String>),
    /// To be computed because its cache entry failed a check (a corrupt or missing blob, a
    /// manifest that does not match its key or digest): the reason names the stage, the unit
    /// and the file. A run warns of it.
    Distrusted(String),
}

/// The reason a forced stage computes.
pub const FORCED: &str = "forced with --force";

pub fn decide(store: &Store, stage: &dyn Stage, unit: &str, keyed: &Keyed, verify: bool, forced: bool) -> Decision {
    if forced {
        return Decision::Compute(vec![FORCED.into()]);
    }
    let expected = Expected { unit, inputs: &keyed.inputs };
    match store.lookup(stage.name(), &keyed.key, &expected, verify) {
        Lookup::Hit(m) => Decision::Cached(m),
        Lookup::Fetched(m) => Decision::Fetched(m),
        Lookup::Broken(why) => Decision::Distrusted(why),
        Lookup::Miss => Decision::Compute(why_stale(store, stage, unit, keyed)),
    }
}

/// Compares what the stage would be keyed by now with what it was last computed from.
pub fn why_stale(store: &Store, stage: &dyn Stage, unit: &str, keyed: &Keyed) -> Vec<String> {
    let Some(last) = store.latest(stage.name(), unit) else {
        return vec!["never run".into()];
    };
    let mut reasons = own_changes(&last, stage, &keyed.params);
    let old: Vec<(String, String, Hash)> =
        last.inputs.iter().map(|i| (i.stage.clone(), i.name.clone(), i.hash)).collect();
    reasons.extend(input_changes(&old, &keyed.inputs));
    if reasons.is_empty() {
        reasons.push("not in the cache (removed, or computed by another configuration)".into());
    }
    reasons
}

/// Changes of the stage itself (version, parameters) since `last` was computed.
pub fn own_changes(last: &Manifest, stage: &dyn Stage, params: &serde_json::Value) -> Vec<String> {
    let mut out = Vec::new();
    if last.version != stage.version() {
        out.push(format!("stage version changed ({} → {})", last.version, stage.version()));
    }
    out.extend(param_changes(&last.params, params));
    out
}

/// `param name: old → new` for every parameter that differs (nested keys dotted).
pub fn param_changes(old: &serde_json::Value, new: &serde_json::Value) -> Vec<String> {
    let (mut a, mut b) = (BTreeMap::new(), BTreeMap::new());
    flatten("", old, &mut a);
    flatten("", new, &mut b);
    let names: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    let show = |v: Option<&String>| v.cloned().unwrap_or_else(|| "(unset)".into());
    names
        .into_iter()
        .filter(|n| a.get(*n) != b.get(*n))
        .map(|n| format!("parameter `{n}` changed: {} → {}", show(a.get(n)), show(b.get(n))))
        .collect()
}

fn flatten(prefix: &str, v: &serde_json::Value, out: &mut BTreeMap<String, String>) {
    match v {
        serde_json::Value::Object(map) if !map.is_empty() => {
            for (k, v) in map {
                let name = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                flatten(&name, v, out);
            }
        }
        serde_json::Value::Object(_) if prefix.is_empty() => {}
        other => {
            out.insert(prefix.to_string(), other.to_string());
        }
    }
}

fn input_changes(old: &[(String, String, Hash)], new: &[(String, String, Hash)]) -> Vec<String> {
    let old_map: BTreeMap<(&str, &str), Hash> = old.iter().map(|(s, n, h)| ((s.as_str(), n.as_str()), *h)).collect();
    let new_map: BTreeMap<(&str, &str), Hash> = new.iter().map(|(s, n, h)| ((s.as_str(), n.as_str()), *h)).collect();
    let mut changed: Vec<String> = Vec::new();
    for (k, h) in &new_map {
        match old_map.get(k) {
            None => changed.push(format!("{}/{} (new)", k.0, k.1)),
            Some(o) if o != h => changed.push(format!("{}/{}", k.0, k.1)),
            _ => {}
        }
    }
    changed.extend(old_map.keys().filter(|k| !new_map.contains_key(*k)).map(|k| format!("{}/{} (gone)", k.0, k.1)));
    if changed.is_empty() {
        return vec![];
    }
    const SHOWN: usize = 3;
    let more = changed.len().saturating_sub(SHOWN);
    let mut line = format!("input changed: {}", changed[..changed.len().min(SHOWN)].join(", "));
    if more > 0 {
        line.push_str(&format!(" and {more} more"));
    }
    vec![line]
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn param_changes_name_old_and_new() {
        let c = param_changes(&json!({"hu_max": 400, "hu_min": -1000}), &json!({"hu_max": 500, "hu_min": -1000}));
        assert_eq!(c, vec!["parameter `hu_max` changed: 400 → 500"]);
        assert!(param_changes(&json!({}), &json!({})).is_empty());
        let nested = param_changes(&json!({"a": {"b": 1}}), &json!({"a": {"b": 1, "c": true}}));
        assert_eq!(nested, vec!["parameter `a.c` changed: (unset) → true"]);
    }

    #[test]
    fn input_changes_are_summarised() {
        let h = |s: &str| Hash::of(s.as_bytes());
        let old = vec![("source".into(), "a.dcm".into(), h("a")), ("source".into(), "b.dcm".into(), h("b"))];
        let new = vec![("source".into(), "a.dcm".into(), h("A")), ("source".into(), "c.dcm".into(), h("c"))];
        let c = input_changes(&old, &new);
        assert_eq!(c, vec!["input changed: source/a.dcm, source/c.dcm (new), source/b.dcm (gone)"]);
    }
}
