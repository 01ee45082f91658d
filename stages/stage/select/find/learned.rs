//! `blind_tie_break = "learned"`: the blind search takes the accepted blob that a ranking
//! learned on phantom anatomies scores highest. The ranking is a conditional logit over
//! features of each blob and its half-maximum region; `tools/train_blob_ranker.py` fits it and
//! writes `models/blob_ranker.json`, which is built into the binary. The features are defined
//! here and in that script, and a model whose feature names differ from these is refused.

use super::Centre;
use crate::stage::select::params::BLOB_RANKER_JSON;
use serde::Deserialize;
use std::sync::OnceLock;

/// The features, in the order of the model's weights, named as the training script names them.
pub const FEATURES: [&str; 9] = [
    "ln response",
    "ln response / strongest accepted",
    "ln peak contrast",
    "ln response / peak contrast",
    "roundness",
    "ln region diameter / reference",
    "|ln region diameter / reference|",
    "depth in the lung field / 10 mm",
    "rank / 16",
];

/// A learned ranking of blobs: score = Σ weight · (feature − mean) / sd.
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct BlobRanker {
    pub features: Vec<String>,
    /// What region diameters are measured against, mm (the blind search is told none).
    pub reference_diameter_mm: f64,
    /// Depth in the lung field counts up to this, mm.
    pub depth_cap_mm: f64,
    pub mean: Vec<f64>,
    pub sd: Vec<f64>,
    pub weights: Vec<f64>,
}

impl BlobRanker {
    /// The ranking built into the binary (`models/blob_ranker.json`, checked by the tests).
    pub fn built_in() -> &'static BlobRanker {
        static BUILT_IN: OnceLock<BlobRanker> = OnceLock::new();
        BUILT_IN.get_or_init(|| {
            BlobRanker::parse(BLOB_RANKER_JSON).unwrap_or_else(|e| panic!("models/blob_ranker.json: {e:#}"))
        })
    }

    /// A ranking from its JSON, refused unless it has this code's features and finite numbers.
    pub fn parse(text: &str) -> anyhow::Result<BlobRanker> {
        let ranker: BlobRanker = serde_json::from_str(text)?;
        if ranker.features != FEATURES {
            anyhow::bail!(
                "its features are {:?} and this build computes {FEATURES:?}: retrain it with \
                 tools/train_blob_ranker.py",
                ranker.features
            );
        }
        let n = FEATURES.len();
        if [ranker.mean.len(), ranker.sd.len(), ranker.weights.len()] != [n; 3] {
            anyhow::bail!("mean, sd and weights must each hold {n} numbers");
        }
        let finite = ranker.mean.iter().chain(&ranker.weights).all(|v| v.is_finite());
        let positive = ranker.sd.iter().chain([&ranker.reference_diameter_mm, &ranker.depth_cap_mm]);
        if !finite || !positive.into_iter().all(|v| v.is_finite() && *v > 0.0) {
            anyhow::bail!("mean and weights must be finite; sd, reference_diameter_mm and depth_cap_mm positive");
        }
        Ok(ranker)
    }

    /// A blob's features ([`FEATURES`]), among accepted blobs whose strongest response is
    /// `strongest_response`; none without a blob, a region, or a positive response and peak.
    pub fn features(&self, centre: &Centre, strongest_response: f32) -> Option<[f64; 9]> {
        let (blob, region) = (centre.blob?, centre.region?);
        let (response, peak) = (f64::from(blob.response), f64::from(region.peak_score));
        if !(response > 0.0 && peak > 0.0 && strongest_response > 0.0) {
            return None;
        }
        let diameter_ratio = (region.diameter_mm.max(1e-3) / self.reference_diameter_mm).ln();
        Some([
            response.ln(),
            (response / f64::from(strongest_response)).ln(),
            peak.ln(),
            (response / peak).ln(),
            region.roundness,
            diameter_ratio,
            diameter_ratio.abs(),
            centre.depth_mm.unwrap_or(0.0).min(self.depth_cap_mm) / 10.0,
            centre.rank as f64 / 16.0,
        ])
    }

    /// The blob's score ([`Self::features`]).
    pub fn score(&self, centre: &Centre, strongest_response: f32) -> Option<f64> {
        let x = self.features(centre, strongest_response)?;
        Some((0..x.len()).map(|j| self.weights[j] * (x[j] - self.mean[j]) / self.sd[j]).sum())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_ranking_reads_with_this_builds_features() {
        let ranker = BlobRanker::built_in();
        assert_eq!(ranker.weights.len(), FEATURES.len());
        let renamed = BLOB_RANKER_JSON.replacen("\"roundness\"", "\"sphericity\"", 1);
        let e = BlobRanker::parse(&renamed).unwrap_err().to_string();
        assert!(e.contains("sphericity") && e.contains("tools/train_blob_ranker.py"), "{e}");
    }
}
