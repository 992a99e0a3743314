//! Summary statistics shared by the load test, the demo and the daemon's latency rings.

/// Nearest-rank percentile `q` ∈ [0, 1] of `v` (sorted in place), `None` when `v` is empty.
pub fn percentile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let rank = (q * v.len() as f64).ceil() as usize;
    Some(v[rank.clamp(1, v.len()) - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank() {
        let mut v = [4.0, 2.0, 3.0, 1.0];
        assert_eq!(percentile(&mut v, 0.5), Some(2.0));
        assert_eq!(percentile(&mut v, 0.99), Some(4.0));
        assert_eq!(percentile(&mut v, 0.0), Some(1.0));
        assert_eq!(percentile(&mut [], 0.5), None);
    }
}
