//! Where a map's data lie on the ground: the map-frame positions of the returns a range GP was
//! trained on, bucketed by their horizontal position, for the nearest one to a point.
//!
//! A range GP interpolates in angle. Between two rings of a VLP-16 twenty metres out lie metres
//! of ground that no return touched, yet the GP's own σ there is that of a few milliradians of
//! angle. How far an answer lies from the nearest datum, in metres on the ground, is what the
//! relief term of its σ is taken at ([`super::relief`]).

/// Farthest distance searched, metres: an answer farther from every datum counts as this far.
pub const MAX_DATA_DISTANCE_M: f64 = 16.0;
/// Most buckets an index holds, 512 KiB of offsets (a scan spread wider gets coarser buckets).
const MAX_BUCKETS: usize = 1 << 17;
/// Buckets per point of an even spread: returns crowd near the sensor, so buckets a quarter of
/// the mean spacing keep a near query's search to a few dozen points.
const BUCKETS_PER_POINT: f64 = 16.0;
/// Bounds of a bucket's side, metres.
const BUCKET_M: (f64, f64) = (0.1, 4.0);

/// Training returns bucketed by their horizontal position in the map frame.
#[derive(Debug, Clone, Default)]
pub struct DataIndex {
    /// Lower-left corner of bucket (0, 0), metres.
    origin: [f64; 2],
    /// Bucket side, metres.
    bucket_m: f64,
    cols: usize,
    rows: usize,
    /// Start of each bucket's points in `xyz` (one more than there are buckets).
    starts: Vec<u32>,
    /// Points (x, y relative to `origin`; z as given), bucket by bucket.
    xyz: Vec<[f32; 3]>,
    /// Distance from each bucket's centre to the nearest bucket holding a point, metres (a
    /// Euclidean distance transform): what [`Self::distance`] interpolates.
    field: Vec<f32>,
    /// Mean height of the points of that nearest bucket, metres: what [`Self::height_near`]
    /// interpolates.
    heights: Vec<f32>,
}

impl DataIndex {
    /// The index of `points` (non-finite ones are left out): buckets of a quarter of the points'
    /// mean horizontal spacing, at most `MAX_BUCKETS` of them.
    pub fn new(points: &[[f64; 3]]) -> Self {
        let finite: Vec<[f64; 3]> = points
            .iter()
            .copied()
            .filter(|p| p.iter().all(|v| v.is_finite()))
            .collect();
        let Some(&first) = finite.first() else {
            return Self::default();
        };
        let (lo, hi) = finite
            .iter()
            .fold(([first[0], first[1]], [first[0], first[1]]), |(lo, hi), p| {
                (
                    [lo[0].min(p[0]), lo[1].min(p[1])],
                    [hi[0].max(p[0]), hi[1].max(p[1])],
                )
            });
        let (w, h) = (hi[0] - lo[0], hi[1] - lo[1]);
        let mut bucket_m = ((w * h) / (BUCKETS_PER_POINT * finite.len() as f64))
            .sqrt()
            .clamp(BUCKET_M.0, BUCKET_M.1);
        let shape = |b: f64| ((w / b) as usize + 1, (h / b) as usize + 1);
        while shape(bucket_m).0 * shape(bucket_m).1 > MAX_BUCKETS {
            bucket_m *= 1.5;
        }
        let (cols, rows) = shape(bucket_m);
        let bucket = |p: &[f64; 3]| {
            let c = (((p[0] - lo[0]) / bucket_m) as usize).min(cols - 1);
            let r = (((p[1] - lo[1]) / bucket_m) as usize).min(rows - 1);
            r * cols + c
        };
        let mut starts = vec![0u32; cols * rows + 1];
        for p in &finite {
            starts[bucket(p) + 1] += 1;
        }
        for k in 1..starts.len() {
            starts[k] += starts[k - 1];
        }
        let mut next = starts.clone();
        let mut xyz = vec![[0f32; 3]; finite.len()];
        for p in &finite {
            let b = bucket(p);
            xyz[next[b] as usize] = [(p[0] - lo[0]) as f32, (p[1] - lo[1]) as f32, p[2] as f32];
            next[b] += 1;
        }
        let seeds: Vec<bool> = starts.windows(2).map(|w| w[1] > w[0]).collect();
        let mean_z: Vec<f32> = starts
            .windows(2)
            .map(|w| {
                let points = &xyz[w[0] as usize..w[1] as usize];
                let sum: f64 = points.iter().map(|p| f64::from(p[2])).sum();
                (sum / points.len().max(1) as f64) as f32
            })
            .collect();
        let (field, heights) = distance_transform(&seeds, cols, rows)
            .into_iter()
            .map(|(d2, seed)| ((d2.sqrt() * bucket_m) as f32, mean_z[seed]))
            .unzip();
        Self {
            origin: lo,
            bucket_m,
            cols,
            rows,
            starts,
            xyz,
            field,
            heights,
        }
    }

    /// Horizontal distance from (x, y) to the data, metres, at most [`MAX_DATA_DISTANCE_M`]
    /// (which an empty index always gives): the distance field between bucket centres,
    /// interpolated bilinearly, plus the way to the index's box from outside it. Continuous in
    /// (x, y); inside the box within a bucket's diagonal of the distance to the nearest point,
    /// outside it never much nearer (the sum over-states it); a few tens of nanoseconds (every
    /// elevation answer asks it).
    pub fn distance(&self, x: f64, y: f64) -> f64 {
        if self.field.is_empty() {
            return MAX_DATA_DISTANCE_M;
        }
        let (cu, cv, outside) = self.centre_coordinates(x, y);
        (self.bilinear(&self.field, cu, cv) + outside).min(MAX_DATA_DISTANCE_M)
    }

    /// The height of the data nearest to (x, y), metres: the mean height of the nearest bucket
    /// holding points, interpolated bilinearly between bucket centres (continuous in (x, y));
    /// `None` for an empty index. Where an answer far from its data has drifted toward its
    /// prior, this still shows the level of the ground the data saw there.
    pub fn height_near(&self, x: f64, y: f64) -> Option<f64> {
        if self.heights.is_empty() {
            return None;
        }
        let (cu, cv, _) = self.centre_coordinates(x, y);
        Some(self.bilinear(&self.heights, cu, cv))
    }

    /// (x, y) in the grid of bucket centres, clamped to it, and its distance outside it, metres.
    fn centre_coordinates(&self, x: f64, y: f64) -> (f64, f64, f64) {
        let b = self.bucket_m;
        let (u, v) = ((x - self.origin[0]) / b - 0.5, (y - self.origin[1]) / b - 0.5);
        let (cmax, rmax) = ((self.cols - 1) as f64, (self.rows - 1) as f64);
        let (cu, cv) = (u.clamp(0.0, cmax), v.clamp(0.0, rmax));
        (cu, cv, (u - cu).hypot(v - cv) * b)
    }

    /// `grid` (one value per bucket) interpolated bilinearly at bucket coordinates (`cu`, `cv`)
    /// inside the grid of bucket centres.
    fn bilinear(&self, grid: &[f32], cu: f64, cv: f64) -> f64 {
        let (c0, r0) = (cu.floor() as usize, cv.floor() as usize);
        let (c1, r1) = ((c0 + 1).min(self.cols - 1), (r0 + 1).min(self.rows - 1));
        let (wu, wv) = (cu - c0 as f64, cv - r0 as f64);
        let f = |c: usize, r: usize| f64::from(grid[r * self.cols + c]);
        (f(c0, r0) * (1.0 - wu) + f(c1, r0) * wu) * (1.0 - wv)
            + (f(c0, r1) * (1.0 - wu) + f(c1, r1) * wu) * wv
    }

    /// The indexed point horizontally nearest to (x, y) among those within `radius_m` (at most
    /// [`MAX_DATA_DISTANCE_M`]), with its horizontal distance: the search visits only the buckets
    /// that radius reaches.
    pub fn nearest_within(&self, x: f64, y: f64, radius_m: f64) -> Option<([f64; 3], f64)> {
        let radius_m = radius_m.min(MAX_DATA_DISTANCE_M);
        if self.xyz.is_empty() || radius_m.is_nan() || radius_m <= 0.0 {
            return None;
        }
        let (u, v) = (x - self.origin[0], y - self.origin[1]);
        let b = self.bucket_m;
        // Farther than the cap from the index's box: nothing to search.
        let (w, h) = (self.cols as f64 * b, self.rows as f64 * b);
        let (ox, oy) = ((-u).max(u - w).max(0.0), (-v).max(v - h).max(0.0));
        if ox.hypot(oy) >= radius_m {
            return None;
        }
        let (cu, cv) = ((u / b).floor() as i64, (v / b).floor() as i64);
        let mut best2 = radius_m * radius_m;
        let mut best = None;
        let rings = (radius_m / b).ceil() as i64 + 1;
        for ring in 0..=rings {
            // Every point of a bucket in this ring or beyond lies at least (ring − 1) buckets
            // away: once the best is nearer, no farther ring can beat it.
            let reach = (ring - 1).max(0) as f64 * b;
            if reach * reach >= best2 {
                break;
            }
            for r in (cv - ring)..=(cv + ring) {
                if r < 0 || r >= self.rows as i64 {
                    continue;
                }
                let edge = (r - cv).abs() == ring;
                let step = if edge { 1 } else { (2 * ring).max(1) as usize };
                for c in ((cu - ring)..=(cu + ring)).step_by(step) {
                    if c < 0 || c >= self.cols as i64 {
                        continue;
                    }
                    let k = r as usize * self.cols + c as usize;
                    for p in &self.xyz[self.starts[k] as usize..self.starts[k + 1] as usize] {
                        let d2 = (f64::from(p[0]) - u).powi(2) + (f64::from(p[1]) - v).powi(2);
                        if d2 < best2 {
                            best2 = d2;
                            best = Some(p);
                        }
                    }
                }
            }
        }
        best.map(|p| {
            let q = [
                f64::from(p[0]) + self.origin[0],
                f64::from(p[1]) + self.origin[1],
                f64::from(p[2]),
            ];
            (q, best2.sqrt())
        })
    }
}

/// Squared distances, in buckets, from each bucket of a `cols` × `rows` grid to the nearest
/// seed, with that seed's index (Felzenszwalb and Huttenlocher's exact transform: one pass along
/// rows, one along columns); `f64::INFINITY` (and index 0) everywhere without a seed.
fn distance_transform(seeds: &[bool], cols: usize, rows: usize) -> Vec<(f64, usize)> {
    let mut d: Vec<f64> = seeds
        .iter()
        .map(|&s| if s { 0.0 } else { f64::INFINITY })
        .collect();
    // After the pass along rows: the column of each bucket's nearest seed in its row.
    let mut seed_col = vec![0usize; d.len()];
    let mut line = Vec::new();
    for r in 0..rows {
        line.clear();
        line.extend_from_slice(&d[r * cols..(r + 1) * cols]);
        for (c, (v, q)) in lower_envelope(&line).into_iter().enumerate() {
            d[r * cols + c] = v;
            seed_col[r * cols + c] = q;
        }
    }
    let mut out = vec![(f64::INFINITY, 0); d.len()];
    for c in 0..cols {
        line.clear();
        line.extend((0..rows).map(|r| d[r * cols + c]));
        for (r, (v, q)) in lower_envelope(&line).into_iter().enumerate() {
            out[r * cols + c] = (v, q * cols + seed_col[q * cols + c]);
        }
    }
    out
}

/// The 1-D squared distance transform of `f`: min over q of (p − q)² + f(q), by the lower
/// envelope of the parabolas rooted at the finite entries, with the minimising q (0 where none
/// is finite).
fn lower_envelope(f: &[f64]) -> Vec<(f64, usize)> {
    let roots: Vec<usize> = (0..f.len()).filter(|&q| f[q].is_finite()).collect();
    let mut out = vec![(f64::INFINITY, 0); f.len()];
    if roots.is_empty() {
        return out;
    }
    // Parabolas of the envelope (their roots) and where each starts to hold.
    let mut hull: Vec<usize> = Vec::with_capacity(roots.len());
    let mut from: Vec<f64> = Vec::with_capacity(roots.len());
    let meet = |q: usize, p: usize| {
        let (q, p) = (q as f64, p as f64);
        ((f[q as usize] + q * q) - (f[p as usize] + p * p)) / (2.0 * (q - p))
    };
    for &q in &roots {
        while let Some(&p) = hull.last() {
            let s = meet(q, p);
            if from.last().is_some_and(|&start| s <= start) {
                hull.pop();
                from.pop();
            } else {
                from.push(s);
                break;
            }
        }
        if hull.is_empty() {
            from.clear();
            from.push(f64::NEG_INFINITY);
        }
        hull.push(q);
    }
    let mut k = 0;
    for (p, o) in out.iter_mut().enumerate() {
        while k + 1 < hull.len() && from[k + 1] < p as f64 {
            k += 1;
        }
        let q = hull[k];
        *o = ((p as f64 - q as f64).powi(2) + f[q], q);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The distance by brute force.
    fn brute(points: &[[f64; 3]], x: f64, y: f64) -> f64 {
        points
            .iter()
            .map(|p| (p[0] - x).hypot(p[1] - y))
            .fold(MAX_DATA_DISTANCE_M, f64::min)
    }

    #[test]
    fn the_height_near_a_point_is_its_nearest_datas_and_continuous() {
        // Two patches of data 10 m apart, one 1 m above the other.
        let mut points = Vec::new();
        for i in 0..20 {
            for j in 0..20 {
                let (x, y) = (i as f64 * 0.1, j as f64 * 0.1);
                points.push([x, y, 0.0]);
                points.push([x + 10.0, y, 1.0]);
            }
        }
        let index = DataIndex::new(&points);
        let near = |x: f64| index.height_near(x, 1.0).expect("data");
        assert!(near(1.0).abs() < 1e-6);
        assert!((near(11.0) - 1.0).abs() < 1e-6);
        // Nearer the first patch, mostly its height; across the gap no jump.
        assert!(near(3.5) < 0.5 && near(8.5) > 0.5);
        let mut x = 1.0;
        while x < 11.0 {
            assert!((near(x + 1e-6) - near(x)).abs() < 1e-3, "jump at {x}");
            x += 0.0137;
        }
        assert_eq!(DataIndex::new(&[]).height_near(0.0, 0.0), None);
    }

    #[test]
    fn the_distance_is_the_nearest_points_inside_and_outside_the_box() {
        // Rings of points as a scanner leaves them on flat ground: dense near, sparse far.
        let mut points = Vec::new();
        for ring in 1..12 {
            let r = 0.5 * 1.4f64.powi(ring);
            for k in 0..200 {
                let a = k as f64 * std::f64::consts::TAU / 200.0;
                points.push([3.0 + r * a.cos(), -2.0 + r * a.sin(), r]);
            }
        }
        points.push([f64::NAN, 1.0, 0.0]);
        let index = DataIndex::new(&points);
        let finite: Vec<[f64; 3]> = points.iter().copied().filter(|p| p[0].is_finite()).collect();
        for k in 0..2000 {
            let t = k as f64 * 0.618;
            let (x, y) = (3.0 + 40.0 * (t.sin()), -2.0 + 40.0 * ((1.7 * t).cos()));
            let (got, want) = (index.distance(x, y), brute(&finite, x, y));
            let diagonal = index.bucket_m * std::f64::consts::SQRT_2;
            let (u, v) = (x - index.origin[0], y - index.origin[1]);
            let inside = u >= 0.0
                && v >= 0.0
                && u <= index.cols as f64 * index.bucket_m
                && v <= index.rows as f64 * index.bucket_m;
            if inside {
                assert!(
                    (got - want).abs() <= diagonal,
                    "at ({x}, {y}): {got} against {want}"
                );
            } else {
                // Outside the box the way to it is added: never nearer than the data.
                assert!(got >= want - diagonal, "at ({x}, {y}): {got} against {want}");
            }
            if let Some((p, d)) = index.nearest_within(x, y, MAX_DATA_DISTANCE_M) {
                assert!((d - want).abs() < 1e-5, "the nearest point is the nearest");
                assert!(
                    ((p[0] - x).hypot(p[1] - y) - d).abs() < 1e-4,
                    "the point is that far"
                );
                assert!(
                    (p[2] - (p[0] - 3.0).hypot(p[1] + 2.0)).abs() < 1e-3,
                    "with its own z"
                );
            }
        }
        assert_eq!(index.distance(500.0, 0.0), MAX_DATA_DISTANCE_M);
        let (x, y) = (3.0 + 0.5 * 1.4f64.powi(11) + 2.0, -2.0);
        assert!(
            index.nearest_within(x, y, 1.9).is_none(),
            "2 m beyond the outer ring"
        );
        assert!(index.nearest_within(x, y, 2.1).is_some());
    }

    #[test]
    fn an_empty_index_is_far_from_everything() {
        assert_eq!(DataIndex::new(&[]).distance(0.0, 0.0), MAX_DATA_DISTANCE_M);
        assert_eq!(
            DataIndex::new(&[[f64::NAN, 0.0, 0.0]]).distance(0.0, 0.0),
            MAX_DATA_DISTANCE_M
        );
    }

    #[test]
    fn a_wide_scatter_keeps_its_buckets_bounded() {
        let points: Vec<[f64; 3]> = (0..1000)
            .map(|k| [k as f64 * 10.0, (k % 7) as f64 * 1000.0, 0.0])
            .collect();
        let index = DataIndex::new(&points);
        assert!(index.cols * index.rows <= MAX_BUCKETS);
        let (_, d) = index
            .nearest_within(5.0, 0.0, MAX_DATA_DISTANCE_M)
            .expect("a point 5 m away");
        assert!((d - 5.0).abs() < 1e-4);
    }

    #[test]
    fn the_transform_is_the_brute_force_one_and_names_the_nearest_seed() {
        let (cols, rows) = (23, 17);
        let seeds: Vec<bool> = (0..cols * rows).map(|k| k % 37 == 5 || k == 200).collect();
        let d = distance_transform(&seeds, cols, rows);
        for r in 0..rows {
            for c in 0..cols {
                let want = (0..cols * rows)
                    .filter(|&k| seeds[k])
                    .map(|k| ((k % cols) as f64 - c as f64).powi(2) + ((k / cols) as f64 - r as f64).powi(2))
                    .fold(f64::INFINITY, f64::min);
                let (d2, seed) = d[r * cols + c];
                assert_eq!(d2, want, "at ({c}, {r})");
                // The seed named is a seed at that distance.
                let at =
                    ((seed % cols) as f64 - c as f64).powi(2) + ((seed / cols) as f64 - r as f64).powi(2);
                assert!(seeds[seed] && at == want, "seed {seed} at ({c}, {r})");
            }
        }
        assert!(distance_transform(&[false; 6], 3, 2)
            .iter()
            .all(|v| v.0.is_infinite()));
    }

    #[test]
    fn the_distance_is_continuous() {
        let points: Vec<[f64; 3]> = (0..400)
            .map(|k| [(k % 20) as f64 * 0.7, (k / 20) as f64 * 1.3, 0.0])
            .collect();
        let index = DataIndex::new(&points);
        let mut last = index.distance(-5.0, 3.0);
        for k in 1..=40_000 {
            let x = -5.0 + k as f64 * 1e-3;
            let d = index.distance(x, 3.0);
            assert!((d - last).abs() <= 2.5e-3, "jump at x = {x}: {last} to {d}");
            last = d;
        }
    }
}
