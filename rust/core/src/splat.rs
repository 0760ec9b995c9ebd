//! Bilinear splatting of complex point weights onto a grid: the first step of the B-mode
//! simulator's echo formation (`usdeform.sim.imaging.echo`), before the Gaussian blur.
//!
//! A point at grid position (`fine_col`, `fine_row`) (cells, fractional) with the complex weight
//! `w` adds `w (1 - fr) (1 - fc)`, `w (1 - fr) fc`, `w fr (1 - fc)` and `w fr fc` to the cells
//! (row0, col0), (row0, col0 + 1), (row0 + 1, col0) and (row0 + 1, col0 + 1), where col0, row0 are
//! the floors and fc, fr the fractional parts; points whose four cells are not all on the grid are
//! left out. The sums are bit-identical to the NumPy twin's (`usdeform.reference.splat_bilinear`),
//! which gathers the four corners of all points and sums them with `np.bincount`: each cell sums
//! its contributions in float64 in that order (corner by corner, points in order within a corner),
//! every product is formed as there (`(w * (1 - fr)) * (1 - fc)`, real and imaginary parts apart;
//! Rust never fuses a multiply and an add), and the sums are rounded to float32 at the end.
//!
//! The points land in random cells of a grid larger than a core's cache, so the grid is filled
//! band of rows by band of rows, each band's working sums staying in cache: the points' upper
//! corner pairs (row0) and lower corner pairs (row0 + 1) are sorted by band, stably, and a band
//! takes its upper pairs' left then right corners and its lower pairs' left then right corners. A
//! cell lies in one band, so it still sums its contributions in bincount's order. One thread: the
//! order of the sums is the result (and the kernel is bound by memory).

use crate::error::{check_finite, reserve, KernelError, Result};

/// Most cells a grid may have: 2^31.
pub const MAX_CELLS: usize = 1 << 31;

/// Bytes of working sums (real and imaginary, float64) of one band: a few rows of the grid,
/// small enough to stay in a core's L2 cache.
const BAND_BYTES: usize = 1 << 18;

/// The real and imaginary grids (rows, cols), row-major, float32.
#[derive(Debug, Clone, PartialEq)]
pub struct SplatGrids {
    pub real: Vec<f32>,
    pub imag: Vec<f32>,
}

/// Splats the points (`fine_col`, `fine_row`) with weights `weight_real + i weight_imag` (all of
/// one length, finite) bilinearly onto a grid of `shape` (rows, cols) cells: see the module.
pub fn splat_bilinear(
    fine_col: &[f64],
    fine_row: &[f64],
    weight_real: &[f64],
    weight_imag: &[f64],
    shape: [usize; 2],
) -> Result<SplatGrids> {
    let cells = check_inputs(fine_col, fine_row, weight_real, weight_imag, shape)?;
    let mut real = reserve::<f32>("grid_shape", cells)?;
    let mut imag = reserve::<f32>("grid_shape", cells)?;
    let points = [fine_col, fine_row, weight_real, weight_imag];
    splat_sums(points, shape, |sums| {
        // `as` rounds to nearest (ties to even), as NumPy's astype(float32).
        real.extend(sums.iter().map(|cell| cell[0] as f32));
        imag.extend(sums.iter().map(|cell| cell[1] as f32));
    })?;
    Ok(SplatGrids { real, imag })
}

/// The float64 sums (real, imaginary) of the checked `points` (fine_col, fine_row, weight_real,
/// weight_imag), given to `take_band` band by band, in row-major order.
fn splat_sums(
    [fine_col, fine_row, weight_real, weight_imag]: [&[f64]; 4],
    shape: [usize; 2],
    mut take_band: impl FnMut(&[[f64; 2]]),
) -> Result<()> {
    let [rows, cols] = shape;
    let bands = Bands::new(shape);
    let locate = |point: usize| locate(fine_col[point], fine_row[point], shape);

    // Sorting by band, stably: count each band's corner pairs, then place them.
    let mut upper_start = zeroed::<usize>("grid_shape", bands.count + 1)?;
    let mut lower_start = zeroed::<usize>("grid_shape", bands.count + 1)?;
    for point in 0..fine_col.len() {
        if let Some(cell) = locate(point) {
            upper_start[bands.of_row(cell.row0) + 1] += 1;
            lower_start[bands.of_row(cell.row0 + 1) + 1] += 1;
        }
    }
    for band in 0..bands.count {
        upper_start[band + 1] += upper_start[band];
        lower_start[band + 1] += lower_start[band];
    }
    let inside = upper_start[bands.count];
    let mut upper = zeroed::<CornerPair>("fine_col", inside)?;
    let mut lower = zeroed::<CornerPair>("fine_col", inside)?;
    let (mut upper_next, mut lower_next) = (upper_start.clone(), lower_start.clone());
    for point in 0..fine_col.len() {
        if let Some(cell) = locate(point) {
            let index = cell.row0 * cols + cell.col0;
            let (real, imag) = (weight_real[point], weight_imag[point]);
            let slot = &mut upper_next[bands.of_row(cell.row0)];
            upper[*slot] = CornerPair {
                index,
                frac_col: cell.frac_col,
                real: real * (1.0 - cell.frac_row),
                imag: imag * (1.0 - cell.frac_row),
            };
            *slot += 1;
            let slot = &mut lower_next[bands.of_row(cell.row0 + 1)];
            lower[*slot] = CornerPair {
                index: index + cols,
                frac_col: cell.frac_col,
                real: real * cell.frac_row,
                imag: imag * cell.frac_row,
            };
            *slot += 1;
        }
    }

    let mut sums = zeroed::<[f64; 2]>("grid_shape", bands.rows * cols)?;
    for band in 0..bands.count {
        let first = band * bands.rows * cols;
        let end = ((band + 1) * bands.rows).min(rows) * cols;
        let sums = &mut sums[..end - first];
        sums.fill([0.0; 2]);
        let upper = &upper[upper_start[band]..upper_start[band + 1]];
        let lower = &lower[lower_start[band]..lower_start[band + 1]];
        // bincount's order: corner 00 of every point, then 01, 10 and 11.
        for pairs in [upper, lower] {
            for pair in pairs {
                let cell = &mut sums[pair.index - first];
                cell[0] += pair.real * (1.0 - pair.frac_col);
                cell[1] += pair.imag * (1.0 - pair.frac_col);
            }
            for pair in pairs {
                let cell = &mut sums[pair.index + 1 - first];
                cell[0] += pair.real * pair.frac_col;
                cell[1] += pair.imag * pair.frac_col;
            }
        }
        take_band(sums);
    }
    Ok(())
}

/// The bands of rows the grid is filled by: `count` bands of `rows` rows (the last one may be
/// shorter).
struct Bands {
    rows: usize,
    count: usize,
}

impl Bands {
    fn new([rows, cols]: [usize; 2]) -> Self {
        let row_bytes = cols.saturating_mul(std::mem::size_of::<[f64; 2]>());
        let band_rows = (BAND_BYTES / row_bytes).clamp(1, rows);
        Bands {
            rows: band_rows,
            count: rows.div_ceil(band_rows),
        }
    }

    fn of_row(&self, row: usize) -> usize {
        row / self.rows
    }
}

/// Where a point lands: its upper left cell (row0, col0) and its fractional parts.
struct Cell {
    row0: usize,
    col0: usize,
    frac_row: f64,
    frac_col: f64,
}

/// Two horizontally adjacent corners of a point: the weight along the rows (`real`, `imag`: the
/// point's weight times 1 - fr for the upper pair, fr for the lower) at cell `index`, to be
/// multiplied by 1 - fc there and by fc at `index + 1`.
#[derive(Debug, Clone, Copy, Default)]
struct CornerPair {
    index: usize,
    frac_col: f64,
    real: f64,
    imag: f64,
}

/// The cell of a point at (`col`, `row`) (finite), or None where its four cells are not all on the
/// grid: NumPy's test of the floors cast to int64, and its fractional parts, the position minus
/// the int64 floor converted back, as there.
#[inline(always)]
fn locate(col: f64, row: f64, [rows, cols]: [usize; 2]) -> Option<Cell> {
    let (col0, row0) = (floor_index(col), floor_index(row));
    let on_grid = |floor: i64, cells: usize| floor >= 0 && (floor as u64) + 1 < cells as u64;
    if !(on_grid(col0, cols) && on_grid(row0, rows)) {
        return None;
    }
    Some(Cell {
        row0: row0 as usize,
        col0: col0 as usize,
        frac_row: row - row0 as f64,
        frac_col: col - col0 as f64,
    })
}

/// floor(x) as an integer for finite x: exact within the i64 range, saturating beyond it (where
/// NumPy's cast is undefined; such points are off any grid in both). Truncation and a correction
/// rather than `f64::floor`, which is a library call on baseline x86-64.
#[inline(always)]
fn floor_index(x: f64) -> i64 {
    let truncated = x as i64;
    if (truncated as f64) > x {
        truncated.saturating_sub(1)
    } else {
        truncated
    }
}

fn check_inputs(
    fine_col: &[f64],
    fine_row: &[f64],
    weight_real: &[f64],
    weight_imag: &[f64],
    shape: [usize; 2],
) -> Result<usize> {
    let cells = shape[0]
        .checked_mul(shape[1])
        .filter(|&cells| cells <= MAX_CELLS);
    let cells = match cells {
        Some(cells) if cells > 0 => cells,
        _ => {
            return Err(KernelError::Value {
                argument: "grid_shape",
                message: format!(
                "expected (rows, cols), two positive integers of at most {MAX_CELLS} cells in all, got ({}, {})",
                shape[0], shape[1]
            ),
            })
        }
    };
    let n = fine_col.len();
    for (argument, values) in [
        ("fine_row", fine_row),
        ("weight_real", weight_real),
        ("weight_imag", weight_imag),
    ] {
        if values.len() != n {
            return Err(KernelError::Shape {
                argument,
                expected: format!("{n} values, as fine_col"),
                got: format!("{} values", values.len()),
            });
        }
    }
    for (argument, values) in [
        ("fine_col", fine_col),
        ("fine_row", fine_row),
        ("weight_real", weight_real),
        ("weight_imag", weight_imag),
    ] {
        check_finite(argument, values)?;
    }
    Ok(cells)
}

/// `len` zeros (`T::default()`), or an error naming `argument`.
fn zeroed<T: Default + Clone>(argument: &'static str, len: usize) -> Result<Vec<T>> {
    let mut values = reserve(argument, len)?;
    values.resize(len, T::default());
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splat(points: &[(f64, f64, f64, f64)], shape: [usize; 2]) -> SplatGrids {
        let column = |k: usize| -> Vec<f64> {
            points
                .iter()
                .map(|p| [p.0, p.1, p.2, p.3][k])
                .collect::<Vec<_>>()
        };
        splat_bilinear(&column(0), &column(1), &column(2), &column(3), shape).unwrap()
    }

    #[test]
    fn a_point_spreads_over_its_four_cells() {
        // col 1.25, row 2.5 on a 4 x 5 grid, weight 2 - 4i
        let grids = splat(&[(1.25, 2.5, 2.0, -4.0)], [4, 5]);
        let mut expected = [0.0f32; 20];
        expected[2 * 5 + 1] = 0.375; // (1 - 0.5) (1 - 0.25)
        expected[2 * 5 + 2] = 0.125; // (1 - 0.5) 0.25
        expected[3 * 5 + 1] = 0.375; // 0.5 (1 - 0.25)
        expected[3 * 5 + 2] = 0.125; // 0.5 0.25
        assert_eq!(grids.real, expected.map(|w| 2.0 * w));
        assert_eq!(grids.imag, expected.map(|w| -4.0 * w));
        let total: f32 = grids.real.iter().sum();
        assert_eq!(total, 2.0);
    }

    #[test]
    fn points_whose_cells_leave_the_grid_are_dropped() {
        let shape = [4, 5];
        let outside = [
            (-0.5, 1.0),          // left of the grid
            (4.0, 1.0),           // on the last column: col0 + 1 is off the grid
            (1.0, -1e-12),        // above
            (1.0, 3.0),           // on the last row
            (1e300, 1.0),         // beyond any index
            (-1e300, -1e300),     // before any index
            (f64::MAX, f64::MIN), // the extremes
        ];
        let points: Vec<_> = outside.iter().map(|&(c, r)| (c, r, 1.0, 1.0)).collect();
        let grids = splat(&points, shape);
        assert!(grids.real.iter().chain(&grids.imag).all(|&v| v == 0.0));
        // just inside the last cell edge: all in the last cells
        let edge = 4.0 - f64::EPSILON * 4.0;
        let grids = splat(&[(edge, 3.0 - 1e-9, 1.0, 0.0)], shape);
        assert!(grids.real[3 * 5 + 4] > 0.99 && grids.real.iter().sum::<f32>() == 1.0);
    }

    /// The float64 sums of the plain loop NumPy's bincount runs: corner by corner, every point in
    /// order, on one grid.
    fn bincount_order(points: &[(f64, f64, f64, f64)], [rows, cols]: [usize; 2]) -> Vec<[f64; 2]> {
        let mut sums = vec![[0.0f64; 2]; rows * cols];
        for (down, right) in [(false, false), (false, true), (true, false), (true, true)] {
            for &(col, row, real, imag) in points {
                let (col0, row0) = (col.floor(), row.floor());
                if !(col0 >= 0.0
                    && col0 < (cols - 1) as f64
                    && row0 >= 0.0
                    && row0 < (rows - 1) as f64)
                {
                    continue;
                }
                let (frac_col, frac_row) = (col - col0, row - row0);
                let along_row = if down { frac_row } else { 1.0 - frac_row };
                let along_col = if right { frac_col } else { 1.0 - frac_col };
                let index = (row0 as usize + usize::from(down)) * cols + col0 as usize;
                let cell = &mut sums[index + usize::from(right)];
                cell[0] += real * along_row * along_col;
                cell[1] += imag * along_row * along_col;
            }
        }
        sums
    }

    #[test]
    fn bands_sum_every_cell_in_bincount_order() {
        // The float64 sums, bit for bit (before the float32 rounding hides most changes of order):
        // wide grids of many bands (one to a few rows each) and narrow ones of a single band, some
        // points off the grid and a third of them crowded on a few cells.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for shape in [[40, 9000], [17, 3000], [30, 20], [2, 2]] {
            let [rows, cols] = shape.map(|n| n as f64);
            let points: Vec<_> = (0..5000)
                .map(|k| {
                    let (col, row) = if k % 3 == 0 {
                        (2.0 + uniform() * 2.0, rows / 2.0 - 1.0 + uniform() * 2.0)
                    } else {
                        (
                            uniform() * (cols + 2.0) - 1.0,
                            uniform() * (rows + 2.0) - 1.0,
                        )
                    };
                    (col, row, uniform() - 0.5, (uniform() - 0.5) * 1e-3)
                })
                .collect();
            let column =
                |k: usize| -> Vec<f64> { points.iter().map(|p| [p.0, p.1, p.2, p.3][k]).collect() };
            let columns = [column(0), column(1), column(2), column(3)];
            let mut sums = Vec::new();
            let slices = [&*columns[0], &*columns[1], &*columns[2], &*columns[3]];
            splat_sums(slices, shape, |band| sums.extend_from_slice(band)).unwrap();
            let bits = |sums: &[[f64; 2]]| {
                sums.iter()
                    .map(|cell| cell.map(f64::to_bits))
                    .collect::<Vec<_>>()
            };
            assert_eq!(
                bits(&sums),
                bits(&bincount_order(&points, shape)),
                "{shape:?}"
            );
            let grids = splat(&points, shape);
            assert!(grids.real.iter().zip(&sums).all(|(&r, s)| r == s[0] as f32));
            assert!(grids.imag.iter().zip(&sums).all(|(&i, s)| i == s[1] as f32));
        }
        assert!(Bands::new([40, 9000]).count == 40 && Bands::new([30, 20]).count == 1);
    }

    #[test]
    fn a_grid_of_one_row_or_column_takes_no_point() {
        for shape in [[1, 5], [5, 1], [1, 1]] {
            let grids = splat(&[(0.5, 0.5, 1.0, 1.0), (0.0, 0.0, 1.0, 1.0)], shape);
            assert_eq!(grids.real.len(), shape[0] * shape[1]);
            assert!(grids.real.iter().all(|&v| v == 0.0));
        }
    }

    #[test]
    fn bad_inputs_name_the_argument() {
        let ones = [1.0; 3];
        let argument = |error: KernelError| match error {
            KernelError::Shape { argument, .. }
            | KernelError::NonFinite { argument, .. }
            | KernelError::Value { argument, .. } => argument,
            other => panic!("{other}"),
        };
        let error = splat_bilinear(&ones, &ones[..2], &ones, &ones, [4, 4]).unwrap_err();
        assert_eq!(argument(error), "fine_row");
        let error = splat_bilinear(&ones, &ones, &ones, &[1.0, f64::NAN, 1.0], [4, 4]).unwrap_err();
        assert_eq!(argument(error), "weight_imag");
        for shape in [[0, 4], [4, 0], [usize::MAX, 2], [MAX_CELLS, 2]] {
            let error = splat_bilinear(&ones, &ones, &ones, &ones, shape).unwrap_err();
            assert_eq!(argument(error), "grid_shape");
        }
    }
}
