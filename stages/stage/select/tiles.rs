//! Comparing the boxes of `[drr] roi_center = "tiles"`: each box's searches find their own
//! centres, and each rule keeps the box whose centre scores most, its blob response × its
//! depth inside the lung field found in σ (`depth_mm`).
//!
//! Why depth: across boxes the hilum answers as strongly as a nodule or more, but its blind
//! centres lie near the lung field's edge (9–15 mm deep) while nodules in the parenchyma lie
//! deeper (29–43 mm). The rule was fixed on two pilot patients and then tested on seven held
//! out (lab/log.md, "Tiling the lungs with the paper's box").

use super::find::Centre;
use super::params::Rule;
use super::result::{Oracle, Selection, TileScore};
use super::Chosen;

/// A centre's score across boxes: its blob response × its depth inside the lung field.
pub fn score(centre: Option<&Centre>) -> Option<f64> {
    let centre = centre?;
    Some(f64::from(centre.blob.as_ref()?.response) * centre.depth_mm?)
}

/// The index of the highest score (the first, on a tie); none when no box has one.
pub fn best(scores: impl IntoIterator<Item = Option<f64>>) -> Option<usize> {
    let mut top: Option<(usize, f64)> = None;
    for (i, s) in scores.into_iter().enumerate() {
        if let Some(s) = s.filter(|s| s.is_finite()) {
            if top.is_none_or(|(_, t)| s > t) {
                top = Some((i, s));
            }
        }
    }
    top.map(|(i, _)| i)
}

/// One result over all boxes: the guided rule's selection and centre from the box whose guided
/// centre scores most, both blind rules' from the box whose blind centre does, and the primary
/// rule's box for the mask, mesh and previews. The oracle is the best over every box.
pub(super) fn combine(mut boxes: Vec<Chosen>, primary: Rule) -> Chosen {
    let table: Vec<TileScore> = boxes
        .iter()
        .map(|b| TileScore {
            tile: b.box_name.clone(),
            guided_score: score(b.result.centres.guided.as_ref()),
            blind_score: score(b.result.centres.blind.as_ref()),
            blind_on_nodule: b.result.centres.blind.as_ref().and_then(|c| c.on_nodule),
        })
        .collect();
    let guided_box = best(table.iter().map(|t| t.guided_score));
    let blind_box = best(table.iter().map(|t| t.blind_score));
    let tagged =
        |i: usize, s: &Option<Selection>| s.clone().map(|s| Selection { tile: Some(boxes[i].box_name.clone()), ..s });
    let guided = guided_box.and_then(|i| tagged(i, &boxes[i].result.guided));
    let blind_largest = blind_box.and_then(|i| tagged(i, &boxes[i].result.blind_largest));
    let blind_persistent = blind_box.and_then(|i| tagged(i, &boxes[i].result.blind_persistent));
    let guided_centres = guided_box.map(|i| &boxes[i].result.centres);
    let guided_centre = guided_centres.and_then(|c| c.guided.clone());
    let guided_accepted = guided_centres.map(|c| c.guided_accepted.clone()).unwrap_or_default();
    let blind_centres = blind_box.map(|i| &boxes[i].result.centres);
    let blind_centre = blind_centres.and_then(|c| c.blind.clone());
    let blind_accepted = blind_centres.map(|c| c.blind_accepted.clone()).unwrap_or_default();
    let oracle = best_oracle(boxes.iter().filter_map(|b| b.result.oracle.as_ref()));
    let candidates = boxes.iter().map(|b| b.result.candidates).sum();
    let shown = match primary {
        Rule::Guided => guided_box.or(blind_box),
        Rule::BlindLargest | Rule::BlindPersistent => blind_box.or(guided_box),
    };
    let mut out = boxes.swap_remove(shown.unwrap_or(0));
    let r = &mut out.result;
    (r.guided, r.blind_largest, r.blind_persistent) = (guided, blind_largest, blind_persistent);
    (r.centres.guided, r.centres.guided_accepted) = (guided_centre, guided_accepted);
    (r.centres.blind, r.centres.blind_accepted) = (blind_centre, blind_accepted);
    (r.oracle, r.candidates, r.tiles) = (oracle, candidates, table);
    // The primary's mask was cut in the box it is shown from; without a selection it has none.
    if r.selection(primary).is_none() {
        out.primary_mask = None;
    }
    out
}

/// What the verdict adds for a tiling: which box `rule`'s centre came from, and by how much it
/// scored over the next box's (a small margin: two places are nearly as likely).
pub fn margin_note(tiles: &[TileScore], rule: Rule) -> Option<String> {
    let score_of = |t: &TileScore| match rule {
        Rule::Guided => t.guided_score,
        Rule::BlindLargest | Rule::BlindPersistent => t.blind_score,
    };
    let top = best(tiles.iter().map(score_of))?;
    let top_score = score_of(&tiles[top])?;
    let others = tiles.iter().enumerate().filter(|(i, _)| *i != top).map(|(_, t)| score_of(t));
    let next =
        others.flatten().filter(|s| s.is_finite()).fold(None, |m: Option<f64>, s| Some(m.map_or(s, |m| m.max(s))));
    Some(match next {
        Some(next) if next > 0.0 => format!(
            "found in box {} of {}, scoring {:.2}× the next box",
            tiles[top].tile,
            tiles.len(),
            top_score / next
        ),
        _ => format!("found in box {} of {}, the only box with a centre", tiles[top].tile, tiles.len()),
    })
}

/// Could any candidate of any box have been right, and which came closest.
fn best_oracle<'a>(oracles: impl Iterator<Item = &'a Oracle>) -> Option<Oracle> {
    oracles.fold(None, |best: Option<Oracle>, o| match best {
        Some(b) if b.best_dice >= o.best_dice => Some(Oracle { any_hit: b.any_hit || o.any_hit, ..b }),
        Some(b) => Some(Oracle { any_hit: b.any_hit || o.any_hit, ..o.clone() }),
        None => Some(o.clone()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::lung_mask::BlobPeak;

    fn centre(response: f32, depth_mm: Option<f64>) -> Centre {
        let blob = Some(BlobPeak { voxel: [0; 3], response, scale_mm: 6.0 });
        Centre { blob, depth_mm, ..Centre::at([0; 3], [0.0; 3]) }
    }

    #[test]
    fn a_deep_blob_outranks_a_stronger_shallow_one() {
        // The pilot's 0003: the hilar box answers 0.105 at 12 mm deep, the nodule's 0.083 at 35 mm.
        let hilum = score(Some(&centre(0.105, Some(12.0))));
        let nodule = score(Some(&centre(0.083, Some(35.0))));
        assert_eq!(best([hilum, None, nodule]), Some(2));
        assert_eq!(score(Some(&centre(0.1, None))), None);
        assert_eq!(score(None), None);
    }

    #[test]
    fn the_first_box_wins_a_tie_and_no_score_is_no_box() {
        assert_eq!(best([Some(1.0), Some(2.0), Some(2.0)]), Some(1));
        assert_eq!(best([None, None]), None);
        assert_eq!(best([Some(f64::NAN), Some(-1.0)]), Some(1));
    }

    #[test]
    fn the_verdict_names_the_box_and_its_margin_over_the_next() {
        let tile = |name: &str, guided_score, blind_score| TileScore {
            tile: name.into(),
            guided_score,
            blind_score,
            blind_on_nodule: None,
        };
        let tiles = [tile("tile00", Some(1.0), Some(2.0)), tile("tile01", None, Some(3.0)), tile("tile02", None, None)];
        let blind = margin_note(&tiles, Rule::BlindPersistent).unwrap();
        assert_eq!(blind, "found in box tile01 of 3, scoring 1.50× the next box");
        let guided = margin_note(&tiles, Rule::Guided).unwrap();
        assert_eq!(guided, "found in box tile00 of 3, the only box with a centre");
        assert_eq!(margin_note(&tiles[2..], Rule::Guided), None);
    }

    #[test]
    fn the_oracle_is_the_best_box_and_any_hit_anywhere() {
        let o = |any_hit, best_dice| Oracle { any_hit, best_dice, best: None };
        let all = [o(true, 0.4), o(false, 0.6), o(false, 0.1)];
        assert_eq!(best_oracle(all.iter()), Some(o(true, 0.6)));
        assert_eq!(best_oracle([].iter()), None);
    }
}
