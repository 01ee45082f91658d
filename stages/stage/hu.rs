//! `hu`: Hounsfield units to the unit interval (SPEC §3 hu; paper §4.2, §5.2c).
//!
//! Input: `ingest/ct_hu.mhd` + `ct_hu.raw` (int16 HU). Output: `ct_unit.mhd` + `ct_unit.raw`,
//! float32 `v = (clip(HU, hu_min, hu_max) − hu_min) / (hu_max − hu_min)` ∈ [0, 1], same geometry.

use crate::artifacts::{CT_HU, CT_UNIT};
use crate::engine::{Context, Output, Stage};
use crate::volume::Volume;
use anyhow::bail;
use serde::{Deserialize, Serialize};

pub const VERSION: u32 = 1;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Lower end of the HU window: air, mapped to 0.
    pub hu_min: f64,
    /// Upper end of the HU window, mapped to 1 (bone above it saturates).
    pub hu_max: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { hu_min: -1000.0, hu_max: 400.0 }
    }
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        if !(self.hu_min.is_finite() && self.hu_max.is_finite() && self.hu_min < self.hu_max) {
            bail!("[hu] needs finite hu_min < hu_max (got hu_min = {}, hu_max = {})", self.hu_min, self.hu_max);
        }
        Ok(())
    }
}

/// `v = (clip(hu) − min) / (max − min)`.
pub fn hu_to_unit(hu: f64, params: &Params) -> f32 {
    ((hu.clamp(params.hu_min, params.hu_max) - params.hu_min) / (params.hu_max - params.hu_min)) as f32
}

/// The whole stage as a pure function of the HU volume.
pub fn normalise(ct_hu: &Volume<i16>, params: &Params) -> Volume<f32> {
    ct_hu.map(|hu| hu_to_unit(f64::from(hu), params))
}

pub struct Hu {
    pub params: Params,
}

impl Stage for Hu {
    fn name(&self) -> &'static str {
        "hu"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["ingest"]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, _stage: &str, output: &str) -> bool {
        CT_HU.holds(output)
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let ct_hu: Volume<i16> = super::read_volume(ctx, CT_HU)?;
        Ok(Vec::from(super::volume_outputs(CT_UNIT, &normalise(&ct_hu, &self.params))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_maps_to_unit_interval() {
        let p = Params::default();
        assert_eq!(hu_to_unit(-1000.0, &p), 0.0);
        assert_eq!(hu_to_unit(-3024.0, &p), 0.0);
        assert_eq!(hu_to_unit(400.0, &p), 1.0);
        assert_eq!(hu_to_unit(2000.0, &p), 1.0);
        assert!((hu_to_unit(0.0, &p) - 1000.0 / 1400.0).abs() < 1e-7);
    }

    #[test]
    fn bad_window_is_an_error() {
        assert!(Params { hu_min: 10.0, hu_max: 10.0 }.check().is_err());
    }
}
