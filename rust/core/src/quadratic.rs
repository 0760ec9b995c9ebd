//! The paper's quadratic spatial basis (eq. 7).
//!
//! With `M(x, y, h) = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]` and normalised inputs, the rate
//! `d = K M` is a quadratic in `h` whose coefficients are polynomials in `(x, y)`:
//! `d = A(x, y) + B(x, y) h + C h^2`. The displacement at force `F` is the integral of `d` over
//! the (normalised) force, so it only needs three per-frame scalars, the force integrals of `1`,
//! `h` and `h^2` ([`ForceTerms`]). The per-pixel cost is then a fixed quadratic in `(x, y)`,
//! whatever the number of force intervals.

use crate::error::{check_finite, KernelError, Result};
use crate::terms::{ForceTerms, Normalization, RowField};

/// Number of terms of the paper's regression vector `M(x, y, h)`.
pub const N_TERMS: usize = 10;

/// Regression coefficients: row 0 lateral (`K^x`), row 1 axial (`K^y`), in the order of `M`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QuadraticModel {
    pub coefficients: [[f64; N_TERMS]; 2],
    pub normalization: Normalization,
}

impl QuadraticModel {
    pub fn new(coefficients: &[f64], normalization: Normalization) -> Result<Self> {
        if coefficients.len() != 2 * N_TERMS {
            return Err(KernelError::Shape {
                argument: "coefficients",
                expected: "shape (2, 10)".into(),
                got: format!("{} values", coefficients.len()),
            });
        }
        check_finite("coefficients", coefficients)?;
        let mut rows = [[0.0; N_TERMS]; 2];
        rows[0].copy_from_slice(&coefficients[..N_TERMS]);
        rows[1].copy_from_slice(&coefficients[N_TERMS..]);
        Ok(QuadraticModel {
            coefficients: rows,
            normalization,
        })
    }

    /// Per-frame polynomial of the displacement in normalised `(x, y)` for given force terms.
    pub fn frame_polynomial(&self, terms: ForceTerms) -> FramePolynomial {
        let scale = [
            self.normalization.lateral_scale,
            self.normalization.axial_scale,
        ];
        let mut components = [[0.0; 6]; 2];
        for (component, k) in self.coefficients.iter().enumerate() {
            let s = scale[component];
            // Basis order: x^2, y^2, xy, x, y, 1.
            components[component] = [
                s * k[0] * terms.one,
                s * k[1] * terms.one,
                s * k[3] * terms.one,
                s * (k[6] * terms.one + k[4] * terms.h),
                s * (k[7] * terms.one + k[5] * terms.h),
                s * (k[9] * terms.one + k[8] * terms.h + k[2] * terms.h2),
            ];
        }
        FramePolynomial {
            components,
            x_scale: self.normalization.x_scale,
            y_scale: self.normalization.y_scale,
        }
    }
}

/// Displacement of one frame as a quadratic in pixel coordinates, in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FramePolynomial {
    /// Per component (lateral, axial): coefficients of `x_n^2, y_n^2, x_n y_n, x_n, y_n, 1`.
    components: [[f64; 6]; 2],
    x_scale: f64,
    y_scale: f64,
}

impl FramePolynomial {
    /// The displacement along the row `row`: per component `D(x) = (a x_n + b) x_n + c`.
    #[inline]
    pub fn row(&self, row: usize) -> PolynomialRow {
        let y = row as f64 / self.y_scale;
        let mut coefficients = [[0.0; 3]; 2];
        for (component, p) in self.components.iter().enumerate() {
            coefficients[component] = [p[0], p[2] * y + p[3], (p[1] * y + p[4]) * y + p[5]];
        }
        PolynomialRow {
            coefficients,
            inverse_x_scale: 1.0 / self.x_scale,
        }
    }
}

/// One row of a [`FramePolynomial`]: per component `(a, b, c)` of `(a x_n + b) x_n + c`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolynomialRow {
    coefficients: [[f64; 3]; 2],
    /// `1 / x_scale`: a multiplication per pixel instead of a division.
    inverse_x_scale: f64,
}

impl RowField for PolynomialRow {
    #[inline]
    fn at(&self, col: usize) -> [f64; 2] {
        let x = col as f64 * self.inverse_x_scale;
        let [[ax, bx, cx], [ay, by, cy]] = self.coefficients;
        [(ax * x + bx) * x + cx, (ay * x + by) * x + cy]
    }
}
