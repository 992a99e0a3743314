//! The rays of a view: a sensor at a pose, its pixels turned into map-frame rays that
//! [`super::query::ray`] answers one by one.

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use rangegp_proto::msg::{Camera, Ray, ViewRequest};

/// Checks `req` and returns its rows, columns and one map-frame ray per pixel (row-major from
/// the top), or why it cannot be cast.
pub fn view_rays(req: &ViewRequest) -> Result<(u32, u32, Vec<Ray>), String> {
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
    if !finite(&req.position_m) || !finite(&req.orientation_xyzw) {
        return Err("position_m and orientation_xyzw must be finite".into());
    }
    let [x, y, z, w] = req.orientation_xyzw;
    let q = Quaternion::new(w, x, y, z);
    if (q.norm() - 1.0).abs() > 1e-3 {
        return Err(format!(
            "orientation_xyzw must be a unit quaternion (norm {})",
            q.norm()
        ));
    }
    let rotation = UnitQuaternion::from_quaternion(q);
    let origin = req.position_m;
    let (rows, cols, max_range_m, local): (u32, u32, f64, Vec<Vector3<f64>>) = match &req.camera {
        Camera::Lidar {
            ring_elevations_rad,
            columns,
            max_range_m,
        } => {
            let ok = !ring_elevations_rad.is_empty()
                && ring_elevations_rad
                    .iter()
                    .all(|e| e.is_finite() && e.abs() < std::f64::consts::FRAC_PI_2)
                && *columns > 0;
            if !ok {
                return Err("lidar: at least one ring elevation in (−π/2, π/2) and one column".into());
            }
            let dirs = ring_elevations_rad
                .iter()
                .flat_map(|&e| {
                    (0..*columns).map(move |c| {
                        let a = std::f64::consts::TAU * f64::from(c) / f64::from(*columns);
                        Vector3::new(e.cos() * a.cos(), e.cos() * a.sin(), e.sin())
                    })
                })
                .collect();
            (ring_elevations_rad.len() as u32, *columns, *max_range_m, dirs)
        }
        Camera::Pinhole {
            width,
            height,
            hfov_rad,
            max_range_m,
        } => {
            if *width == 0 || *height == 0 || !(*hfov_rad > 0.0 && *hfov_rad < std::f64::consts::PI) {
                return Err("pinhole: width and height of at least 1 pixel, hfov_rad in (0, π)".into());
            }
            let step = 2.0 * (hfov_rad / 2.0).tan() / f64::from(*width);
            let (cx, cy) = (f64::from(*width) / 2.0, f64::from(*height) / 2.0);
            let dirs = (0..*height)
                .flat_map(|r| {
                    (0..*width).map(move |c| {
                        let (u, v) = (f64::from(c) + 0.5, f64::from(r) + 0.5);
                        Vector3::new(1.0, (cx - u) * step, (cy - v) * step)
                    })
                })
                .collect();
            (*height, *width, *max_range_m, dirs)
        }
    };
    if !(max_range_m.is_finite() && max_range_m > 0.0) {
        return Err("max_range_m must be positive and finite".into());
    }
    let rays = local
        .into_iter()
        .map(|d| Ray {
            origin_m: origin,
            direction: (rotation * d).into(),
            max_range_m,
        })
        .collect();
    Ok((rows, cols, rays))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rangegp_proto::PROTOCOL_VERSION;

    fn request(camera: Camera, yaw: f64) -> ViewRequest {
        let q = UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        ViewRequest {
            version: PROTOCOL_VERSION,
            position_m: [1.0, 2.0, 0.5],
            orientation_xyzw: [q.i, q.j, q.k, q.w],
            camera,
        }
    }

    #[test]
    fn pixels_point_where_the_sensor_looks() {
        let lidar = Camera::Lidar {
            ring_elevations_rad: vec![0.1, -0.2],
            columns: 4,
            max_range_m: 30.0,
        };
        let (rows, cols, rays) = view_rays(&request(lidar, std::f64::consts::FRAC_PI_2)).expect("valid");
        assert_eq!((rows, cols, rays.len()), (2, 4, 8));
        // Top ring, column 0: straight ahead, which the pose turned to +y; slightly up.
        let d = Vector3::from(rays[0].direction);
        assert!(d.x.abs() < 1e-12 && d.y > 0.99 && (d.z - 0.1f64.sin()).abs() < 1e-12);
        // Second ring, column 1: a quarter turn left of ahead (−x in the map), down.
        let d = Vector3::from(rays[5].direction);
        assert!(d.x < -0.97 && d.y.abs() < 1e-12 && d.z < 0.0);
        let pinhole = Camera::Pinhole {
            width: 3,
            height: 2,
            hfov_rad: 1.0,
            max_range_m: 10.0,
        };
        let (rows, cols, rays) = view_rays(&request(pinhole, 0.0)).expect("valid");
        assert_eq!((rows, cols), (2, 3));
        // Top-left pixel looks left and up, bottom-right right and down.
        let (tl, br) = (Vector3::from(rays[0].direction), Vector3::from(rays[5].direction));
        assert!(tl.y > 0.0 && tl.z > 0.0 && br.y < 0.0 && br.z < 0.0);
        assert!(rays
            .iter()
            .all(|r| r.origin_m == [1.0, 2.0, 0.5] && r.max_range_m == 10.0));
    }

    #[test]
    fn bad_views_are_refused_with_a_reason() {
        let lidar = |rings: Vec<f64>, columns| Camera::Lidar {
            ring_elevations_rad: rings,
            columns,
            max_range_m: 30.0,
        };
        assert!(view_rays(&request(lidar(vec![], 4), 0.0)).is_err());
        assert!(view_rays(&request(lidar(vec![0.1], 0), 0.0)).is_err());
        assert!(view_rays(&request(lidar(vec![2.0], 4), 0.0)).is_err());
        let mut r = request(lidar(vec![0.1], 4), 0.0);
        r.orientation_xyzw = [0.0, 0.0, 0.0, 2.0];
        assert!(view_rays(&r).unwrap_err().contains("unit quaternion"));
        r.orientation_xyzw = [0.0, 0.0, 0.0, 1.0];
        r.position_m[0] = f64::NAN;
        assert!(view_rays(&r).is_err());
    }
}
