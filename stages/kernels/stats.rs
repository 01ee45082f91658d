//! Small order statistics shared across the pipeline, computed as numpy computes them.

/// Median of a non-empty list, as numpy computes it (the mean of the two middle values for an
/// even count). Used for slice gaps everywhere a slice spacing is needed, so DICOM ingest,
/// the LIDC ground truth and the phantom agree.
pub fn median(values: &[f64]) -> f64 {
    // Not percentile 50: numpy's median averages the two middle values, its percentile
    // interpolates between them, and the two can differ in the last bit.
    let v = sorted(values);
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

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PercentileError {
    #[error("the percentile of no values is undefined")]
    Empty,
    #[error("percentiles must be in [0, 100], got {0}")]
    OutOfRange(f64),
}

/// `np.percentile(values, p)` for each `p` of `ps` (numpy's default method, "linear": the
/// order statistics at ranks ⌊h⌋ and ⌊h⌋ + 1, h = (n − 1)·p/100, interpolated). Sorts once.
/// Equal to numpy's result for float64 input, bit for bit: f32 data widened to f64 first equals
/// `np.percentile(x.astype(np.float64), p)`. Any NaN makes every result NaN, as in numpy.
pub fn percentiles(values: &[f64], ps: &[f64]) -> Result<Vec<f64>, PercentileError> {
    if values.is_empty() {
        return Err(PercentileError::Empty);
    }
    if let Some(&p) = ps.iter().find(|p| !(0.0..=100.0).contains(*p)) {
        return Err(PercentileError::OutOfRange(p));
    }
    let v = ordered_at(values, ps);
    Ok(ps.iter().map(|&p| percentile_of_sorted(&v, p)).collect())
}

/// `values` with the order statistics [`percentile_of_sorted`] reads for each `p` (and the
/// largest) at their ranks, as [`sorted`] would place them: selections in rank order, each in
/// what the one before left above it, instead of a sort. `total_cmp` is a total order, so the
/// value at each rank is the sort's, bit for bit.
fn ordered_at(values: &[f64], ps: &[f64]) -> Vec<f64> {
    let mut v = values.to_vec();
    let last = v.len() - 1;
    let mut ranks: Vec<usize> = ps
        .iter()
        .flat_map(|&p| {
            let below = ((last as f64 * (p / 100.0)).floor() as usize).min(last);
            [below, (below + 1).min(last)]
        })
        .chain([last])
        .collect();
    ranks.sort_unstable();
    ranks.dedup();
    let mut start = 0;
    for rank in ranks {
        v[start..].select_nth_unstable_by(rank - start, f64::total_cmp);
        start = rank + 1;
    }
    v
}

/// [`percentiles`] for one `p`.
pub fn percentile(values: &[f64], p: f64) -> Result<f64, PercentileError> {
    Ok(percentiles(values, &[p])?[0])
}

/// numpy's linear percentile of non-empty ascending `sorted` (NaNs last), `p` in [0, 100].
/// Every operation is numpy's, in its order (`_quantile` and `_lerp` of numpy 2), so the
/// rounding is too.
fn percentile_of_sorted(sorted: &[f64], p: f64) -> f64 {
    let n = sorted.len();
    if sorted[n - 1].is_nan() {
        return f64::NAN;
    }
    let h = (n - 1) as f64 * (p / 100.0);
    if h >= (n - 1) as f64 {
        return sorted[n - 1];
    }
    let below = h.floor();
    let (a, b) = (sorted[below as usize], sorted[below as usize + 1]);
    let t = h - below;
    let diff = b - a;
    // numpy's _lerp: from the nearer end, so t = 1 gives b exactly.
    if t >= 0.5 {
        b - diff * (1.0 - t)
    } else {
        a + diff * t
    }
}

/// An ascending copy (NaNs last). `total_cmp` is a total order, so an unstable sort gives the
/// same values in the same places as a stable one.
fn sorted(values: &[f64]) -> Vec<f64> {
    let mut v = values.to_vec();
    v.sort_unstable_by(f64::total_cmp);
    v
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

    #[test]
    fn percentile_is_numpys_linear() {
        // np.percentile([1, 2, 3, 4], [0, 25, 50, 90, 100]) = [1, 1.75, 2.5, 3.7, 4]
        let got = percentiles(&[4.0, 1.0, 3.0, 2.0], &[0.0, 25.0, 50.0, 90.0, 100.0]).unwrap();
        assert_eq!(got, vec![1.0, 1.75, 2.5, 3.7, 4.0]);
        // np.percentile([0.1, 0.7, 0.2], 85) = 0.5499999999999999 (numpy's rounding, not 0.55)
        assert_eq!(percentile(&[0.1, 0.7, 0.2], 85.0).unwrap(), 0.5499999999999999);
        assert_eq!(percentile(&[5.0], 37.0).unwrap(), 5.0);
        assert!(percentile(&[1.0, f64::NAN], 10.0).unwrap().is_nan());
        assert_eq!(percentile(&[], 50.0), Err(PercentileError::Empty));
        assert_eq!(percentile(&[1.0], 100.5), Err(PercentileError::OutOfRange(100.5)));
        assert_eq!(percentiles(&[1.0], &[-1.0]).unwrap_err().to_string(), "percentiles must be in [0, 100], got -1");
    }

    #[test]
    fn selections_read_what_a_sort_reads() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let ps = [99.0, 0.0, 85.0, 85.0, 37.5, 100.0, 50.0, 99.9, 1e-9];
        for n in [1, 2, 3, 10, 1001] {
            // Repeats, signed zeros and a wide range, as a density's values have.
            let values: Vec<f64> = (0..n)
                .map(|_| match rng.gen_range(0..4) {
                    0 => 0.0,
                    1 => -0.0,
                    2 => f64::from(rng.gen_range(-3i8..3)),
                    _ => rng.gen_range(-1e3..1e3),
                })
                .collect();
            let by_sort: Vec<f64> = ps.iter().map(|&p| percentile_of_sorted(&sorted(&values), p)).collect();
            let got = percentiles(&values, &ps).unwrap();
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                by_sort.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "n = {n}"
            );
        }
    }
}
