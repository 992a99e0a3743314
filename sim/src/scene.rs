//! Scenes a LiDAR can be cast against: the [`Surface`] trait, implemented by the heightmap and by
//! [`Tunnel`], the overhang scene of seed 000 §V-C (vertical walls under a roof, which no
//! elevation map can hold).

use crate::terrain::Heightmap;
use nalgebra::Vector3;

/// Anything a ray can hit.
pub trait Surface {
    /// Distance along the unit ray `dir` from `origin` to the first hit within `max_range`.
    fn cast(&self, origin: Vector3<f64>, dir: Vector3<f64>, max_range: f64) -> Option<f64>;

    /// Unit normal of the surface at a hit `p`, where the surface can tell (`None`: a scanner's
    /// weak-return model treats the hit as met squarely).
    fn normal(&self, _p: Vector3<f64>) -> Option<Vector3<f64>> {
        None
    }
}

impl Surface for Heightmap {
    fn cast(&self, origin: Vector3<f64>, dir: Vector3<f64>, max_range: f64) -> Option<f64> {
        Heightmap::cast(self, origin, dir, max_range)
    }

    /// From central differences of the heights one sample apart.
    fn normal(&self, p: Vector3<f64>) -> Option<Vector3<f64>> {
        let d = self.resolution();
        let dx = self.height(p.x + d, p.y)? - self.height(p.x - d, p.y)?;
        let dy = self.height(p.x, p.y + d)? - self.height(p.x, p.y - d)?;
        Some(Vector3::new(-dx, -dy, 2.0 * d).normalize())
    }
}

/// A straight tunnel along +x on flat ground at z = 0: walls at y = ±half_width, a flat roof at
/// z = height, open at both ends. Everything is a plane, so casting is exact (closed form).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tunnel {
    /// x where the tunnel starts, metres.
    pub x_start_m: f64,
    /// x where it ends, metres.
    pub x_end_m: f64,
    /// Half the inner width, metres.
    pub half_width_m: f64,
    /// Inner height of the roof above the floor, metres.
    pub height_m: f64,
}

impl Default for Tunnel {
    /// 4 m wide, 2.5 m high, from x = −20 m to x = 20 m: a mine drift.
    fn default() -> Self {
        Self {
            x_start_m: -20.0,
            x_end_m: 20.0,
            half_width_m: 2.0,
            height_m: 2.5,
        }
    }
}

impl Tunnel {
    /// Whether (x, y, z) is inside the tunnel's open interior (or outside it along x).
    fn inside(&self, p: &Vector3<f64>) -> bool {
        p.y.abs() < self.half_width_m && p.z > 0.0 && p.z < self.height_m
    }
}

impl Surface for Tunnel {
    /// Rays must start inside the tunnel; the first plane crossed (floor, roof or a wall) within
    /// the tunnel's length is the hit. Rays that leave through an open end return `None`.
    fn cast(&self, origin: Vector3<f64>, dir: Vector3<f64>, max_range: f64) -> Option<f64> {
        if !self.inside(&origin) {
            return None;
        }
        let mut best = f64::INFINITY;
        let mut consider = |t: f64| {
            if t > 0.0 && t < best {
                best = t;
            }
        };
        if dir.z < 0.0 {
            consider(-origin.z / dir.z);
        }
        if dir.z > 0.0 {
            consider((self.height_m - origin.z) / dir.z);
        }
        if dir.y > 0.0 {
            consider((self.half_width_m - origin.y) / dir.y);
        }
        if dir.y < 0.0 {
            consider((-self.half_width_m - origin.y) / dir.y);
        }
        let x = origin.x + dir.x * best;
        (best < max_range && x >= self.x_start_m && x <= self.x_end_m).then_some(best)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tunnel_hits_each_plane_in_closed_form() {
        let t = Tunnel::default();
        let o = Vector3::new(0.0, 0.0, 1.0);
        let down = Vector3::new(1.0, 0.0, -1.0).normalize();
        assert!((t.cast(o, down, 10.0).expect("floor") - 2f64.sqrt()).abs() < 1e-12);
        let up = Vector3::new(0.0, 0.0, 1.0);
        assert!((t.cast(o, up, 10.0).expect("roof") - 1.5).abs() < 1e-12);
        let side = Vector3::new(0.0, -1.0, 0.0);
        assert!((t.cast(o, side, 10.0).expect("wall") - 2.0).abs() < 1e-12);
        let along = Vector3::new(1.0, 0.0, 0.0);
        assert!(
            t.cast(o, along, 10.0).is_none(),
            "open along the axis within 10 m"
        );
        assert!(t.cast(Vector3::new(0.0, 3.0, 1.0), up, 10.0).is_none(), "outside");
    }

    #[test]
    fn overhang_has_two_surfaces_over_one_place() {
        let t = Tunnel::default();
        let o = Vector3::new(0.0, 1.0, 1.0);
        let floor = t.cast(o, Vector3::new(0.0, 0.0, -1.0), 10.0).expect("floor");
        let roof = t.cast(o, Vector3::new(0.0, 0.0, 1.0), 10.0).expect("roof");
        assert_eq!((floor, roof), (1.0, 1.5));
    }
}
