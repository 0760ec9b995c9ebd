//! A tensor-product cubic B-spline spatial basis for the displacement model.
//!
//! `D(x, y, F) = sum_ij B_i(y_n) B_j(x_n) (a_ij I1(F) + b_ij Ih(F) + c_ij Ih2(F))` per displacement
//! component, with `B` the cubic B-splines on uniform clamped knots over [0, 1] and `I1, Ih, Ih2`
//! the force integrals of `1, h, h^2` ([`ForceTerms`]). Per frame the three force terms collapse
//! into one coefficient grid; per row the `y` basis collapses it to one coefficient per `x`
//! function; per pixel only the 4 non-zero `x` functions remain, whatever the grid size or the
//! number of force intervals. Outside [0, 1] the end polynomial pieces are extended.

use std::ops::Range;
use std::sync::Arc;

use crate::error::{check_finite, check_len, KernelError, Result};
use crate::terms::{ForceTerms, Normalization, RowField};

/// Polynomial degree of the basis.
pub const DEGREE: usize = 3;
/// Fewest basis functions per axis (one knot span).
pub const MIN_FUNCTIONS: usize = DEGREE + 1;

/// The 4 non-zero cubic B-splines at `u` (normalised coordinate) for `n_functions` functions on
/// uniform clamped knots over [0, 1]: the index of the first one and their values (Cox-de Boor).
pub fn nonzero_basis(u: f64, n_functions: usize) -> (usize, [f64; 4]) {
    let n_spans = n_functions - DEGREE;
    let knot = |index: usize| -> f64 {
        // Knot `index` of the clamped vector: DEGREE + 1 zeros, interior knots, DEGREE + 1 ones.
        (index.saturating_sub(DEGREE).min(n_spans)) as f64 / n_spans as f64
    };
    // The span holding u (the end spans for u outside [0, 1]); u >= 0 here so `as` floors.
    let span = if u > 0.0 {
        ((u * n_spans as f64) as usize).min(n_spans - 1)
    } else {
        0
    };
    let last = span + DEGREE; // knot index t[last] <= u < t[last + 1]
    let mut values = [1.0, 0.0, 0.0, 0.0];
    let (mut left, mut right) = ([0.0; 4], [0.0; 4]);
    for j in 1..=DEGREE {
        left[j] = u - knot(last + 1 - j);
        right[j] = knot(last + j) - u;
        let mut saved = 0.0;
        for r in 0..j {
            let temp = values[r] / (right[r + 1] + left[j - r]);
            values[r] = saved + right[r + 1] * temp;
            saved = left[j - r] * temp;
        }
        values[j] = saved;
    }
    (span, values)
}

/// Basis values at the pixel positions `0..n` of one axis: per position the first non-zero
/// function and the 4 values.
#[derive(Debug, Clone, PartialEq)]
pub struct BasisTable {
    first: Vec<usize>,
    values: Vec<[f64; 4]>,
}

impl BasisTable {
    /// The table at pixels `0..n_pixels`, normalised by `scale` (pixels), for `n_functions` functions.
    pub fn new(n_pixels: usize, scale: f64, n_functions: usize) -> Self {
        let (first, values) = (0..n_pixels)
            .map(|pixel| nonzero_basis(pixel as f64 / scale, n_functions))
            .unzip();
        BasisTable { first, values }
    }
}

/// Spline coefficients, shape (2, 3, n_y, n_x): component (lateral, axial), force term (`1`, `h`,
/// `h^2`), `y` function, `x` function; with the normalisation of the inputs and outputs.
#[derive(Debug, Clone, PartialEq)]
pub struct BSplineModel {
    coefficients: Vec<f64>,
    n_y: usize,
    n_x: usize,
    pub normalization: Normalization,
}

impl BSplineModel {
    /// `coefficients` flat in the order (2, 3, n_y, n_x); `n_y, n_x >= 4`.
    pub fn new(
        coefficients: &[f64],
        n_y: usize,
        n_x: usize,
        normalization: Normalization,
    ) -> Result<Self> {
        if n_y < MIN_FUNCTIONS || n_x < MIN_FUNCTIONS {
            return Err(KernelError::Shape {
                argument: "coefficients",
                expected: format!("shape (2, 3, n_y, n_x) with n_y, n_x >= {MIN_FUNCTIONS}"),
                got: format!("n_y = {n_y}, n_x = {n_x}"),
            });
        }
        check_len("coefficients", coefficients, 2 * 3 * n_y * n_x)?;
        check_finite("coefficients", coefficients)?;
        Ok(BSplineModel {
            coefficients: coefficients.to_vec(),
            n_y,
            n_x,
            normalization,
        })
    }

    /// The basis tables of a `rows x cols` pixel grid, shared by every frame evaluated on it.
    pub fn tables(&self, rows: usize, cols: usize) -> SplineTables {
        SplineTables {
            x: Arc::new(BasisTable::new(cols, self.normalization.x_scale, self.n_x)),
            y: Arc::new(BasisTable::new(rows, self.normalization.y_scale, self.n_y)),
        }
    }

    /// The frame's displacement spline (pixels) for the given force terms on `tables`' grid.
    pub fn frame_spline(&self, terms: ForceTerms, tables: &SplineTables) -> FrameSpline {
        let n = &self.normalization;
        let size = self.n_y * self.n_x;
        let mut combined = vec![0.0; 2 * size];
        for (component, scale) in [n.lateral_scale, n.axial_scale].into_iter().enumerate() {
            let k = &self.coefficients[component * 3 * size..(component + 1) * 3 * size];
            let (one, h, h2) = (&k[..size], &k[size..2 * size], &k[2 * size..]);
            for (j, out) in combined[component * size..(component + 1) * size]
                .iter_mut()
                .enumerate()
            {
                *out = scale * (one[j] * terms.one + h[j] * terms.h + h2[j] * terms.h2);
            }
        }
        FrameSpline {
            combined,
            n_x: self.n_x,
            tables: tables.clone(),
        }
    }
}

/// Basis tables along the columns (`x`) and rows (`y`) of a pixel grid.
#[derive(Debug, Clone, PartialEq)]
pub struct SplineTables {
    x: Arc<BasisTable>,
    y: Arc<BasisTable>,
}

/// One frame's displacement as a spline: coefficients (2, n_y, n_x) in pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameSpline {
    combined: Vec<f64>,
    n_x: usize,
    tables: SplineTables,
}

impl FrameSpline {
    /// The displacement along the row `row`: the `y` basis applied, one coefficient per `x` function.
    pub fn row(&self, row: usize) -> SplineRow<'_> {
        let mut coefficients = Vec::new();
        self.row_into(row, &mut coefficients);
        SplineRow {
            coefficients,
            x: &self.tables.x,
        }
    }

    /// [`FrameSpline::row`]'s coefficients into `coefficients` (reused scratch: no allocation once
    /// it has grown to `n_x`).
    #[inline(always)]
    pub fn row_into(&self, row: usize, coefficients: &mut Vec<[f64; 2]>) {
        let (first_y, weights_y) = (self.tables.y.first[row], self.tables.y.values[row]);
        let n_x = self.n_x;
        let size = self.combined.len() / 2;
        coefficients.clear();
        coefficients.resize(n_x, [0.0; 2]);
        for (component, grid) in self.combined.chunks_exact(size).enumerate() {
            for (offset, weight) in weights_y.iter().enumerate() {
                let start = (first_y + offset) * n_x;
                for (out, c) in coefficients.iter_mut().zip(&grid[start..start + n_x]) {
                    out[component] += weight * c;
                }
            }
        }
    }

    /// A row field over `coefficients` filled by [`FrameSpline::row_into`].
    pub fn row_over<'a>(&'a self, coefficients: &'a [[f64; 2]]) -> SplineRowView<'a> {
        SplineRowView {
            coefficients,
            x: &self.tables.x,
        }
    }
}

/// One row of a [`FrameSpline`]: per `x` function the (lateral, axial) coefficient in pixels.
pub struct SplineRow<'a> {
    coefficients: Vec<[f64; 2]>,
    x: &'a BasisTable,
}

impl RowField for SplineRow<'_> {
    #[inline]
    fn at(&self, col: usize) -> [f64; 2] {
        spline_at(&self.coefficients, self.x, col)
    }
}

/// [`SplineRow`] over borrowed coefficients (a reused scratch buffer).
pub struct SplineRowView<'a> {
    coefficients: &'a [[f64; 2]],
    x: &'a BasisTable,
}

impl RowField for SplineRowView<'_> {
    #[inline]
    fn at(&self, col: usize) -> [f64; 2] {
        spline_at(self.coefficients, self.x, col)
    }
}

impl SplineRowView<'_> {
    /// [`RowField::at`] of each column of `cols` into `out` (as long as `cols`), a run of columns
    /// with the same non-zero functions at a time (the same sums, in a loop the compiler vectorises).
    #[inline(always)]
    pub fn fill(&self, cols: Range<usize>, out: &mut [[f64; 2]]) {
        let mut start = cols.start;
        while start < cols.end {
            // `first` grows with the column.
            let first = self.x.first[start];
            let end = start + self.x.first[start..cols.end].partition_point(|&f| f <= first);
            let around = &self.coefficients[first..first + 4];
            let values = &mut out[start - cols.start..end - cols.start];
            for (value, weights) in values.iter_mut().zip(&self.x.values[start..end]) {
                *value = spline_sum(weights, around);
            }
            start = end;
        }
    }
}

#[inline]
fn spline_at(coefficients: &[[f64; 2]], x: &BasisTable, col: usize) -> [f64; 2] {
    let first = x.first[col];
    spline_sum(&x.values[col], &coefficients[first..first + 4])
}

/// The 4 non-zero functions' `weights` times their coefficients `around` (lateral, axial), summed.
#[inline(always)]
fn spline_sum(weights: &[f64; 4], around: &[[f64; 2]]) -> [f64; 2] {
    let mut out = [0.0; 2];
    for component in 0..2 {
        out[component] = weights[0] * around[0][component]
            + weights[1] * around[1][component]
            + weights[2] * around[2][component]
            + weights[3] * around[3][component];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Plain Cox-de Boor recursion over the full clamped knot vector, for the tests.
    fn basis_by_recursion(u: f64, n_functions: usize) -> Vec<f64> {
        let n_spans = n_functions - DEGREE;
        let knots: Vec<f64> = (0..n_functions + DEGREE + 1)
            .map(|i| (i.saturating_sub(DEGREE).min(n_spans)) as f64 / n_spans as f64)
            .collect();
        // Degree 0: the span holding u (the last non-empty one for u = 1).
        let mut values: Vec<f64> = (0..knots.len() - 1)
            .map(|i| {
                let inside = knots[i] <= u && u < knots[i + 1];
                let at_end = u == 1.0 && knots[i] < 1.0 && knots[i + 1] == 1.0;
                if inside || at_end {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        for degree in 1..=DEGREE {
            values = (0..knots.len() - 1 - degree)
                .map(|i| {
                    let ratio = |num: f64, den: f64| if den > 0.0 { num / den } else { 0.0 };
                    ratio(u - knots[i], knots[i + degree] - knots[i]) * values[i]
                        + ratio(
                            knots[i + degree + 1] - u,
                            knots[i + degree + 1] - knots[i + 1],
                        ) * values[i + 1]
                })
                .collect();
        }
        values
    }

    #[test]
    fn nonzero_basis_matches_the_recursion_and_sums_to_one() {
        for n_functions in [4, 5, 7, 12] {
            for step in 0..=40 {
                let u = step as f64 / 40.0;
                let (first, values) = nonzero_basis(u, n_functions);
                let full = basis_by_recursion(u, n_functions);
                for (index, expected) in full.iter().enumerate() {
                    let got = if (first..first + 4).contains(&index) {
                        values[index - first]
                    } else {
                        0.0
                    };
                    assert!(
                        (got - expected).abs() < 1e-14,
                        "n {n_functions} u {u} i {index}"
                    );
                }
                assert!((values.iter().sum::<f64>() - 1.0).abs() < 1e-14);
            }
        }
    }

    #[test]
    fn partition_of_unity_holds_when_extrapolating() {
        for u in [-0.3, -1e-9, 1.0 + 1e-9, 1.4] {
            let (first, values) = nonzero_basis(u, 6);
            assert!(first + 4 <= 6);
            assert!((values.iter().sum::<f64>() - 1.0).abs() < 1e-12, "u {u}");
        }
    }

    fn normalization(rows: usize, cols: usize) -> Normalization {
        Normalization {
            x_scale: (cols - 1) as f64,
            y_scale: (rows - 1) as f64,
            force_scale: 1.0,
            h_scale: 1.0,
            lateral_scale: 2.0,
            axial_scale: -3.0,
        }
    }

    #[test]
    fn constant_coefficients_give_a_constant_field() {
        let (n_y, n_x, rows, cols) = (5, 7, 9, 13);
        let size = n_y * n_x;
        let mut coefficients = vec![0.0; 6 * size];
        coefficients[..size].fill(1.5); // lateral, term 1
        coefficients[3 * size + size..3 * size + 2 * size].fill(0.5); // axial, term h
        let model = BSplineModel::new(&coefficients, n_y, n_x, normalization(rows, cols)).unwrap();
        let tables = model.tables(rows, cols);
        let terms = ForceTerms {
            one: 2.0,
            h: 4.0,
            h2: 7.0,
        };
        let spline = model.frame_spline(terms, &tables);
        for row in 0..rows {
            let row_field = spline.row(row);
            for col in 0..cols {
                let [lateral, axial] = row_field.at(col);
                assert!((lateral - 2.0 * 1.5 * 2.0).abs() < 1e-12);
                assert!((axial - -3.0 * 0.5 * 4.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn a_row_filled_over_columns_is_the_field_at_each() {
        let (n_y, n_x, rows, cols) = (5, 7, 9, 41);
        let coefficients: Vec<f64> = (0..6 * n_y * n_x).map(|i| (i as f64 * 0.9).sin()).collect();
        let model = BSplineModel::new(&coefficients, n_y, n_x, normalization(rows, cols)).unwrap();
        let tables = model.tables(rows, cols);
        let terms = ForceTerms {
            one: 2.0,
            h: -4.0,
            h2: 7.0,
        };
        let spline = model.frame_spline(terms, &tables);
        let mut scratch = Vec::new();
        for (row, columns) in [(0, 0..cols), (4, 3..29), (8, 17..18)] {
            spline.row_into(row, &mut scratch);
            let mut filled = vec![[0.0; 2]; columns.len()];
            spline.row_over(&scratch).fill(columns.clone(), &mut filled);
            let row_field = spline.row(row);
            let each: Vec<[f64; 2]> = columns.map(|col| row_field.at(col)).collect();
            assert_eq!(filled, each, "row {row}");
        }
    }

    #[test]
    fn too_few_functions_are_rejected() {
        let err = BSplineModel::new(&[0.0; 2 * 3 * 3 * 4], 3, 4, normalization(4, 4)).unwrap_err();
        assert!(err.to_string().starts_with("coefficients:"), "{err}");
    }
}
