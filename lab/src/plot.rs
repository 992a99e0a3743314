//! The one renderer of every picture (demo, `rangegp grid --png`, evaluation): a colour-mapped
//! raster in map coordinates with axes in their units, a title, the robot's path, and a colour
//! bar with values and units. `plotters` draws (fonts from the `dejavu` crate, so nothing is
//! needed from the system), `colorous` supplies perceptual colour maps, `image` writes the PNG.

use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use rangegp_proto::msg::GridReply;
use rangegp_service::metrics::latency::percentile;
use std::path::Path;
use std::sync::Once;
use thiserror::Error;

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

/// The value range the colours span.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Limits {
    /// The 2nd to the 98th percentile of the values: one outlier cannot wash the rest out;
    /// values beyond are drawn in the end colours and the colour bar says so.
    Robust,
    /// Exactly this range (e.g. shared by a prediction and its ground truth).
    Fixed(f64, f64),
}

/// A picture could not be made.
#[derive(Debug, Error)]
pub enum PlotError {
    /// plotters could not draw (a font, a layout).
    #[error("cannot draw the picture")]
    Draw(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// The PNG could not be encoded or written.
    #[error("cannot write the picture")]
    Write(#[from] image::ImageError),
}

/// What a heat map shows: title, units, colours, limits and an optional path overlay.
#[derive(Debug, Clone)]
pub struct Heatmap<'a> {
    title: String,
    x_label: &'a str,
    y_label: &'a str,
    value_label: &'a str,
    gradient: colorous::Gradient,
    limits: Limits,
    path: &'a [[f64; 2]],
}

/// Grey of cells without a value.
const NO_VALUE: RGBColor = RGBColor(170, 170, 170);
/// Width of the colour-bar panel, pixels.
const BAR_PANEL: u32 = 150;
/// Largest side of the raster, pixels.
const MAX_SIDE: u32 = 820;

impl<'a> Heatmap<'a> {
    /// A map-view heat map titled `title` of a quantity labelled `value_label` (with its unit,
    /// e.g. `"σ (m)"`); axes `x (m)` and `y (m)`, viridis, robust limits, no path.
    pub fn new(title: impl Into<String>, value_label: &'a str) -> Self {
        Self {
            title: title.into(),
            x_label: "x (m)",
            y_label: "y (m)",
            value_label,
            gradient: colorous::VIRIDIS,
            limits: Limits::Robust,
            path: &[],
        }
    }

    /// Axis labels with units (e.g. azimuth and elevation in degrees).
    pub fn axes(mut self, x_label: &'a str, y_label: &'a str) -> Self {
        (self.x_label, self.y_label) = (x_label, y_label);
        self
    }

    /// The colour map.
    pub fn gradient(mut self, gradient: colorous::Gradient) -> Self {
        self.gradient = gradient;
        self
    }

    /// The value range the colours span.
    pub fn limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// A path (map x, y) drawn over the raster in red.
    pub fn path(mut self, path: &'a [[f64; 2]]) -> Self {
        self.path = path;
        self
    }

    /// Draws `raster` to the PNG `file`.
    pub fn save(&self, file: &Path, raster: &Raster) -> Result<(), PlotError> {
        let (lo, hi, clipped) = self.value_range(raster);
        let cell = (MAX_SIDE / raster.nx.max(raster.ny).max(1) as u32).clamp(1, 16);
        let (plot_w, plot_h) = (raster.nx as u32 * cell, raster.ny as u32 * cell);
        let (left, bottom, top, right) = (80, 55, 45, 20);
        let (w, h) = (left + plot_w + right + BAR_PANEL, top + plot_h.max(200) + bottom);
        render_png(file, (w, h), |buf| {
            self.draw(buf, (w, h), raster, (lo, hi, clipped), (left, bottom, top))
        })
    }

    /// (lo, hi, whether values lie beyond) of the colour scale.
    fn value_range(&self, raster: &Raster) -> (f64, f64, bool) {
        let mut values: Vec<f64> = raster.values.iter().flatten().copied().collect();
        let (lo, hi) = match self.limits {
            Limits::Fixed(lo, hi) => (lo, hi),
            Limits::Robust => (
                percentile(&mut values, 0.02).unwrap_or(0.0),
                percentile(&mut values, 0.98).unwrap_or(1.0),
            ),
        };
        let hi = if hi > lo {
            hi
        } else {
            lo + 1e-9_f64.max(lo.abs() * 1e-6)
        };
        let clipped = values.iter().any(|&v| v < lo || v > hi);
        (lo, hi, clipped)
    }

    fn draw(
        &self,
        buf: &mut [u8],
        size: (u32, u32),
        raster: &Raster,
        (lo, hi, clipped): (f64, f64, bool),
        (left, bottom, top): (u32, u32, u32),
    ) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
        let root = BitMapBackend::with_buffer(buf, size).into_drawing_area();
        let (main, bar) = root.split_horizontally(size.0 - BAR_PANEL);
        let half = raster.resolution / 2.0;
        let xs = (raster.x0 - half)..(raster.x0 + (raster.nx as f64 - 0.5) * raster.resolution);
        let ys = (raster.y0 - half)..(raster.y0 + (raster.ny as f64 - 0.5) * raster.resolution);
        let mut chart = ChartBuilder::on(&main)
            .caption(&self.title, ("sans-serif", 20))
            .margin_top(top.saturating_sub(35))
            .x_label_area_size(bottom)
            .y_label_area_size(left)
            .build_cartesian_2d(xs, ys)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc(self.x_label)
            .y_desc(self.y_label)
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 15))
            .draw()?;
        let span = hi - lo;
        let colour = |v: f64| {
            let c = self.gradient.eval_continuous(((v - lo) / span).clamp(0.0, 1.0));
            RGBColor(c.r, c.g, c.b)
        };
        chart.draw_series(raster.values.iter().enumerate().map(|(k, v)| {
            let (col, row) = ((k % raster.nx) as f64, (k / raster.nx) as f64);
            let x = raster.x0 + col * raster.resolution;
            let y = raster.y0 + row * raster.resolution;
            let fill = v.map_or(NO_VALUE, colour);
            Rectangle::new([(x - half, y - half), (x + half, y + half)], fill.filled())
        }))?;
        if !self.path.is_empty() {
            chart.draw_series(LineSeries::new(
                self.path.iter().map(|p| (p[0], p[1])),
                RED.stroke_width(2),
            ))?;
        }
        let label = if clipped {
            format!("{} (ends clipped)", self.value_label)
        } else {
            self.value_label.to_owned()
        };
        let mut legend = ChartBuilder::on(&bar)
            .margin_top(top)
            .margin_bottom(bottom)
            .margin_right(70)
            .y_label_area_size(0)
            .right_y_label_area_size(60)
            .build_cartesian_2d(0.0..1.0, lo..hi)?;
        legend
            .configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(label)
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 14))
            .draw()?;
        let steps = 200;
        legend.draw_series((0..steps).map(|i| {
            let a = lo + span * i as f64 / steps as f64;
            let b = lo + span * (i + 1) as f64 / steps as f64;
            Rectangle::new([(0.0, a), (1.0, b)], colour((a + b) / 2.0).filled())
        }))?;
        bar.draw(&Text::new(
            "grey: no answer",
            (5, size.1 as i32 - 22),
            ("sans-serif", 12),
        ))?;
        root.present()?;
        Ok(())
    }
}

/// A reliability diagram: the observed frequency of an event against the probability predicted
/// for it, one point per bin (its size written beside it), with the diagonal of perfect
/// calibration; `title` names what was predicted.
pub fn reliability_chart(file: &Path, title: &str, bins: &[(f64, f64, usize)]) -> Result<(), PlotError> {
    let size = (640, 560);
    render_png(file, size, |buf| draw_reliability(buf, size, title, bins))
}

/// One curve of a [`coverage_chart`]: its legend, and (nominal probability, observed share)
/// points in ascending nominal order.
pub struct CoverageCurve {
    /// Legend text (what was pooled, with its answer count).
    pub label: String,
    /// (central interval's probability, share of errors inside it).
    pub points: Vec<[f64; 2]>,
}

/// A reliability diagram of σ: for central intervals mean ± Φ⁻¹((1 + p) / 2) σ, the share of
/// true values inside against p, one coloured curve per `curves` entry, the diagonal of a
/// calibrated σ, and `targets` as shaded boxes ((p, [lo, hi]): where the share at p must lie).
pub fn coverage_chart(
    file: &Path,
    title: &str,
    curves: &[CoverageCurve],
    targets: &[(f64, (f64, f64))],
) -> Result<(), PlotError> {
    let size = (720, 600);
    render_png(file, size, |buf| draw_coverage(buf, size, title, curves, targets))
}

/// A chart over the unit square on `root`: captioned `title`, both axes described, a light
/// mesh (what the reliability diagrams draw on).
fn unit_square<'a, 'b>(
    root: &'a DrawingArea<BitMapBackend<'b>, plotters::coord::Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
) -> Result<UnitSquare<'a, 'b>, Box<dyn std::error::Error + Send + Sync>> {
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 17))
        .margin(20)
        .x_label_area_size(50)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..1.0, 0.0..1.0)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .light_line_style(RGBColor(238, 238, 238))
        .label_style(("sans-serif", 13))
        .axis_desc_style(("sans-serif", 15))
        .draw()?;
    Ok(chart)
}

/// What [`unit_square`] makes.
type UnitSquare<'a, 'b> = ChartContext<
    'a,
    BitMapBackend<'b>,
    Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>,
>;

fn draw_coverage(
    buf: &mut [u8],
    size: (u32, u32),
    title: &str,
    curves: &[CoverageCurve],
    targets: &[(f64, (f64, f64))],
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let root = BitMapBackend::with_buffer(buf, size).into_drawing_area();
    let mut chart = unit_square(
        &root,
        title,
        "central interval's probability (mean ± z·σ)",
        "share of true heights inside",
    )?;
    let shade = RGBColor(120, 200, 120).mix(0.35);
    chart.draw_series(
        targets
            .iter()
            .map(|&(p, (lo, hi))| Rectangle::new([(p - 0.012, lo), (p + 0.012, hi)], shade.filled())),
    )?;
    chart
        .draw_series(LineSeries::new([(0.0, 0.0), (1.0, 1.0)], BLACK.stroke_width(1)))?
        .label("calibrated (diagonal); green: the bar")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 18, y)], BLACK));
    for (k, curve) in curves.iter().enumerate() {
        let c = colorous::CATEGORY10[k % colorous::CATEGORY10.len()];
        let colour = RGBColor(c.r, c.g, c.b);
        chart
            .draw_series(LineSeries::new(
                curve.points.iter().map(|&[p, f]| (p, f)),
                colour.stroke_width(2),
            ))?
            .label(curve.label.as_str())
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], colour.stroke_width(2)));
        chart.draw_series(
            curve
                .points
                .iter()
                .map(|&[p, f]| Circle::new((p, f), 3, colour.filled())),
        )?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 13))
        .draw()?;
    root.present()?;
    Ok(())
}

/// Draws a picture of `size` pixels with `draw` (onto a white RGB buffer, the fonts registered)
/// and writes it to the PNG `file`.
fn render_png(
    file: &Path,
    (w, h): (u32, u32),
    draw: impl FnOnce(&mut [u8]) -> Result<(), Box<dyn std::error::Error + Send + Sync>>,
) -> Result<(), PlotError> {
    static FONT: Once = Once::new();
    FONT.call_once(|| {
        // The dejavu crate's bytes are a valid TrueType font; a failure would only mean text
        // falls back to nothing, which the draw reports.
        let _ = register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    });
    let mut buf = vec![255u8; (w * h * 3) as usize];
    draw(&mut buf).map_err(PlotError::Draw)?;
    let img = image::RgbImage::from_raw(w, h, buf)
        .ok_or_else(|| PlotError::Draw("picture buffer of the wrong size".into()))?;
    img.save(file)?;
    Ok(())
}

fn draw_reliability(
    buf: &mut [u8],
    size: (u32, u32),
    title: &str,
    bins: &[(f64, f64, usize)],
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let root = BitMapBackend::with_buffer(buf, size).into_drawing_area();
    let mut chart = unit_square(&root, title, "predicted probability", "observed frequency")?;
    chart.draw_series(LineSeries::new([(0.0, 0.0), (1.0, 1.0)], BLACK.stroke_width(1)))?;
    chart.draw_series(LineSeries::new(
        bins.iter().map(|&(p, f, _)| (p, f)),
        BLUE.stroke_width(2),
    ))?;
    chart.draw_series(
        bins.iter()
            .map(|&(p, f, _)| Circle::new((p, f), 4, BLUE.filled())),
    )?;
    chart.draw_series(bins.iter().map(|&(p, f, n)| {
        Text::new(
            format!("{n}"),
            (p + 0.01, (f - 0.04).max(0.0)),
            ("sans-serif", 11),
        )
    }))?;
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raster() -> Raster {
        Raster {
            nx: 3,
            ny: 2,
            x0: 0.0,
            y0: 0.0,
            resolution: 1.0,
            values: vec![Some(0.0), Some(1.0), None, Some(2.0), None, Some(0.5)],
        }
    }

    #[test]
    fn a_picture_has_the_raster_its_colour_bar_and_grey_for_no_value() {
        let r = raster();
        assert_eq!(r.range(), Some((0.0, 2.0)));
        let dir = std::env::temp_dir().join(format!("rangegp-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let file = dir.join("t.png");
        Heatmap::new("test", "z (m)")
            .limits(Limits::Fixed(0.0, 2.0))
            .path(&[[0.0, 0.0], [2.0, 1.0]])
            .save(&file, &r)
            .expect("png");
        let img = image::open(&file).expect("read back").to_rgb8();
        let pixels: Vec<_> = img.pixels().collect();
        let grey = pixels.iter().filter(|p| p.0 == [170, 170, 170]).count();
        let red = pixels.iter().filter(|p| p.0 == [255, 0, 0]).count();
        let viridis_top = colorous::VIRIDIS.eval_continuous(1.0);
        let top = pixels
            .iter()
            .filter(|p| p.0 == [viridis_top.r, viridis_top.g, viridis_top.b])
            .count();
        // Two cells without value, a path, the highest value in one cell and in the bar.
        assert!(grey > 1000, "grey pixels: {grey}");
        assert!(red > 50, "path pixels: {red}");
        assert!(top > 1000, "top-colour pixels: {top}");
        // Text was drawn (black pixels of labels and title beyond the axes' lines).
        let dark = pixels.iter().filter(|p| p.0.iter().all(|&c| c < 60)).count();
        assert!(dark > 500, "dark (text and axis) pixels: {dark}");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn robust_limits_ignore_one_outlier() {
        let mut r = raster();
        r.values = (0..100).map(|i| Some(i as f64 * 0.001)).collect();
        r.values[7] = Some(1000.0);
        (r.nx, r.ny) = (10, 10);
        let (lo, hi, clipped) = Heatmap::new("t", "σ (m)").value_range(&r);
        assert!(lo >= 0.0 && hi < 0.1, "({lo}, {hi})");
        assert!(clipped);
    }
}
