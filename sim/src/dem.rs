//! Digital elevation models from files: real geography for the evaluations, beside the family.
//!
//! The format read is the ESRI ASCII grid (`.asc`, GDAL's `AAIGrid`): a few `key value` header
//! lines, then the heights row by row from the north. Every GIS writes it, and any raster GDAL
//! reads becomes one with `gdal_translate -of AAIGrid in.tif out.asc`.

use std::path::{Path, PathBuf};

use crate::terrain::Heightmap;

/// Why a DEM could not be read or turned into a terrain.
#[derive(Debug, thiserror::Error)]
pub enum DemError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// A header every ASCII grid carries is missing.
    #[error(
        "the header has no `{0}` line (an ESRI ASCII grid starts ncols, nrows, xllcorner, \
         yllcorner, cellsize)"
    )]
    MissingHeader(&'static str),
    /// A header's value is not a number of the kind it needs.
    #[error("header `{key}` has the value `{value}`, which is not a {want}")]
    BadHeader {
        /// The header's key.
        key: String,
        /// Its value as written.
        value: String,
        /// What it must be.
        want: &'static str,
    },
    /// The grid's cells are not square (`dx` and `dy` headers that differ, or both kinds).
    #[error("the grid's cells are not square (dx / dy headers): resample it to square cells first")]
    NonSquareCells,
    /// The header asks for more cells than [`MAX_CELLS`].
    #[error("the grid is {ncols} × {nrows} cells, more than {MAX_CELLS}: crop or resample it first")]
    TooLarge {
        /// Columns.
        ncols: usize,
        /// Rows.
        nrows: usize,
    },
    /// A header this reader does not know.
    #[error("unknown header `{0}`")]
    UnknownHeader(String),
    /// The body holds a number of heights other than ncols × nrows.
    #[error("the grid holds {found} heights where ncols × nrows is {expected}")]
    WrongCount {
        /// ncols × nrows.
        expected: usize,
        /// Heights found.
        found: usize,
    },
    /// A height is not a finite number.
    #[error("height {index} (row {row}, column {column}) is `{text}`, not a finite number")]
    BadHeight {
        /// Its place in the body, from 0.
        index: usize,
        /// Its row from the north, from 0.
        row: usize,
        /// Its column from the west, from 0.
        column: usize,
        /// As written.
        text: String,
    },
    /// The terrain's square holds cells without data.
    #[error("{count} cells of the central {side} × {side} square hold no data: fill or crop them first")]
    NoData {
        /// Cells without data.
        count: usize,
        /// Side of the square, cells.
        side: usize,
    },
    /// The grid is too small to be a terrain.
    #[error("the grid is {ncols} × {nrows} cells; a terrain needs at least 3 × 3")]
    TooSmall {
        /// Columns.
        ncols: usize,
        /// Rows.
        nrows: usize,
    },
    /// The cell size or relief factor asked for is not a positive finite number.
    #[error("{what} must be a positive finite number, got {value}")]
    BadScale {
        /// Which one.
        what: &'static str,
        /// Its value.
        value: f64,
    },
}

/// The value that marks a cell without data when the header names none (the format's default).
pub const DEFAULT_NODATA: f64 = -9999.0;

/// Most cells a grid may hold (a 7 000 × 7 000 grid), so that a header cannot ask for more memory
/// than a lab machine has.
pub const MAX_CELLS: usize = 50_000_000;

/// A grid of heights read from a file: row 0 is the northernmost, column 0 the westernmost.
#[derive(Debug, Clone, PartialEq)]
pub struct Dem {
    ncols: usize,
    nrows: usize,
    /// Cell size as the file states it (metres, or degrees for a geographic grid).
    cell: f64,
    /// Heights, row-major from the north-west; `None` where the file says no data.
    z: Vec<Option<f64>>,
}

impl Dem {
    /// Reads an ESRI ASCII grid from `path`.
    pub fn read(path: &Path) -> Result<Self, DemError> {
        let text = std::fs::read_to_string(path).map_err(|source| DemError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::parse(&text)
    }

    /// Parses the text of an ESRI ASCII grid.
    pub fn parse(text: &str) -> Result<Self, DemError> {
        let mut tokens = text.split_ascii_whitespace().peekable();
        let (mut ncols, mut nrows, mut cell, mut dx, mut dy) = (None, None, None, None, None);
        // Without a NODATA_value line the format's default holds.
        let mut nodata = DEFAULT_NODATA;
        let (mut xll, mut yll) = (false, false);
        // Header keys are words; the body starts at the first number (`nan` and `inf` included).
        while let Some(key) = tokens.next_if(|t| t.parse::<f64>().is_err()) {
            let key = key.to_ascii_lowercase();
            let value = tokens.next().unwrap_or_default();
            let bad = |want| DemError::BadHeader {
                key: key.clone(),
                value: value.to_owned(),
                want,
            };
            let count = || value.parse::<usize>().map_err(|_| bad("whole number"));
            let number = || {
                value
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| bad("finite number"))
            };
            let size = || {
                number()
                    .ok()
                    .filter(|&c| c > 0.0)
                    .ok_or_else(|| bad("positive number"))
            };
            match key.as_str() {
                "ncols" => ncols = Some(count()?),
                "nrows" => nrows = Some(count()?),
                "xllcorner" | "xllcenter" => xll = number().map(|_| true)?,
                "yllcorner" | "yllcenter" => yll = number().map(|_| true)?,
                "cellsize" => cell = Some(size()?),
                "dx" => dx = Some(size()?),
                "dy" => dy = Some(size()?),
                "nodata_value" => {
                    nodata = value
                        .parse::<f64>()
                        .ok()
                        .filter(|v| !v.is_infinite())
                        .ok_or_else(|| bad("number or nan"))?
                }
                _ => return Err(DemError::UnknownHeader(key)),
            }
        }
        let ncols = ncols.ok_or(DemError::MissingHeader("ncols"))?;
        let nrows = nrows.ok_or(DemError::MissingHeader("nrows"))?;
        let cell = match (cell, dx, dy) {
            (Some(cell), None, None) => cell,
            // GDAL writes dx and dy instead of cellsize; equal ones are square cells.
            (None, Some(dx), Some(dy)) if (dx - dy).abs() <= 1e-9 * dx.max(dy) => dx,
            (None, None, None) => return Err(DemError::MissingHeader("cellsize")),
            _ => return Err(DemError::NonSquareCells),
        };
        if !xll {
            return Err(DemError::MissingHeader("xllcorner"));
        }
        if !yll {
            return Err(DemError::MissingHeader("yllcorner"));
        }
        if ncols < 3 || nrows < 3 {
            return Err(DemError::TooSmall { ncols, nrows });
        }
        let expected = ncols
            .checked_mul(nrows)
            .filter(|&n| n <= MAX_CELLS)
            .ok_or(DemError::TooLarge { ncols, nrows })?;
        let body: Vec<&str> = tokens.collect();
        if body.len() != expected {
            return Err(DemError::WrongCount {
                expected,
                found: body.len(),
            });
        }
        // GDAL may write the header's value to more digits than the body's.
        let is_nodata = |v: f64| match nodata.is_nan() {
            true => v.is_nan(),
            false => (v - nodata).abs() <= 1e-6 * nodata.abs().max(1.0),
        };
        let mut z = Vec::with_capacity(expected);
        for (index, text) in body.into_iter().enumerate() {
            let v = text
                .parse::<f64>()
                .ok()
                .filter(|&v| v.is_finite() || is_nodata(v));
            let v = v.ok_or_else(|| DemError::BadHeight {
                index,
                row: index / ncols,
                column: index % ncols,
                text: text.to_owned(),
            })?;
            z.push((!is_nodata(v)).then_some(v));
        }
        Ok(Self {
            ncols,
            nrows,
            cell,
            z,
        })
    }

    /// Columns and rows.
    pub fn shape(&self) -> (usize, usize) {
        (self.ncols, self.nrows)
    }

    /// The central square of the grid as a terrain centred on (0, 0), north along +y: cells of
    /// `cell_m` metres (`None`: the file's cell size, taken as metres), heights × `relief`
    /// about their mean. A landscape shrunk to a rover's scale keeps its slopes when `relief`
    /// is the ratio of the new cell size to the true one.
    pub fn heightmap(&self, cell_m: Option<f64>, relief: f64) -> Result<Heightmap, DemError> {
        let cell_m = cell_m.unwrap_or(self.cell);
        for (what, value) in [("the cell size", cell_m), ("the relief factor", relief)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(DemError::BadScale { what, value });
            }
        }
        let side = self.ncols.min(self.nrows);
        let (c0, r0) = ((self.ncols - side) / 2, (self.nrows - side) / 2);
        let at = |row: usize, col: usize| self.z[(r0 + row) * self.ncols + c0 + col];
        let heights: Vec<f64> = (0..side)
            .flat_map(|j| (0..side).filter_map(move |i| at(side - 1 - j, i)))
            .collect();
        let count = side * side - heights.len();
        if count > 0 {
            return Err(DemError::NoData { count, side });
        }
        let mean = heights.iter().sum::<f64>() / heights.len() as f64;
        let z = heights.iter().map(|h| (h - mean) * relief).collect();
        Ok(Heightmap::from_grid((side - 1) as f64 * cell_m, cell_m, z))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GRID: &str = "ncols 4\nNROWS 3\nxllcorner 10\nyllcorner -5.5\ncellsize 2\nNODATA_value -9999\n\
                        1 2 3 4\n5 6 7 8\n9 10 11 -9999\n";

    #[test]
    fn a_grid_is_read_north_row_first_and_its_central_square_put_north_up() {
        let dem = Dem::parse(GRID).expect("parses");
        assert_eq!(dem.shape(), (4, 3));
        // The central 3 × 3 square is columns 0–2 (one column left over, dropped from the east
        // by the floor of the half), rows 0–2; mean 6, relief 0.5.
        let map = dem.heightmap(None, 0.5).expect("a terrain");
        assert_eq!((map.resolution(), map.half_extent()), (2.0, 2.0));
        // South-west corner: row 2 (southernmost), column 0 = 9 → (9 − 6) × 0.5.
        assert_eq!(map.height(-2.0, -2.0), Some(1.5));
        // North-east corner of the square: row 0, column 2 = 3 → −1.5.
        assert_eq!(map.height(2.0, 2.0), Some(-1.5));
        let scaled = dem.heightmap(Some(0.25), 1.0).expect("a terrain");
        assert_eq!(scaled.half_extent(), 0.25);
        assert_eq!(scaled.height(-0.25, 0.25), Some(1.0 - 6.0));
    }

    #[test]
    fn no_data_inside_the_square_is_refused_and_outside_it_is_ignored() {
        let holed = GRID.replace(" 11 -9999", " -9999 12");
        assert!(matches!(
            Dem::parse(&holed).expect("parses").heightmap(None, 1.0),
            Err(DemError::NoData { count: 1, side: 3 })
        ));
        assert!(Dem::parse(GRID).expect("parses").heightmap(None, 1.0).is_ok());
    }

    #[test]
    fn the_header_variants_gis_tools_write_are_read() {
        let centred = GRID
            .replace("xllcorner", "XLLCENTER")
            .replace("yllcorner", "yllcenter");
        assert!(Dem::parse(&centred).is_ok());
        let gdal = Dem::parse(&GRID.replace("cellsize 2", "dx 2\ndy 2")).expect("square dx, dy");
        assert_eq!(gdal.heightmap(None, 1.0).map(|m| m.resolution()).ok(), Some(2.0));
        // Without a NODATA_value line, -9999 still marks a cell without data.
        let holed = GRID
            .replace("NODATA_value -9999\n", "")
            .replace(" 11 -9999", " -9999 12");
        assert!(matches!(
            Dem::parse(&holed).expect("parses").heightmap(None, 1.0),
            Err(DemError::NoData { count: 1, .. })
        ));
        // NaN as the marker, and a marker written to more digits than the body's.
        let nan = GRID.replace("-9999", "nan");
        assert!(Dem::parse(&nan).expect("parses").heightmap(None, 1.0).is_ok());
        let float = GRID
            .replace("NODATA_value -9999", "NODATA_value -3.4028234663852886e+38")
            .replace(" 11 -9999", " -3.4028235e+38 12");
        assert!(matches!(
            Dem::parse(&float).expect("parses").heightmap(None, 1.0),
            Err(DemError::NoData { count: 1, .. })
        ));
    }

    #[test]
    fn malformed_grids_are_refused_with_their_reason() {
        /// Whether an error is the one a case expects.
        type Expected = fn(&DemError) -> bool;
        let cases: Vec<(String, Expected)> = vec![
            (GRID.replace("ncols 4\n", ""), |e| {
                matches!(e, DemError::MissingHeader("ncols"))
            }),
            (GRID.replace("cellsize 2", "cellsize -2"), |e| {
                matches!(e, DemError::BadHeader { .. })
            }),
            (GRID.replace("cellsize 2", "dx 2\ndy 3"), |e| {
                matches!(e, DemError::NonSquareCells)
            }),
            (GRID.replace("NODATA", "zunits 1\nNODATA"), |e| {
                matches!(e, DemError::UnknownHeader(_))
            }),
            (GRID.replace(" 8\n", "\n"), |e| {
                matches!(
                    e,
                    DemError::WrongCount {
                        expected: 12,
                        found: 11
                    }
                )
            }),
            (format!("{GRID} 13"), |e| {
                matches!(
                    e,
                    DemError::WrongCount {
                        expected: 12,
                        found: 13
                    }
                )
            }),
            (GRID.replace(" 6 ", " nan "), |e| {
                matches!(
                    e,
                    DemError::BadHeight {
                        index: 5,
                        row: 1,
                        column: 1,
                        ..
                    }
                )
            }),
            (GRID.replace("yllcorner -5.5\n", ""), |e| {
                matches!(e, DemError::MissingHeader("yllcorner"))
            }),
            (GRID.replace("\n1 2 3 4", "\nnan 2 3 4"), |e| {
                matches!(e, DemError::BadHeight { index: 0, .. })
            }),
            (
                "ncols 4294967296\nnrows 4294967296\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3".into(),
                |e| matches!(e, DemError::TooLarge { .. }),
            ),
        ];
        for (text, expected) in cases {
            let err = Dem::parse(&text).expect_err("refused");
            assert!(expected(&err), "{err}");
        }
        let dem = Dem::parse(GRID).expect("parses");
        assert!(matches!(
            dem.heightmap(Some(0.0), 1.0),
            Err(DemError::BadScale { .. })
        ));
        assert!(matches!(
            dem.heightmap(None, f64::NAN),
            Err(DemError::BadScale { .. })
        ));
    }
}
