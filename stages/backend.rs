//! Where a stage computes (`[drr] backend`, `[train] backend`): plain data, read by the
//! stages' parameters and by the numeric code alike. [`crate::gpu::resolve`] turns `auto` into
//! what this machine has.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Cpu,
    Gpu,
    /// A hardware GPU when one exists, else the CPU (a software adapter such as lavapipe is
    /// slower than the CPU backend, so `auto` does not pick it; `gpu` does).
    Auto,
}

impl Backend {
    pub fn name(self) -> &'static str {
        match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
            Backend::Auto => "auto",
        }
    }
}
