//! The coupled quadratic displacement regression (paper eqs. 7-8 and 12).
//!
//! With `M(x, y, h) = [x^2, y^2, h^2, xy, xh, yh, x, y, h, 1]` and normalised inputs, the rate
//! `d = K M` is a quadratic in `h` whose coefficients are polynomials in `(x, y)`:
//! `d = A(x, y) + B(x, y) h + C h^2`. The displacement at force `F` is the integral of `d` over
//! the (normalised) force, so it only needs three per-frame scalars, the force integrals of `1`,
//! `h` and `h^2`. The per-pixel cost is then a fixed quadratic in `(x, y)`, whatever the number of
//! force intervals. [`SpatialModel`] lets the same force terms multiply either this quadratic or
//! the cubic B-spline basis of [`crate::bspline`]; the kernels evaluate either row by row through
//! [`RowField`].

use crate::bspline::{BSplineModel, FrameSpline};
use crate::error::{check_finite, KernelError, Result};
use crate::stiffness::StiffnessProfile;

/// Number of terms of the paper's regression vector `M(x, y, h)`.
pub const N_TERMS: usize = 10;

/// The scales that map physical quantities to the regression's normalised [0, 1] inputs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normalization {
    /// Lateral pixel coordinate divisor: `x_n = x / x_scale` (pixels).
    pub x_scale: f64,
    /// Axial pixel coordinate divisor: `y_n = y / y_scale` (pixels).
    pub y_scale: f64,
    /// Force divisor: `F_n = F / force_scale` (N).
    pub force_scale: f64,
    /// `h = F / k` divisor: `h_n = h / h_scale` (mm).
    pub h_scale: f64,
    /// Lateral displacement multiplier: `D_x = D_n,x * lateral_scale` (pixels).
    pub lateral_scale: f64,
    /// Axial displacement multiplier: `D_y = D_n,y * axial_scale` (pixels).
    pub axial_scale: f64,
}

impl Normalization {
    pub fn from_slice(values: &[f64]) -> Result<Self> {
        if values.len() != 6 {
            return Err(KernelError::Shape {
                argument: "normalization",
                expected:
                    "6 values (x_scale, y_scale, force_scale, h_scale, lateral_scale, axial_scale)"
                        .into(),
                got: format!("{} values", values.len()),
            });
        }
        check_finite("normalization", values)?;
        if let Some(index) = values[..4].iter().position(|v| *v <= 0.0) {
            return Err(KernelError::Value {
                argument: "normalization",
                message: format!("the divisors x_scale, y_scale, force_scale, h_scale must be positive; value {index} is {}", values[index]),
            });
        }
        Ok(Normalization {
            x_scale: values[0],
            y_scale: values[1],
            force_scale: values[2],
            h_scale: values[3],
            lateral_scale: values[4],
            axial_scale: values[5],
        })
    }
}

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

/// The variable the rate `d(x, y, h)` is integrated over (paper eq. 8 integrates over force).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntegrationVariable {
    /// `D = int_0^F d(x, y, h(f)) df_n`, the paper's eq. 8, with `f_n = f / force_scale`.
    Force,
    /// `D = int_0^lambda(F) d(x, y, h) dlambda_n` with `dlambda = df / k` and `lambda_n = lambda / h_scale`:
    /// for a linear tissue the displacement is then proportional to `F / k`, so every term follows a
    /// change of stiffness, not only the terms in `h`.
    ProbeDisplacement,
}

/// How the rate is integrated: over which variable, on how many equal force intervals (stiffness
/// held at its interval-midpoint value on each).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Integral {
    pub variable: IntegrationVariable,
    pub n_intervals: usize,
}

impl Integral {
    /// The paper's integral over force on `n_intervals` intervals.
    pub fn over_force(n_intervals: usize) -> Integral {
        Integral {
            variable: IntegrationVariable::Force,
            n_intervals,
        }
    }
}

/// The three per-frame scalars multiplying the spatial parts of the model: for the rate `d` at a
/// given `h_n` they are `(1, h_n, h_n^2)`; for the integrated displacement `D` they are the force
/// integrals of `1`, `h_n` and `h_n^2` over the normalised force.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceTerms {
    pub one: f64,
    pub h: f64,
    pub h2: f64,
}

impl ForceTerms {
    /// Terms of the rate `d(x, y, h)` at `h` (mm).
    pub fn at_h(h_mm: f64, normalization: &Normalization) -> ForceTerms {
        let h = h_mm / normalization.h_scale;
        ForceTerms {
            one: 1.0,
            h,
            h2: h * h,
        }
    }

    /// Integrals of `1`, `h_n` and `h_n^2` from 0 to `force_n` (see [`IntegrationVariable`]) with
    /// the stiffness held at its interval-midpoint value on each of the integral's equal force
    /// intervals (paper eq. 8). `frame` only labels errors.
    pub fn integrated(
        force_n: f64,
        profile: &StiffnessProfile,
        integral: Integral,
        normalization: &Normalization,
        frame: usize,
    ) -> Result<ForceTerms> {
        let n_intervals = integral.n_intervals;
        if n_intervals == 0 {
            return Err(KernelError::Value {
                argument: "n_intervals",
                message: "must be at least 1".into(),
            });
        }
        if !force_n.is_finite() {
            return Err(KernelError::NonFinite {
                argument: "forces",
                index: frame,
            });
        }
        profile.check_finite(frame)?;
        let step = force_n / n_intervals as f64;
        // Per interval, exact integrals over [lower, upper] of f^p / k^(p + w) df for p = 0, 1, 2,
        // where w = 0 integrates over force and w = 1 over probe displacement (dlambda = df / k).
        let extra_power = match integral.variable {
            IntegrationVariable::Force => 0,
            IntegrationVariable::ProbeDisplacement => 1,
        };
        let (mut integral_1, mut integral_h, mut integral_h2) = (0.0, 0.0, 0.0);
        for interval in 0..n_intervals {
            let lower = step * interval as f64;
            let upper = step * (interval + 1) as f64;
            let midpoint = 0.5 * (lower + upper);
            let stiffness = match profile
                .lambda_at(midpoint)
                .map(|lambda| profile.stiffness_at(lambda))
            {
                Some(stiffness) if stiffness > 0.0 => stiffness,
                _ => {
                    return Err(KernelError::OutsideRisingBranch {
                        frame,
                        force: midpoint,
                    })
                }
            };
            let weight = stiffness.powi(-extra_power);
            integral_1 += (upper - lower) * weight;
            integral_h += (upper * upper - lower * lower) / (2.0 * stiffness) * weight;
            integral_h2 += (upper.powi(3) - lower.powi(3)) / (3.0 * stiffness * stiffness) * weight;
        }
        let n = normalization;
        let variable_scale = match integral.variable {
            IntegrationVariable::Force => n.force_scale,
            IntegrationVariable::ProbeDisplacement => n.h_scale,
        };
        Ok(ForceTerms {
            one: integral_1 / variable_scale,
            h: integral_h / (n.h_scale * variable_scale),
            h2: integral_h2 / (n.h_scale * n.h_scale * variable_scale),
        })
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
            x_scale: self.x_scale,
        }
    }
}

/// The displacement (lateral, axial; pixels) along one pixel row, column by column.
pub trait RowField {
    fn at(&self, col: usize) -> [f64; 2];
}

/// One row of a [`FramePolynomial`]: per component `(a, b, c)` of `(a x_n + b) x_n + c`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PolynomialRow {
    coefficients: [[f64; 3]; 2],
    x_scale: f64,
}

impl RowField for PolynomialRow {
    #[inline]
    fn at(&self, col: usize) -> [f64; 2] {
        let x = col as f64 / self.x_scale;
        let [[ax, bx, cx], [ay, by, cy]] = self.coefficients;
        [(ax * x + bx) * x + cx, (ay * x + by) * x + cy]
    }
}

/// The spatial basis of the displacement model.
#[derive(Debug, Clone, PartialEq)]
pub enum SpatialModel {
    /// The paper's quadratic regression (eq. 7).
    Quadratic(QuadraticModel),
    /// A tensor-product cubic B-spline with free `1`, `h` and `h^2` coefficients per function.
    BSpline(BSplineModel),
}

impl SpatialModel {
    pub fn normalization(&self) -> &Normalization {
        match self {
            SpatialModel::Quadratic(model) => &model.normalization,
            SpatialModel::BSpline(model) => &model.normalization,
        }
    }

    /// The displacement field (pixels) of each set of force terms on a `rows x cols` pixel grid;
    /// grid-dependent basis values are computed once and shared by all frames.
    pub fn frame_fields(&self, terms: &[ForceTerms], rows: usize, cols: usize) -> Vec<FrameField> {
        match self {
            SpatialModel::Quadratic(model) => terms
                .iter()
                .map(|&t| FrameField::Quadratic(model.frame_polynomial(t)))
                .collect(),
            SpatialModel::BSpline(model) => {
                let tables = model.tables(rows, cols);
                terms
                    .iter()
                    .map(|&t| FrameField::BSpline(model.frame_spline(t, &tables)))
                    .collect()
            }
        }
    }
}

/// One frame's displacement field on a pixel grid, in pixels.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameField {
    Quadratic(FramePolynomial),
    BSpline(FrameSpline),
}

impl FrameField {
    /// Fill `out` (2, rows, cols), C order, with the displacement in pixels.
    pub fn fill(&self, rows: usize, cols: usize, out: &mut [f64]) {
        let (lateral, axial) = out.split_at_mut(rows * cols);
        for (row, (lateral_row, axial_row)) in lateral
            .chunks_mut(cols)
            .zip(axial.chunks_mut(cols))
            .enumerate()
        {
            match self {
                FrameField::Quadratic(polynomial) => {
                    fill_row(&polynomial.row(row), lateral_row, axial_row)
                }
                FrameField::BSpline(spline) => fill_row(&spline.row(row), lateral_row, axial_row),
            }
        }
    }
}

fn fill_row(row_field: &impl RowField, lateral_row: &mut [f64], axial_row: &mut [f64]) {
    for (col, (lateral, axial)) in lateral_row.iter_mut().zip(axial_row).enumerate() {
        [*lateral, *axial] = row_field.at(col);
    }
}

/// Rate `d(x, y, h)` (pixels per unit normalised force) on a `rows x cols` pixel grid, shape (2, rows, cols).
pub fn rate_field(model: &SpatialModel, h_mm: f64, rows: usize, cols: usize) -> Result<Vec<f64>> {
    if !h_mm.is_finite() {
        return Err(KernelError::NonFinite {
            argument: "h",
            index: 0,
        });
    }
    let terms = ForceTerms::at_h(h_mm, model.normalization());
    field_on_grid(model, terms, rows, cols)
}

/// Displacement `D(x, y, F)` (pixels) at `force_n` on a `rows x cols` grid, shape (2, rows, cols).
pub fn displacement_field(
    model: &SpatialModel,
    force_n: f64,
    profile: &StiffnessProfile,
    integral: Integral,
    rows: usize,
    cols: usize,
) -> Result<Vec<f64>> {
    let terms = ForceTerms::integrated(force_n, profile, integral, model.normalization(), 0)?;
    field_on_grid(model, terms, rows, cols)
}

fn field_on_grid(
    model: &SpatialModel,
    terms: ForceTerms,
    rows: usize,
    cols: usize,
) -> Result<Vec<f64>> {
    let mut out = zeroed(
        "rows, cols",
        rows.checked_mul(cols).and_then(|n| n.checked_mul(2)),
    )?;
    model.frame_fields(&[terms], rows, cols)[0].fill(rows, cols, &mut out);
    Ok(out)
}

/// `len` zeros, or an error naming `argument` when `len` overflowed (None) or cannot be allocated:
/// an allocation failure would abort the process, which no panic handler can catch.
pub fn zeroed(argument: &'static str, len: Option<usize>) -> Result<Vec<f64>> {
    let len = len.ok_or(KernelError::Allocation {
        argument,
        bytes: u128::MAX,
    })?;
    let mut values = Vec::new();
    values
        .try_reserve_exact(len)
        .map_err(|_| KernelError::Allocation {
            argument,
            bytes: len as u128 * 8,
        })?;
    values.resize(len, 0.0);
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_normalization() -> Normalization {
        Normalization {
            x_scale: 1.0,
            y_scale: 1.0,
            force_scale: 1.0,
            h_scale: 1.0,
            lateral_scale: 1.0,
            axial_scale: 1.0,
        }
    }

    fn m_vector(x: f64, y: f64, h: f64) -> [f64; N_TERMS] {
        [x * x, y * y, h * h, x * y, x * h, y * h, x, y, h, 1.0]
    }

    #[test]
    fn rate_matches_direct_evaluation_of_m() {
        let mut coefficients = [0.0; 20];
        for (i, c) in coefficients.iter_mut().enumerate() {
            *c = (i as f64 * 0.37).sin();
        }
        let normalization = Normalization {
            x_scale: 7.0,
            y_scale: 5.0,
            force_scale: 3.0,
            h_scale: 2.0,
            lateral_scale: 4.0,
            axial_scale: -1.5,
        };
        let model = QuadraticModel::new(&coefficients, normalization).unwrap();
        let (rows, cols, h) = (5, 7, 1.3);
        let field = rate_field(&SpatialModel::Quadratic(model), h, rows, cols).unwrap();
        for row in 0..rows {
            for col in 0..cols {
                let m = m_vector(col as f64 / 7.0, row as f64 / 5.0, h / 2.0);
                let lateral: f64 = m
                    .iter()
                    .zip(&coefficients[..10])
                    .map(|(a, b)| a * b)
                    .sum::<f64>()
                    * 4.0;
                let axial: f64 = m
                    .iter()
                    .zip(&coefficients[10..])
                    .map(|(a, b)| a * b)
                    .sum::<f64>()
                    * -1.5;
                assert!((field[row * cols + col] - lateral).abs() < 1e-12);
                assert!((field[rows * cols + row * cols + col] - axial).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn constant_stiffness_integrals_are_exact() {
        // k = 2 N/mm constant: int_0^F f/k df = F^2 / 4, int_0^F (f/k)^2 df = F^3 / 12.
        let profile = StiffnessProfile {
            c1: 0.0,
            c2: 2.0,
            c3: 0.0,
        };
        let terms = ForceTerms::integrated(
            3.0,
            &profile,
            Integral::over_force(7),
            &unit_normalization(),
            0,
        )
        .unwrap();
        assert!((terms.one - 3.0).abs() < 1e-12);
        assert!((terms.h - 9.0 / 4.0).abs() < 1e-12);
        assert!((terms.h2 - 27.0 / 12.0).abs() < 1e-12);
    }

    #[test]
    fn displacement_integral_of_a_linear_tissue_is_its_probe_displacement() {
        // k = 2 N/mm: lambda(F) = F / 2, int h dlambda = F^2 / 8, int h^2 dlambda = F^3 / 24.
        let profile = StiffnessProfile {
            c1: 0.0,
            c2: 2.0,
            c3: 0.0,
        };
        let integral = Integral {
            variable: IntegrationVariable::ProbeDisplacement,
            n_intervals: 5,
        };
        let terms =
            ForceTerms::integrated(3.0, &profile, integral, &unit_normalization(), 0).unwrap();
        assert!((terms.one - 1.5).abs() < 1e-12);
        assert!((terms.h - 9.0 / 8.0).abs() < 1e-12);
        assert!((terms.h2 - 27.0 / 24.0).abs() < 1e-12);
    }

    #[test]
    fn preloaded_palpation_integrates_from_zero_force() {
        // Palpation started at a 3 N preload; the quadratic alone never reaches forces below 0.5 N.
        let profile = StiffnessProfile {
            c1: 0.1,
            c2: 1.0,
            c3: 3.0,
        };
        let terms = ForceTerms::integrated(
            10.0,
            &profile,
            Integral::over_force(64),
            &unit_normalization(),
            0,
        );
        assert!(terms.is_ok(), "{terms:?}");
        assert_eq!(profile.lambda_at(1.0), Some(-2.0));
        assert_eq!(profile.stiffness_at(-2.0), 1.0);
    }

    #[test]
    fn nonlinear_profile_converges_with_more_intervals() {
        let profile = StiffnessProfile {
            c1: 0.4,
            c2: 0.8,
            c3: 0.0,
        };
        let coarse = ForceTerms::integrated(
            10.0,
            &profile,
            Integral::over_force(64),
            &unit_normalization(),
            0,
        )
        .unwrap();
        let fine = ForceTerms::integrated(
            10.0,
            &profile,
            Integral::over_force(4096),
            &unit_normalization(),
            0,
        )
        .unwrap();
        assert!((coarse.h - fine.h).abs() / fine.h < 1e-3);
        assert!((coarse.h2 - fine.h2).abs() / fine.h2 < 1e-3);
    }

    #[test]
    fn softening_profile_beyond_its_peak_is_rejected() {
        let profile = StiffnessProfile {
            c1: -1.0,
            c2: 2.0,
            c3: 0.0,
        }; // peaks at F = 1 N
        let err = ForceTerms::integrated(
            2.0,
            &profile,
            Integral::over_force(8),
            &unit_normalization(),
            3,
        )
        .unwrap_err();
        assert!(matches!(
            err,
            KernelError::OutsideRisingBranch { frame: 3, .. }
        ));
    }

    #[test]
    fn bad_normalization_names_the_argument() {
        let err = Normalization::from_slice(&[1.0, 0.0, 1.0, 1.0, 1.0, 1.0]).unwrap_err();
        assert!(err.to_string().starts_with("normalization:"));
    }
}
