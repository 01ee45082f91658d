//! How a rule sizes the nodule once it has a centre (`[select] sizing`): one of the sweep's
//! candidates ([`candidates`]), the region at a fraction of the local contrast's peak
//! ([`half_max`]), or the ellipsoid that best explains that region's shadows in the three views
//! ([`shadows`]).

pub mod candidates;
pub mod half_max;
pub mod shadows;
