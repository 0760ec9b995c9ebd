//! The spatial field of a displacement model, whichever its basis: [`SpatialModel`] lets the same
//! force terms multiply the paper's quadratic ([`crate::quadratic`]) or the cubic B-spline basis
//! ([`crate::bspline`]); the kernels evaluate either row by row through [`RowField`].

use crate::bspline::{BSplineModel, FrameSpline};
use crate::error::{KernelError, Result};
use crate::quadratic::{FramePolynomial, QuadraticModel};
use crate::stiffness::StiffnessProfile;
use crate::terms::{zeroed, ForceTerms, Integral, Normalization, RowField};

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::quadratic::N_TERMS;
    use crate::terms::{force_integral, IntegrationVariable};

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
            &Normalization::UNIT,
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
            ForceTerms::integrated(3.0, &profile, integral, &Normalization::UNIT, 0).unwrap();
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
            &Normalization::UNIT,
            0,
        );
        assert!(terms.is_ok(), "{terms:?}");
        assert_eq!(profile.lambda_at(1.0), Some(-2.0));
        assert_eq!(profile.stiffness_at(-2.0), 1.0);
    }

    /// `int_0^F f^p / k(f)^q df` by the midpoint rule on `n` intervals of the probe displacement
    /// (`df = k dlambda`; the integrand is smooth in lambda, not in f where k is small).
    fn midpoint(profile: &StiffnessProfile, force: f64, p: i32, q: i32, n: usize) -> f64 {
        let (start, end) = (
            profile.lambda_at(0.0).unwrap(),
            profile.lambda_at(force).unwrap(),
        );
        let step = (end - start) / n as f64;
        (0..n)
            .map(|i| {
                let lambda = start + step * (i as f64 + 0.5);
                let stretched = lambda.max(0.0);
                let f = profile.c3 + profile.c2 * lambda + profile.c1 * stretched * stretched;
                let k = profile.stiffness_at(lambda);
                f.powi(p) * k.powi(1 - q) * step
            })
            .sum()
    }

    #[test]
    fn closed_form_integrals_match_fine_quadrature() {
        let profiles = [
            (0.4, 0.8, 0.0),
            (0.08, 0.6, 0.0),
            (1e-9, 1.5, 0.0),  // nearly linear: the series path, no cancellation
            (0.0, 2.0, 0.0),   // linear
            (0.3, 1.0, 3.0),   // preloaded: linear continuation below 3 N
            (0.2, 0.7, -0.4),  // started below zero force
            (0.0, 0.02, -1.0), // ... far below: 0 N is 50 mm up the curve
            (0.5, 0.3, -2.0),  // ... and curved
            (-0.02, 2.0, 0.5), // softening, still rising at 30 N
            (25.0, 0.05, 0.0), // strongly stiffening: the exact path
        ];
        for (c1, c2, c3) in profiles {
            let profile = StiffnessProfile { c1, c2, c3 };
            for force in [-0.3, 6e-8, 0.7, 5.0, 30.0] {
                for (p, q) in [(0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (2, 3)] {
                    let exact = force_integral(&profile, force, p, q).unwrap();
                    let fine = midpoint(&profile, force, p as i32, q as i32, 200_000);
                    assert!(
                        (exact - fine).abs() <= 1e-7 * fine.abs().max(1e-12),
                        "profile {profile:?} F {force} p {p} q {q}: {exact} vs {fine}"
                    );
                }
            }
        }
    }

    #[test]
    fn integrals_ignore_the_interval_count() {
        let profile = StiffnessProfile {
            c1: 0.4,
            c2: 0.8,
            c3: 0.0,
        };
        let terms = |n| {
            ForceTerms::integrated(
                10.0,
                &profile,
                Integral::over_force(n),
                &Normalization::UNIT,
                0,
            )
        };
        assert_eq!(terms(1).unwrap(), terms(4096).unwrap());
        let err = terms(crate::terms::MAX_INTERVALS + 1).unwrap_err();
        assert!(err.to_string().starts_with("n_intervals:"), "{err}");
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
            &Normalization::UNIT,
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
