//! Pictures of map layers: a colour-mapped raster (north up) with an optional path overlay and a
//! colour bar along the bottom. `image` writes the PNG; `colorous` supplies perceptual maps.

use image::{Rgb, RgbImage};
use rangegp_proto::msg::GridReply;
use std::path::Path;

/// A regular grid of optional values; row 0 is the southern edge (smallest y).
#[derive(Debug, Clone, PartialEq)]
pub struct Raster {
    /// Columns.
    pub nx: usize,
    /// Rows.
    pub ny: usize,
    /// x of column 0, metres.
    pub x0: f64,
    /// y of row 0, metres.
    pub y0: f64,
    /// Cell size, metres.
    pub resolution: f64,
    /// Row-major values (`None`: unobserved, drawn grey).
    pub values: Vec<Option<f64>>,
}

impl Raster {
    /// Samples `f` at the centres of a grid over [x0, x1] × [y0, y1] with cell `resolution`
    /// (in parallel: each value may be a map query).
    pub fn from_fn(
        (x0, y0): (f64, f64),
        (x1, y1): (f64, f64),
        resolution: f64,
        f: impl Fn(f64, f64) -> Option<f64> + Sync,
    ) -> Self {
        use rayon::prelude::*;
        let nx = (((x1 - x0) / resolution).ceil() as usize).max(1);
        let ny = (((y1 - y0) / resolution).ceil() as usize).max(1);
        let values = (0..nx * ny)
            .into_par_iter()
            .map(|k| {
                let (col, row) = (k % nx, k / nx);
                f(
                    x0 + (col as f64 + 0.5) * resolution,
                    y0 + (row as f64 + 0.5) * resolution,
                )
            })
            .collect();
        Self {
            nx,
            ny,
            x0: x0 + 0.5 * resolution,
            y0: y0 + 0.5 * resolution,
            resolution,
            values,
        }
    }

    /// One layer of a grid reply (`elevation_m` or `variance_m2`), each value mapped by `f`
    /// (e.g. a variance to σ).
    pub fn from_grid(reply: &GridReply, layer: &[Option<f32>], f: impl Fn(f64) -> f64) -> Self {
        Self {
            nx: reply.cols as usize,
            ny: reply.rows as usize,
            x0: reply.origin_m[0],
            y0: reply.origin_m[1],
            resolution: reply.resolution_m,
            values: layer.iter().map(|v| v.map(|v| f(v as f64))).collect(),
        }
    }

    /// (min, max) of the present values, or `None` when every cell is empty.
    pub fn range(&self) -> Option<(f64, f64)> {
        self.values.iter().flatten().fold(None, |acc, &v| match acc {
            None => Some((v, v)),
            Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
        })
    }
}

/// Writes `raster` as a PNG with `scale` pixels per cell, the colour map stretched over
/// `range` (default: the data's range), and `path` (map x, y) drawn in red.
pub fn save_heatmap(
    file: &Path,
    raster: &Raster,
    range: Option<(f64, f64)>,
    gradient: colorous::Gradient,
    path: &[[f64; 2]],
    scale: u32,
) -> Result<(), image::ImageError> {
    let (lo, hi) = range.or_else(|| raster.range()).unwrap_or((0.0, 1.0));
    let span = (hi - lo).max(1e-12);
    let (w, h) = (raster.nx as u32 * scale, raster.ny as u32 * scale);
    let bar = 16;
    let mut img = RgbImage::from_pixel(w, h + bar, Rgb([255, 255, 255]));
    for row in 0..raster.ny {
        for col in 0..raster.nx {
            let colour = match raster.values[row * raster.nx + col] {
                Some(v) => rgb(gradient.eval_continuous(((v - lo) / span).clamp(0.0, 1.0))),
                None => Rgb([160, 160, 160]),
            };
            let top = (raster.ny - 1 - row) as u32 * scale;
            for dy in 0..scale {
                for dx in 0..scale {
                    img.put_pixel(col as u32 * scale + dx, top + dy, colour);
                }
            }
        }
    }
    for p in path {
        let px = ((p[0] - raster.x0) / raster.resolution + 0.5) * scale as f64;
        let py = h as f64 - ((p[1] - raster.y0) / raster.resolution + 0.5) * scale as f64;
        for dy in -1i64..=1 {
            for dx in -1i64..=1 {
                let (x, y) = (px as i64 + dx, py as i64 + dy);
                if x >= 0 && y >= 0 && (x as u32) < w && (y as u32) < h {
                    img.put_pixel(x as u32, y as u32, Rgb([220, 20, 20]));
                }
            }
        }
    }
    for x in 0..w {
        let c = rgb(gradient.eval_continuous(x as f64 / (w.max(2) - 1) as f64));
        for y in h + 4..h + bar {
            img.put_pixel(x, y, c);
        }
    }
    img.save(file)
}

fn rgb(c: colorous::Color) -> Rgb<u8> {
    Rgb([c.r, c.g, c.b])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_a_png_of_the_expected_size() {
        let raster = Raster {
            nx: 3,
            ny: 2,
            x0: 0.0,
            y0: 0.0,
            resolution: 1.0,
            values: vec![Some(0.0), Some(1.0), None, Some(2.0), None, Some(0.5)],
        };
        assert_eq!(raster.range(), Some((0.0, 2.0)));
        let dir = std::env::temp_dir().join(format!("rangegp-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let file = dir.join("t.png");
        save_heatmap(&file, &raster, None, colorous::VIRIDIS, &[[1.0, 1.0]], 4).expect("png");
        let img = image::open(&file).expect("read back").to_rgb8();
        assert_eq!(img.dimensions(), (12, 8 + 16));
        // Unobserved cell (col 2, row 0) is grey; row 0 is drawn at the bottom.
        assert_eq!(img.get_pixel(9, 5), &Rgb([160, 160, 160]));
        std::fs::remove_dir_all(&dir).ok();
    }
}
