//! The verdict on a primary selection: "hit", or why it cannot be trusted ("MISS: …",
//! "unverified: …"), with notes on an ambiguous or borrowed centre.

use super::find::Centre;
use super::params::Localize;
use super::params::Params;
use super::params::Rule;
use super::result::{SelectResult, Selection};
use super::tiles;

/// The verdict on `result`'s primary selection under `params`, with notes on its centre.
pub(super) fn verdict_of(params: &Params, result: &SelectResult, has_truth: bool) -> String {
    let rule = params.primary;
    let primary = result.selection(rule);
    let line = verdict(rule, primary, has_truth, result.annotated_diameter_mm.is_some(), params);
    let centre = result.centres.of(rule);
    let tiled = (!result.tiles.is_empty()).then(|| tiles::margin_note(&result.tiles, rule)).flatten();
    let notes = [centre.and_then(rival_note), centre.and_then(fallback_note), tiled];
    match primary {
        Some(_) => std::iter::once(line).chain(notes.into_iter().flatten()).collect::<Vec<_>>().join("; "),
        None => line,
    }
}

/// What the verdict adds when `centre` is ambiguous: where its rival lies and how strongly it
/// answers.
fn rival_note(centre: &Centre) -> Option<String> {
    let rival = centre.runner_up.as_ref().filter(|_| centre.ambiguous)?;
    Some(format!(
        "ambiguous: another blob {:.0} mm away answers at {:.2} of this one's response ([select.blob] rival_ratio)",
        rival.distance_mm, rival.ratio
    ))
}

fn fallback_note(centre: &Centre) -> Option<String> {
    let why = match (centre.from_blind, centre.replaced_guided_peak) {
        (false, _) => return None,
        (true, None) => "the guided search found no blob of the annotated size".to_string(),
        (true, Some(peak)) => format!(
            "the guided search's blob barely stands out (peak contrast {peak:.3}, under [select.blob] \
             guided_faint_ratio of this one's)"
        ),
    };
    Some(format!("{why}: this is the blind search's centre ([select.blob] guided_fallback)"))
}

/// One line saying whether `primary` can be trusted: "hit", or why not ("MISS: …").
pub fn verdict(
    rule: Rule,
    primary: Option<&Selection>,
    has_truth: bool,
    has_diameter: bool,
    params: &Params,
) -> String {
    match (primary, has_truth) {
        (None, _) if rule == Rule::Guided && !has_diameter => {
            "unverified: no annotated diameter, so the guided rule cannot choose (set [select] primary to a blind rule)"
                .into()
        }
        (None, _) if params.sizing.cuts_half_max() => "MISS: no nodule centre was found whose half-maximum \
             region is of a nodule's size ([sweep] diameter_mm; for the guided rule also \
             [select.half_max] guided_diameter_ratio × the annotated diameter)"
            .into(),
        (None, _) if params.localize != Localize::None => {
            "MISS: no nodule centre was found, or no candidate of the sweep holds it".into()
        }
        (None, _) => "MISS: no candidate survived the sweep".into(),
        (Some(_), false) => "unverified: no ground truth to localise against".into(),
        (Some(s), true) => match s.localization {
            Some(l) if l.hit => "hit".into(),
            Some(l) => format!(
                "MISS: the selected component does not touch the nodule (Dice {:.2}, centroid {:.1} mm away); \
                 its volume measures something else",
                l.dice, l.centroid_distance_mm
            ),
            None => "unverified".into(),
        },
    }
}
