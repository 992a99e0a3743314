//! The range noise a scan's own returns show, beyond what its header states.
//!
//! A scan header carries one noise coefficient per metre of range (σ = k · r). Real devices also
//! have a floor that holds at every range (a VLP-16 about 3 cm, an OS1-64 1.5–3 cm), which no
//! header field states; a map fitted with millimetre noise near the sensor interpolates 3 cm of
//! noise as if it were relief, and its σ claims millimetres. So the daemon measures the floor
//! from every scan: along a ring, the range of neighbouring columns on smooth ground changes
//! almost linearly, and the second difference r₋₁ − 2r₀ + r₁ is then noise alone, of variance
//! 6σ². Relief that bends within a few centimetres adds to it; the second difference at lag 2
//! (r₋₂ − 2r₀ + r₂, five consecutive columns in all) tells the two apart (noise gives both lags
//! the same spread, curvature four times as much at lag 2), and the nearest returns, where the
//! ground is met steeply and the columns are closest, carry the estimate. Medians keep edges
//! and objects out. The floor is capped at [`MAX_FLOOR_M`]: beyond it the scan is not ground a
//! lidar measures to centimetres, and one such scan must not make every ray of its map noise.

use rangegp_proto::scan::{ScanPoint, FLAG_RING_COLUMN_VALID};

/// Samples (a return with two returned neighbours each side along its ring) needed before a
/// floor is estimated (fewer: the header's model stands).
pub const MIN_TRIPLES: usize = 200;
/// Share of the samples, nearest first, that the estimate uses (at least [`MIN_TRIPLES`]).
const NEAR_SHARE: f64 = 0.25;
/// A ring × column table of more cells than this many per indexed return is not built (no
/// estimate): ring and column come from the driver, and a stray index must not make the table
/// large (an organised cloud has about one cell per point).
const MAX_CELLS_PER_RETURN: usize = 4;
/// Largest floor reported, metres (lidar datasheets give 1–5 cm).
pub const MAX_FLOOR_M: f64 = 0.25;
/// The median of a χ² variable of one degree of freedom: median(d²) = 0.4549 · var(d) for a
/// zero-mean Gaussian d.
const CHI2_1_MEDIAN: f64 = 0.454_936;

/// The range noise floor, metres (at most [`MAX_FLOOR_M`]), that the returns of `points` show
/// beyond the header's `range_noise_per_m` (σ(r)² = floor² + (k·r)²); only returns in
/// (0, `max_range_m`) count, as for the map. `None` when the driver gives no ring and column
/// indices, when its indices span more than `MAX_CELLS_PER_RETURN` cells per return, or when
/// fewer than [`MIN_TRIPLES`] returns have two returned neighbours each side along their ring.
pub fn range_noise_floor(points: &[ScanPoint], range_noise_per_m: f64, max_range_m: f64) -> Option<f64> {
    let returns: Vec<(usize, usize, f64)> = points
        .iter()
        .filter(|p| p.flags & FLAG_RING_COLUMN_VALID != 0 && p.has_return())
        .map(|p| (p.ring as usize, p.column as usize, p.range_m as f64))
        .filter(|&(_, _, r)| r.is_finite() && r > 0.0 && r < max_range_m)
        .collect();
    let (rings, columns) = returns.iter().fold((0, 0), |(r, c), &(ring, column, _)| {
        (r.max(ring + 1), c.max(column + 1))
    });
    let cells = rings.checked_mul(columns)?;
    if cells == 0 || cells > MAX_CELLS_PER_RETURN.saturating_mul(returns.len()) {
        return None;
    }
    let mut table = vec![f64::NAN; cells];
    for &(ring, column, r) in &returns {
        table[ring * columns + column] = r;
    }
    // (range, lag-1 d², lag-2 d²) of each column with both neighbours at both lags returned.
    let mut triples: Vec<(f64, f64, f64)> = Vec::new();
    for row in table.chunks_exact(columns) {
        for c in 2..columns.saturating_sub(2) {
            let [a2, a1, m, b1, b2] = [row[c - 2], row[c - 1], row[c], row[c + 1], row[c + 2]];
            if [a2, a1, m, b1, b2].iter().all(|v| v.is_finite()) {
                triples.push((m, (a1 - 2.0 * m + b1).powi(2), (a2 - 2.0 * m + b2).powi(2)));
            }
        }
    }
    if triples.len() < MIN_TRIPLES {
        return None;
    }
    let near = ((triples.len() as f64 * NEAR_SHARE) as usize).max(MIN_TRIPLES.min(triples.len()));
    if near < triples.len() {
        triples.select_nth_unstable_by(near, |a, b| a.0.total_cmp(&b.0));
        triples.truncate(near);
    }
    let median = |f: &dyn Fn(&(f64, f64, f64)) -> f64| {
        let mut v: Vec<f64> = triples.iter().map(f).collect();
        let mid = v.len() / 2;
        *v.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let (lag1, lag2) = (median(&|t| t.1), median(&|t| t.2));
    // Noise: both lags at 6σ²; curvature: lag 2 at 16× lag 1's. Richardson's extrapolation to no
    // spacing (lag 1 alone where lag 2 shows less, as noise alone may).
    let d2 = if lag2 > lag1 {
        (16.0 * lag1 - lag2) / 15.0
    } else {
        lag1
    };
    let total = d2.max(0.0) / (6.0 * CHI2_1_MEDIAN);
    let stated = median(&|t| (range_noise_per_m * t.0).powi(2));
    Some((total - stated).max(0.0).sqrt().min(MAX_FLOOR_M))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_pcg::Pcg64;
    use rangegp_sim::{simulate_scan, CraterParams, Heightmap, ScannerPreset};

    /// `preset`'s scan from 0.75 m above `terrain`'s centre, as ring- and column-indexed points.
    fn points(terrain: &Heightmap, preset: &ScannerPreset, seed: u64) -> Vec<ScanPoint> {
        let pose = rangegp_sim::level_pose(terrain, 0.0, 0.0, 0.0, preset.mount_height_m);
        simulate_scan(terrain, &pose, preset, &mut Pcg64::seed_from_u64(seed))
            .iter()
            .filter_map(|r| {
                Some(ScanPoint {
                    range_m: r.measured_range_m? as f32,
                    inclination_rad: r.inclination_rad as f32,
                    azimuth_rad: r.azimuth_rad as f32,
                    ring: r.ring,
                    column: r.column,
                    flags: FLAG_RING_COLUMN_VALID,
                    ..ScanPoint::default()
                })
            })
            .collect()
    }

    #[test]
    fn a_devices_floor_is_found_on_rough_ground_and_none_where_there_is_none() {
        let craters = Heightmap::cratered(4, &CraterParams::sized(80.0));
        for (preset, want) in [
            (ScannerPreset::vlp16().with_device_noise(), 0.03),
            (ScannerPreset::os1_64(1024).with_device_noise(), 0.015),
        ] {
            let floor = range_noise_floor(
                &points(&craters, &preset, 1),
                preset.range_noise_per_m,
                preset.max_range_m,
            )
            .expect("an estimate");
            assert!(
                (floor - want).abs() < 0.07 * want,
                "{}: {floor} for {want}",
                preset.name
            );
        }
        // The paper's scanner (2° columns over craters) and a VLP-16 without a floor: under a
        // millimetre (measured 0.3 and 0.2), against the centimetres of a device.
        for preset in [ScannerPreset::seed000(), ScannerPreset::vlp16()] {
            let floor = range_noise_floor(
                &points(&craters, &preset, 2),
                preset.range_noise_per_m,
                preset.max_range_m,
            )
            .expect("an estimate");
            assert!(floor < 0.001, "{}: {floor}", preset.name);
        }
    }

    #[test]
    fn without_ring_and_column_indices_the_header_stands() {
        let craters = Heightmap::cratered(4, &CraterParams::sized(40.0));
        let preset = ScannerPreset::vlp16().with_device_noise();
        let mut pts = points(&craters, &preset, 3);
        for p in &mut pts {
            p.flags = 0;
        }
        assert_eq!(range_noise_floor(&pts, preset.range_noise_per_m, 100.0), None);
        assert_eq!(range_noise_floor(&pts[..0], 0.0, 100.0), None);
    }

    #[test]
    fn stray_indices_far_returns_and_wild_ranges_neither_grow_the_table_nor_the_floor() {
        let craters = Heightmap::cratered(4, &CraterParams::sized(40.0));
        let preset = ScannerPreset::vlp16().with_device_noise();
        let good = points(&craters, &preset, 4);
        let k = preset.range_noise_per_m;
        // One point claiming column 65 535 would make a 16 × 65 536 table: refused.
        let mut stray = good.clone();
        stray[0].column = u16::MAX;
        stray[0].ring = u16::MAX;
        assert_eq!(range_noise_floor(&stray, k, 100.0), None);
        // Returns at or beyond the max range (junk a driver may send) are not samples.
        let mut junk = good.clone();
        for (i, p) in junk.iter_mut().enumerate() {
            p.range_m = if i % 2 == 0 {
                1e30
            } else {
                150.0 + (i % 7) as f32 * 40.0
            };
        }
        assert_eq!(range_noise_floor(&junk, k, 100.0), None);
        // Ranges that jump by metres from column to column (not ground): capped.
        let mut wild = good;
        for (i, p) in wild.iter_mut().enumerate() {
            p.range_m = 5.0 + (i % 5) as f32 * 8.0;
        }
        assert_eq!(range_noise_floor(&wild, k, 100.0), Some(MAX_FLOOR_M));
    }
}
