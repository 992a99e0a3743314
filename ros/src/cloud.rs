//! A sensor_msgs/PointCloud2 as the daemon's scan points: angles and range from each point's
//! x/y/z (the sensor frame), the ring from a `ring` field or an organized cloud's row, the firing
//! time from a `t` (ns, Ouster), `time` (s, Velodyne) or `offset_time` field, and the invalid
//! (NaN) points of an organized cloud kept as no-returns along their row's direction.

use crate::msg::{datatype, PointCloud2, PointField};
use rangegp_proto::scan::{ScanPoint, FLAG_NO_RETURN, FLAG_RING_COLUMN_VALID, MAX_TIME_OFFSET_NS};

/// Why a cloud cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    /// x, y or z is missing or not a float.
    #[error("no float32/float64 field {0:?} (x, y and z are required)")]
    MissingField(&'static str),
    /// `point_step`, `row_step`, the shape and `data` disagree, or a field overruns a point.
    #[error("cloud layout inconsistent: {0}")]
    Layout(String),
    /// More points than a scan may carry.
    #[error("{points} points, more than the {max} a scan carries")]
    TooManyPoints {
        /// Points in the cloud.
        points: usize,
        /// The limit.
        max: usize,
    },
}

/// How one field is read from a point's bytes.
#[derive(Debug, Clone, Copy)]
struct Field {
    offset: usize,
    datatype: u8,
}

impl Field {
    fn find(fields: &[PointField], name: &str) -> Option<Self> {
        fields.iter().find(|f| f.name == name).map(|f| Self {
            offset: f.offset as usize,
            datatype: f.datatype,
        })
    }

    fn size(self) -> usize {
        match self.datatype {
            datatype::INT8 | datatype::UINT8 => 1,
            datatype::INT16 | datatype::UINT16 => 2,
            datatype::INT32 | datatype::UINT32 | datatype::FLOAT32 => 4,
            _ => 8,
        }
    }

    /// The value in `point` (`big`: big-endian data), as f64.
    fn read(self, point: &[u8], big: bool) -> f64 {
        let b = &point[self.offset..self.offset + self.size()];
        macro_rules! num {
            ($t:ty) => {{
                let a = b.try_into().map_or([0; std::mem::size_of::<$t>()], |a| a);
                f64::from(if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                })
            }};
        }
        match self.datatype {
            datatype::INT8 => num!(i8),
            datatype::UINT8 => num!(u8),
            datatype::INT16 => num!(i16),
            datatype::UINT16 => num!(u16),
            datatype::INT32 => num!(i32),
            datatype::UINT32 => num!(u32),
            datatype::FLOAT32 => num!(f32),
            _ => {
                let a = b.try_into().map_or([0; 8], |a| a);
                if big {
                    f64::from_be_bytes(a)
                } else {
                    f64::from_le_bytes(a)
                }
            }
        }
    }
}

/// The unit a firing-time field counts in.
#[derive(Debug, Clone, Copy)]
enum TimeUnit {
    Nanoseconds,
    Seconds,
}

/// A cloud's points as scan points (sensor frame), at most `max_points`.
pub fn scan_points(cloud: &PointCloud2, max_points: usize) -> Result<Vec<ScanPoint>, CloudError> {
    let float = |name: &'static str| {
        Field::find(&cloud.fields, name)
            .filter(|f| matches!(f.datatype, datatype::FLOAT32 | datatype::FLOAT64))
            .ok_or(CloudError::MissingField(name))
    };
    let (fx, fy, fz) = (float("x")?, float("y")?, float("z")?);
    let ring = Field::find(&cloud.fields, "ring");
    let time = Field::find(&cloud.fields, "t")
        .map(|f| (f, TimeUnit::Nanoseconds))
        .or_else(|| Field::find(&cloud.fields, "offset_time").map(|f| (f, TimeUnit::Nanoseconds)))
        .or_else(|| Field::find(&cloud.fields, "time").map(|f| (f, TimeUnit::Seconds)));
    let (rows, cols) = (cloud.height as usize, cloud.width as usize);
    let step = cloud.point_step as usize;
    let n = rows * cols;
    if n > max_points {
        return Err(CloudError::TooManyPoints {
            points: n,
            max: max_points,
        });
    }
    let all = [Some(fx), Some(fy), Some(fz), ring, time.map(|t| t.0)];
    if let Some(f) = all.iter().flatten().find(|f| f.offset + f.size() > step) {
        return Err(CloudError::Layout(format!(
            "a field at byte {} overruns the {step}-byte point",
            f.offset
        )));
    }
    if (cloud.row_step as usize) < cols * step || cloud.data.len() < rows * cloud.row_step as usize {
        return Err(CloudError::Layout(format!(
            "{rows} × {cols} points of {step} bytes, row_step {}, {} bytes of data",
            cloud.row_step,
            cloud.data.len()
        )));
    }
    let big = cloud.is_bigendian;
    let organized = rows > 1;
    let mut points = Vec::with_capacity(n);
    for r in 0..rows {
        let row = &cloud.data[r * cloud.row_step as usize..];
        for c in 0..cols {
            let p = &row[c * step..(c + 1) * step];
            let (x, y, z) = (fx.read(p, big), fy.read(p, big), fz.read(p, big));
            let range = (x * x + y * y + z * z).sqrt();
            let time_offset_ns = time.map_or(0, |(f, unit)| {
                let v = f.read(p, big);
                let ns = match unit {
                    TimeUnit::Nanoseconds => v,
                    TimeUnit::Seconds => v * 1e9,
                };
                ns.clamp(0.0, f64::from(MAX_TIME_OFFSET_NS)) as u32
            });
            let ring = ring.map_or(r, |f| f.read(p, big) as usize);
            let valid = range.is_finite() && range > 0.0;
            let (inclination, azimuth) = if valid {
                ((z / range).clamp(-1.0, 1.0).acos(), y.atan2(x))
            } else {
                (f64::NAN, f64::NAN)
            };
            points.push(ScanPoint {
                range_m: if valid { range as f32 } else { 0.0 },
                inclination_rad: inclination as f32,
                azimuth_rad: azimuth as f32,
                ring: ring.min(usize::from(u16::MAX)) as u16,
                column: c.min(usize::from(u16::MAX)) as u16,
                flags: if organized { FLAG_RING_COLUMN_VALID } else { 0 }
                    | if valid { 0 } else { FLAG_NO_RETURN },
                reserved: 0,
                time_offset_ns,
            });
        }
    }
    if organized {
        aim_no_returns(&mut points, rows, cols);
    }
    // An unorganized cloud's invalid points, and those no row or column could aim, have no
    // direction to keep.
    points.retain(|p| p.inclination_rad.is_finite() && p.azimuth_rad.is_finite());
    Ok(points)
}

/// Median of `v` (NaN when empty).
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Gives each no-return of an organized cloud (`rows` × `cols`, row-major) a direction. The
/// inclination is its row's median, a row without returns (a ring that saw only sky) taking the
/// line through the two nearest rows that have them (rings are evenly spaced on most sensors).
/// The azimuth is interpolated between the nearest returns before and after it in its row, or,
/// in a row with fewer than two returns, the median azimuth of its column.
fn aim_no_returns(points: &mut [ScanPoint], rows: usize, cols: usize) {
    let row_incl: Vec<f64> = (0..rows)
        .map(|r| {
            let row = &points[r * cols..(r + 1) * cols];
            median(
                row.iter()
                    .filter(|p| p.has_return())
                    .map(|p| f64::from(p.inclination_rad))
                    .collect(),
            )
        })
        .collect();
    let known: Vec<usize> = (0..rows).filter(|&r| row_incl[r].is_finite()).collect();
    let col_az: Vec<f64> = (0..cols)
        .map(|c| {
            median(
                (0..rows)
                    .map(|r| &points[r * cols + c])
                    .filter(|p| p.has_return())
                    .map(|p| f64::from(p.azimuth_rad))
                    .collect(),
            )
        })
        .collect();
    for r in 0..rows {
        let incl = if row_incl[r].is_finite() {
            row_incl[r]
        } else if known.len() >= 2 {
            let k = known.partition_point(|&q| q < r).clamp(1, known.len() - 1);
            let (a, b) = (known[k - 1], known[k]);
            let slope = (row_incl[b] - row_incl[a]) / (b as f64 - a as f64);
            (row_incl[a] + slope * (r as f64 - a as f64)).clamp(0.0, std::f64::consts::PI)
        } else {
            continue;
        };
        let row = &mut points[r * cols..(r + 1) * cols];
        aim_row(row, incl as f32, &col_az);
    }
}

/// Aims the no-returns of one row at inclination `incl` (see [`aim_no_returns`]).
fn aim_row(row: &mut [ScanPoint], incl: f32, col_az: &[f64]) {
    let valid: Vec<usize> = (0..row.len()).filter(|&i| row[i].has_return()).collect();
    let tau = std::f64::consts::TAU;
    let mut next = 0;
    for i in 0..row.len() {
        if row[i].has_return() {
            continue;
        }
        while next < valid.len() && valid[next] < i {
            next += 1;
        }
        let az = if valid.len() >= 2 {
            // The returns on either side, and the azimuth per column between them, unwrapped
            // across ±π.
            let (a, b) = match (next.checked_sub(1), valid.get(next)) {
                (Some(p), Some(&q)) => (valid[p], q),
                (None, _) => (valid[0], valid[1]),
                (Some(_), None) => (valid[valid.len() - 2], valid[valid.len() - 1]),
            };
            let (za, zb) = (f64::from(row[a].azimuth_rad), f64::from(row[b].azimuth_rad));
            let mut d = zb - za;
            d -= tau * (d / tau).round();
            let az = za + d / (b as f64 - a as f64) * (i as f64 - a as f64);
            az - tau * ((az + std::f64::consts::PI) / tau).floor()
        } else {
            col_az.get(i).copied().unwrap_or(f64::NAN)
        };
        row[i].inclination_rad = incl;
        row[i].azimuth_rad = az as f32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::Header;

    /// An organized cloud of rows of 4 points: x, y, z (f32), ring (u16) and t (u32 ns).
    fn cloud(points: &[[f32; 3]]) -> PointCloud2 {
        let mut data = Vec::new();
        for (k, p) in points.iter().enumerate() {
            for v in p {
                data.extend(v.to_le_bytes());
            }
            data.extend(((k / 4) as u16 + 10).to_le_bytes());
            data.extend([0u8; 2]);
            data.extend((1000 * k as u32).to_le_bytes());
        }
        PointCloud2 {
            header: Header::default(),
            height: (points.len() / 4) as u32,
            width: 4,
            fields: vec![
                PointField::new("x", 0, datatype::FLOAT32),
                PointField::new("y", 4, datatype::FLOAT32),
                PointField::new("z", 8, datatype::FLOAT32),
                PointField::new("ring", 12, datatype::UINT16),
                PointField::new("t", 16, datatype::UINT32),
            ],
            is_bigendian: false,
            point_step: 20,
            row_step: 80,
            data,
            is_dense: false,
        }
    }

    #[test]
    fn points_become_angles_and_nan_points_no_returns_along_their_row() {
        let n = f32::NAN;
        let c = cloud(&[
            [1.0, 0.0, 0.0],
            [n, n, n],
            [0.0, 1.0, 0.0],
            [0.0, -2.0, 0.0],
            [0.0, 0.0, 3.0],
            [1.0, 1.0, -1.0],
            [n, n, n],
            [n, n, n],
        ]);
        let p = scan_points(&c, 100).expect("readable");
        assert_eq!(p.len(), 8, "both rows have two returns: every no-return is aimed");
        assert!((p[0].range_m - 1.0).abs() < 1e-6);
        assert!((p[0].inclination_rad - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert!(!p[1].has_return() && p[1].flags & FLAG_RING_COLUMN_VALID != 0);
        // Between azimuth 0 (column 0) and π/2 (column 2): π/4 at column 1.
        assert!(
            (p[1].azimuth_rad - std::f32::consts::FRAC_PI_4).abs() < 1e-5,
            "{p:?}"
        );
        assert!((p[3].azimuth_rad + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert!(p[4].inclination_rad.abs() < 1e-6);
        assert_eq!((p[4].ring, p[4].column, p[5].time_offset_ns), (11, 0, 5000));
        // A row that saw only sky continues the rows' inclinations; its columns keep theirs.
        let mut sky = c.clone();
        sky.height = 3;
        for _ in 0..4 {
            for v in [n, n, n] {
                sky.data.extend(v.to_le_bytes());
            }
            sky.data.extend([0u8; 8]);
        }
        let s = scan_points(&sky, 100).expect("readable");
        assert_eq!(s.len(), 12);
        let (r0, r1) = (std::f32::consts::FRAC_PI_2, (-1.0f32 / 3f32.sqrt()).acos());
        assert!(
            (s[8].inclination_rad - (2.0 * r1 - r0)).abs() < 1e-5,
            "{:?}",
            s[8]
        );
        assert!((s[11].azimuth_rad + std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        let mut broken = c.clone();
        broken.fields.retain(|f| f.name != "z");
        assert_eq!(scan_points(&broken, 100), Err(CloudError::MissingField("z")));
        let mut short = c.clone();
        short.data.truncate(100);
        assert!(matches!(scan_points(&short, 100), Err(CloudError::Layout(_))));
        assert!(matches!(
            scan_points(&c, 4),
            Err(CloudError::TooManyPoints { points: 8, max: 4 })
        ));
    }
}
