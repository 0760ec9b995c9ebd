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

/// How the rate is integrated: over which variable. `n_intervals` is the force-interval count a
/// model file records; the quadratic stiffness profile's integrals are closed-form, so it is
/// checked (1 to [`MAX_INTERVALS`]) and kept, not used.
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
    /// `h = f / k(f)` (paper eq. 8), in closed form for the profile's stiffness (see
    /// [`force_integral`]); exact and O(1), whatever `integral.n_intervals`. `frame` only labels
    /// errors.
    pub fn integrated(
        force_n: f64,
        profile: &StiffnessProfile,
        integral: Integral,
        normalization: &Normalization,
        frame: usize,
    ) -> Result<ForceTerms> {
        check_intervals(integral.n_intervals)?;
        if !force_n.is_finite() {
            return Err(KernelError::NonFinite {
                argument: "forces",
                index: frame,
            });
        }
        profile.check_finite(frame)?;
        // Integrals over [0, F] of f^p / k^(p + w) df for p = 0, 1, 2, where w = 0 integrates over
        // force and w = 1 over probe displacement (dlambda = df / k).
        let extra_power = match integral.variable {
            IntegrationVariable::Force => 0,
            IntegrationVariable::ProbeDisplacement => 1,
        };
        let term = |power: u32| {
            force_integral(profile, force_n, power, power + extra_power).ok_or(
                KernelError::OutsideRisingBranch {
                    frame,
                    force: force_n,
                },
            )
        };
        let (integral_1, integral_h, integral_h2) = (term(0)?, term(1)?, term(2)?);
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

/// Most force intervals a model may ask for (they are kept for models written before the integrals
/// became closed-form; a larger count is a mistake).
pub const MAX_INTERVALS: usize = 1_000_000;

/// An error unless `n_intervals` is in `1..=MAX_INTERVALS`.
pub fn check_intervals(n_intervals: usize) -> Result<()> {
    if (1..=MAX_INTERVALS).contains(&n_intervals) {
        Ok(())
    } else {
        Err(KernelError::Value {
            argument: "n_intervals",
            message: format!("expected 1 to {MAX_INTERVALS}, got {n_intervals}"),
        })
    }
}

/// `int_0^F f^p / k(f)^q df` (N^(p+1) / (N/mm)^q) in closed form, with the stiffness `k(f)` of
/// `profile`: `sqrt(c2^2 + 4 c1 (f - c3))` from the palpation start `c3` on, and `c2` below it
/// (the profile's linear continuation). None where the force range leaves the rising branch
/// (`k <= 0` somewhere in it).
///
/// On the quadratic part the integral is taken over the probe displacement `lambda`, where
/// `f = c3 + c2 lambda + c1 lambda^2` and `df = k dlambda` with `k = c2 (1 + e lambda)`,
/// `e = 2 c1 / c2`: the integrand `f^p k^(1-q)` is a polynomial over `(1 + e lambda)^b`, `b = q - 1`.
/// Where `|e lambda| < 1/4` that power is expanded in its (fast converging) binomial series, so
/// that nothing cancels as `c1 -> 0`; elsewhere it is integrated exactly in `u = 1 + e lambda`.
pub fn force_integral(profile: &StiffnessProfile, force_n: f64, p: u32, q: u32) -> Option<f64> {
    let (lower, upper, sign) = if force_n >= 0.0 {
        (0.0, force_n, 1.0)
    } else {
        (force_n, 0.0, -1.0)
    };
    let StiffnessProfile { c2, c3, .. } = *profile;
    let mut total = 0.0;
    if lower < c3 {
        // Linear continuation below the start: k = c2.
        if c2 <= 0.0 {
            return None;
        }
        let top = upper.min(c3);
        let power = (p + 1) as i32;
        total += (top.powi(power) - lower.powi(power)) / (power as f64 * c2.powi(q as i32));
    }
    if upper > c3 {
        let lambda_low = profile.lambda_at(lower.max(c3))?;
        let lambda_high = profile.lambda_at(upper)?;
        if !(c2 > 0.0 && profile.stiffness_at(lambda_high) > 0.0) {
            return None;
        }
        if lambda_low > 0.0 {
            // The curve taken from lambda_low (force and stiffness there), so that the antiderivative starts
            // at 0: from far up the curve its values at the two ends would cancel.
            let from_low = StiffnessProfile {
                c1: profile.c1,
                c2: profile.stiffness_at(lambda_low),
                c3: lower,
            };
            total += quadratic_part(&from_low, p, q, 0.0, from_low.lambda_at(upper)?);
        } else {
            total += quadratic_part(profile, p, q, lambda_low, lambda_high);
        }
    }
    Some(sign * total)
}

/// `int f(lambda)^p k(lambda)^(1-q) dlambda` over `[lambda_low, lambda_high]` (both >= 0, on the
/// rising branch, `c2 > 0`), see [`force_integral`].
fn quadratic_part(
    profile: &StiffnessProfile,
    p: u32,
    q: u32,
    lambda_low: f64,
    lambda_high: f64,
) -> f64 {
    let StiffnessProfile { c1, c2, c3 } = *profile;
    // f^p as a polynomial in lambda (coefficients ascending), times (1 + e lambda) when q = 0.
    let e = 2.0 * c1 / c2;
    let f = [c3, c2, c1];
    let mut polynomial = vec![1.0];
    for _ in 0..p {
        polynomial = multiply(&polynomial, &f);
    }
    if q == 0 {
        polynomial = multiply(&polynomial, &[1.0, e]);
    }
    let denominator_power = q.saturating_sub(1); // b: (1 + e lambda)^(-b)
    let scale = c2.powi(1 - q as i32);
    let antiderivative = |lambda: f64| -> f64 {
        if denominator_power == 0 || (e * lambda_high).abs() < 0.25 {
            series_antiderivative(&polynomial, e, denominator_power, lambda)
        } else {
            exact_antiderivative(&polynomial, e, denominator_power, lambda)
        }
    };
    scale * (antiderivative(lambda_high) - antiderivative(lambda_low))
}

fn multiply(a: &[f64], b: &[f64]) -> Vec<f64> {
    let mut product = vec![0.0; a.len() + b.len() - 1];
    for (i, x) in a.iter().enumerate() {
        for (j, y) in b.iter().enumerate() {
            product[i + j] += x * y;
        }
    }
    product
}

/// `int_0^x P(lambda) (1 + e lambda)^(-b) dlambda` for `|e x| < 1/4` (or `b = 0`): the binomial
/// series `(1 + t)^(-b) = sum_n (-1)^n C(n + b - 1, n) t^n`, b in {0, 1, 2}, summed until the terms
/// vanish (at most 40 terms: 4^-40 ~ 1e-24).
fn series_antiderivative(polynomial: &[f64], e: f64, b: u32, x: f64) -> f64 {
    let n_terms = if b == 0 { 1 } else { 40 };
    let mut total = 0.0;
    let mut e_power = 1.0; // (-e)^n
    for n in 0..n_terms {
        let binomial = match b {
            0 | 1 => 1.0,
            _ => (n + 1) as f64,
        };
        let mut term = 0.0;
        for (j, coefficient) in polynomial.iter().enumerate() {
            let power = (j + n + 1) as i32;
            term += coefficient * x.powi(power) / power as f64;
        }
        total += binomial * e_power * term;
        e_power *= -e;
        if e_power == 0.0 {
            break;
        }
    }
    total
}

/// `int_0^x P(lambda) (1 + e lambda)^(-b) dlambda` exactly in `u = 1 + e lambda` (used for
/// `|e x| >= 1/4`, where nothing cancels badly): `P((u - 1) / e) = sum_i A_i u^i`, and
/// `int_1^U u^(i - b) du / e` is a power or, for `i = b - 1`, `ln U`.
fn exact_antiderivative(polynomial: &[f64], e: f64, b: u32, x: f64) -> f64 {
    // A_i = sum_j P_j e^-j C(j, i) (-1)^(j - i).
    let mut in_u = vec![0.0; polynomial.len()];
    for (j, coefficient) in polynomial.iter().enumerate() {
        let scaled = coefficient / e.powi(j as i32);
        let mut binomial = 1.0; // C(j, i)
        for (i, a) in in_u.iter_mut().enumerate().take(j + 1) {
            let sign = if (j - i) % 2 == 0 { 1.0 } else { -1.0 };
            *a += scaled * binomial * sign;
            binomial = binomial * (j - i) as f64 / (i + 1) as f64;
        }
    }
    let t = e * x;
    let u = 1.0 + t;
    let mut total = 0.0;
    for (i, a) in in_u.iter().enumerate() {
        let exponent = i as i32 - b as i32 + 1; // of the antiderivative u^exponent / exponent
        total += a * if exponent == 0 {
            t.ln_1p()
        } else {
            (u.powi(exponent) - 1.0) / exponent as f64
        };
    }
    total / e
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
    advise_huge_pages(&values);
    values.resize(len, value);
    Ok(values)
}

/// Ask Linux to back the not yet touched allocation of `values` with transparent huge pages
/// (2 MiB) where it spans at least one: a 64 MB accumulator is otherwise faulted in 4 KiB at a
/// time, and those page faults took a third of the fused path's time (860 to 1312
/// frames/s with huge pages alone). Only the 2 MiB-aligned interior is advised; a refusal (huge
/// pages disabled) changes nothing but the speed, so the result is ignored.
fn advise_huge_pages<T>(values: &Vec<T>) {
    #[cfg(target_os = "linux")]
    {
        const HUGE_PAGE: usize = 2 << 20;
        let start = values.as_ptr() as usize;
        let end = start + values.capacity() * std::mem::size_of::<T>();
        let (first, last) = (start.next_multiple_of(HUGE_PAGE), end & !(HUGE_PAGE - 1));
        if last > first {
            // SAFETY: [first, last) lies inside the vector's allocation, and MADV_HUGEPAGE only
            // changes how the kernel backs those pages, never their contents.
            unsafe {
                libc::madvise(
                    first as *mut libc::c_void,
                    last - first,
                    libc::MADV_HUGEPAGE,
                );
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = values;
}
