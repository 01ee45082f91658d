//! Training a TensoRF attenuation field to three radiographs (SPEC §3 train), as separate
//! kernels the GPU backend can mirror one for one: compose the dense field ([`field`]), march
//! and render a ray batch with its loss and the scatter of `dL/dF` ([`render`]), contract to
//! the factors ([`field`]; in f32, [`compose`] and [`contract`]), regularisers
//! ([`regularize`]), Adam ([`adam`]). The step's randomly read buffers live on huge pages
//! ([`huge_pages`]). A dense lattice under 3-D TV is fitted by [`dense_tv`]; [`truth`] puts the
//! true CT on the lattice instead, as a ceiling.

pub mod adam;
#[cfg(target_arch = "x86_64")]
pub mod compose;
pub mod contract;
pub mod dense_tv;
pub mod field;
pub mod fit;
pub mod gemm;
pub mod huge_pages;
pub mod params;
pub mod projector;
pub mod regularize;
pub mod render;
pub mod truth;
