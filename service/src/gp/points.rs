//! Training inputs stored coordinate by coordinate (structure of arrays): the layout the vector
//! kernels of `gp::vector` load four inputs at a time from, with no gather.

/// `len` points of R^D in one allocation: every x₀, then every x₁, … .
#[derive(Debug, Clone, PartialEq)]
pub struct Points<const D: usize> {
    len: usize,
    coords: Vec<f64>,
}

impl<const D: usize> Points<D> {
    /// The points of `points`, in order.
    pub fn new(points: &[[f64; D]]) -> Self {
        let coords = (0..D).flat_map(|k| points.iter().map(move |p| p[k])).collect();
        Self {
            len: points.len(),
            coords,
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there are no points.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Coordinate `k` of every point (panics when `k ≥ D`: misuse).
    pub fn coord(&self, k: usize) -> &[f64] {
        assert!(k < D, "coordinate {k} of a point in R^{D}");
        &self.coords[k * self.len..(k + 1) * self.len]
    }

    /// Point `i` (panics when out of range: misuse).
    pub fn get(&self, i: usize) -> [f64; D] {
        assert!(i < self.len, "point {i} of {}", self.len);
        std::array::from_fn(|k| self.coords[k * self.len + i])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_round_trip_by_coordinate() {
        let pts = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
        let p = Points::new(&pts);
        assert_eq!(p.len(), 2);
        assert_eq!(p.coord(1), &[2.0, 5.0]);
        assert_eq!(p.get(1), pts[1]);
        assert!(Points::<3>::new(&[]).is_empty());
    }
}
