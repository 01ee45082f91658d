//! How a search ranks the blobs it accepted: which it takes among those that answer alike
//! (`tie_break`), and its runner-up.

use super::{BlobRanker, Centre, RunnerUp, Search};
use crate::stage::select::params::{BlobParams, TieBreak};
use glam::DVec3;

impl BlobParams {
    /// How `search` judges between blobs that answer alike.
    pub fn tie_break_of(&self, search: Search) -> TieBreak {
        match search {
            Search::Guided => self.tie_break,
            Search::Blind => self.blind_tie_break,
        }
    }
}

/// The accepted blobs (strongest first) with the score `tie_break` ranks them by: for
/// `"learned"`, the learned ranking's ([`BlobRanker`]) of every one. Other tie-breaks score none.
pub(super) fn with_ranking_scores(mut accepted: Vec<Centre>, tie_break: TieBreak) -> Vec<Centre> {
    match tie_break {
        TieBreak::Response | TieBreak::Roundness => {}
        TieBreak::Learned => {
            let ranker = BlobRanker::built_in();
            let strongest = accepted.iter().filter_map(|c| c.blob).map(|b| b.response).fold(0.0, f32::max);
            for c in &mut accepted {
                c.ranking_score = ranker.score(c, strongest);
            }
        }
    }
    accepted
}

/// How far `other` lies from `taken`, if outside the ball `taken`'s scale is matched to (a ball
/// of radius √3·s answers most at scale s): another object, not a second peak of the same one.
fn another_object_mm(taken: &Centre, other: &Centre) -> Option<f64> {
    let distance_mm = DVec3::from(taken.position_mm).distance(DVec3::from(other.position_mm));
    (distance_mm > 3f64.sqrt() * taken.blob?.scale_mm).then_some(distance_mm)
}

/// `rival` as `taken`'s runner-up, if it is another object ([`another_object_mm`]).
fn runner_up(taken: &Centre, rival: &Centre) -> Option<RunnerUp> {
    let (mine, theirs) = (taken.blob?, rival.blob?);
    let distance_mm = another_object_mm(taken, rival)?;
    Some(RunnerUp {
        position_mm: rival.position_mm,
        response: theirs.response,
        scale_mm: theirs.scale_mm,
        distance_mm,
        ratio: f64::from(theirs.response) / f64::from(mine.response),
        rank: rival.rank,
        roundness: rival.roundness(),
    })
}

/// The blob a search takes among those it `accepted` (strongest first), with its runner-up:
/// the strongest by default, the roundest contender with `tie_break = "roundness"`, the best
/// ranked by the learned ranking with `"learned"`.
pub(super) fn pick(mut accepted: Vec<Centre>, params: &BlobParams, tie_break: TieBreak) -> Option<Centre> {
    let strongest = accepted.first()?.clone();
    let taken_at = match tie_break {
        TieBreak::Response => 0,
        TieBreak::Roundness => {
            let response = |c: &Centre| c.blob.map_or(0.0, |b| f64::from(b.response));
            let line = params.rival_ratio * response(&strongest);
            let contenders = accepted
                .iter()
                .enumerate()
                .filter(|(i, c)| *i == 0 || (response(c) >= line && another_object_mm(&strongest, c).is_some()));
            // The roundest; the stronger of two alike.
            contenders
                .fold(None::<(usize, f64)>, |best, (i, c)| {
                    let r = c.roundness().unwrap_or(0.0);
                    match best {
                        Some((_, b)) if b >= r => best,
                        _ => Some((i, r)),
                    }
                })
                .map_or(0, |(i, _)| i)
        }
        TieBreak::Learned => {
            // The best scored; the stronger of two alike.
            let score = |c: &Centre| c.ranking_score.unwrap_or(f64::NEG_INFINITY);
            accepted
                .iter()
                .enumerate()
                .fold((0, f64::NEG_INFINITY), |best, (i, c)| if score(c) > best.1 { (i, score(c)) } else { best })
                .0
        }
    };
    let mut taken = accepted.remove(taken_at);
    taken.runner_up = accepted.iter().find_map(|rival| runner_up(&taken, rival));
    taken.ambiguous = taken.runner_up.as_ref().is_some_and(|r| r.ratio >= params.rival_ratio);
    Some(taken)
}
