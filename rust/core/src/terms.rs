//! The shared terms of every displacement model: the normalisation of inputs and outputs, the
//! integral of the rate over force (paper eq. 8) and its three per-frame force terms, the row
//! evaluation interface of the spatial fields, and checked allocation.

use crate::error::{check_finite, KernelError, Result};
use crate::stiffness::StiffnessProfile;

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
    /// Every scale 1: normalised and physical values coincide.
    pub const UNIT: Normalization = Normalization {
        x_scale: 1.0,
        y_scale: 1.0,
        force_scale: 1.0,
        h_scale: 1.0,
        lateral_scale: 1.0,
        axial_scale: 1.0,
    };

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

/// The displacement (lateral, axial; pixels) along one pixel row, column by column.
pub trait RowField {
    fn at(&self, col: usize) -> [f64; 2];
}

/// `len` zeros, or an error naming `argument` when `len` overflowed (None) or cannot be allocated.
pub fn zeroed(argument: &'static str, len: Option<usize>) -> Result<Vec<f64>> {
    let len = len.ok_or(KernelError::Allocation {
        argument,
        bytes: u128::MAX,
    })?;
    filled(argument, len, 0.0)
}

/// `len` copies of `value`, or an error naming `argument` when they cannot be allocated: an
/// allocation failure would abort the process, which no panic handler can catch.
pub fn filled<T: Clone>(argument: &'static str, len: usize, value: T) -> Result<Vec<T>> {
    let mut values = Vec::new();
    values
        .try_reserve_exact(len)
        .map_err(|_| KernelError::Allocation {
            argument,
            bytes: len as u128 * std::mem::size_of::<T>() as u128,
        })?;
    values.resize(len, value);
    Ok(values)
}
