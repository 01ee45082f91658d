//! Where the guided search finds nothing it can size, or only a faint centre, the guided rule
//! takes the blind centre (`guided_fallback`, `guided_faint_ratio`).

use super::{Centre, Centres, Weighed};

impl Centres {
    /// The blind centre in place of the guided one, if `guided_accepts` it (the guided search's
    /// size check, against the annotated diameter), where the guided search found no centre or
    /// one whose region peaks below `faint_ratio` × the blind region's local contrast: a blob
    /// of the annotated size that barely stands out is weaker evidence than a contrasted one
    /// of a size the check allows (`faint_ratio` 0: only where it found none). Nothing changes
    /// otherwise.
    pub fn fall_back_to_blind(&mut self, faint_ratio: f64, guided_accepts: impl Fn(&Centre) -> Weighed) {
        let Some(blind) = self.blind.as_ref() else { return };
        let replaced_guided_peak = match &self.guided {
            None => None,
            Some(guided) => match (guided.region, blind.region) {
                (Some(own), Some(theirs)) if (own.peak_score as f64) < faint_ratio * theirs.peak_score as f64 => {
                    Some(own.peak_score)
                }
                _ => return,
            },
        };
        if let Weighed::Accepted { region } = guided_accepts(blind) {
            self.guided = Some(Centre { region, from_blind: true, replaced_guided_peak, ..blind.clone() });
        }
    }
}
