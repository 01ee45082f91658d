//! How a rule sizes the nodule once it has a centre (`[select] sizing`): one of the sweep's
//! candidates ([`candidates`]), the region at a fraction of the local contrast's peak
//! ([`half_max`]), or the ellipsoid that best explains that region's shadows in the three views
//! ([`shadows`]). A new sizing is a file here, a variant of [`Sizing`], and its arms below.

pub mod candidates;
pub mod half_max;
pub mod shadows;

use super::find::{Centre, Centres, Search, Weighed};
use super::params::{Params, Sizing};
use super::result::Selection;
use crate::kernels::localization::GroundTruthOnGrid;
use crate::stage::sweep::{Level, Params as SweepParams, Scored};
use crate::volume::Volume;
use candidates::Analysis;

/// What a sizing reads of one box.
pub struct Inputs<'a> {
    pub params: &'a Params,
    pub density: &'a Volume<f32>,
    pub scored: &'a Scored,
    pub sweep: &'a SweepParams,
    pub levels: &'a [Level],
    pub analysis: &'a Analysis<'a>,
    pub gt: Option<&'a GroundTruthOnGrid>,
    /// The three DRRs, when the sizing reads them ([`reads_views`]).
    pub views: Option<&'a shadows::Views>,
    /// The guided rule's diameter (none without an annotation).
    pub annotated_mm: Option<f64>,
}

/// One rule's selection and its mask over the lattice; none when it could not size.
pub type Sized = Option<(Selection, Vec<bool>)>;

/// Whether `search` accepts the blob at `centre`, with the region it judged it by.
pub fn weigh(inputs: &Inputs, search: Search, centre: &Centre) -> Weighed {
    match inputs.params.sizing {
        Sizing::Candidates => Weighed::Accepted { region: None },
        Sizing::HalfMax | Sizing::Shadows => half_max::weigh(inputs, search, centre),
    }
}

/// Each rule's selection at its centre, in `Rule` order: guided, blind_largest,
/// blind_persistent.
pub fn size(inputs: &Inputs, centres: &Centres) -> [Sized; 3] {
    match inputs.params.sizing {
        Sizing::Candidates => candidates::size(inputs, centres),
        Sizing::HalfMax => half_max::size(inputs, centres),
        Sizing::Shadows => shadows::size(inputs, centres),
    }
}

/// Whether `sizing` reads the three DRRs.
pub fn reads_views(sizing: Sizing) -> bool {
    sizing == Sizing::Shadows
}
