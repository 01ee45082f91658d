//! Small order statistics shared across the pipeline.

/// Median of a non-empty list, as numpy computes it (the mean of the two middle values for an
/// even count). Used for slice gaps everywhere a slice spacing is needed, so DICOM ingest,
/// the LIDC ground truth and the phantom agree.
pub fn median(values: &[f64]) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let mid = v.len() / 2;
    if v.len() % 2 == 1 {
        v[mid]
    } else {
        (v[mid - 1] + v[mid]) / 2.0
    }
}

/// The median gap between consecutive positions (a slice spacing).
pub fn median_gap(positions: &[f64]) -> f64 {
    let gaps: Vec<f64> = positions.windows(2).map(|w| w[1] - w[0]).collect();
    median(&gaps)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_is_numpys() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median_gap(&[0.0, 2.5, 5.0, 8.0]), 2.5);
    }
}
