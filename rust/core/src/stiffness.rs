//! The quadratic force-displacement curve of a palpation and its dynamic stiffness (paper eqs. 4-5).

use crate::error::{KernelError, Result};

/// `F(lambda) = c1 lambda^2 + c2 lambda + c3` (N, lambda in mm); stiffness `k = 2 c1 lambda + c2` (N/mm).
///
/// `lambda = 0` is where the palpation started (possibly at a contact preload `c3 > 0`). Below it the
/// curve is extended linearly with the stiffness at the start, `F = c3 + c2 lambda`, rather than by
/// the fitted quadratic, whose curvature is not measured there and may not even reach 0 N.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StiffnessProfile {
    pub c1: f64,
    pub c2: f64,
    pub c3: f64,
}

impl StiffnessProfile {
    /// A constant stiffness of 1 N/mm through the origin: with it `h = F / k` equals `F`
    /// numerically, which turns the stiffness-based model into the force-based baseline.
    pub const UNIT: StiffnessProfile = StiffnessProfile {
        c1: 0.0,
        c2: 1.0,
        c3: 0.0,
    };

    /// Dynamic stiffness at probe displacement `lambda_mm`, N/mm (`c2` below `lambda = 0`).
    pub fn stiffness_at(&self, lambda_mm: f64) -> f64 {
        2.0 * self.c1 * lambda_mm.max(0.0) + self.c2
    }

    /// Probe displacement (mm) at which the curve reaches `force_n`, on its rising branch.
    ///
    /// Uses `2 (F - c3) / (c2 + sqrt(c2^2 + 4 c1 (F - c3)))`, which stays exact when `c1 -> 0`, and
    /// `(F - c3) / c2` below the start. Returns None where the curve never reaches `force_n` or the
    /// branch is not rising.
    pub fn lambda_at(&self, force_n: f64) -> Option<f64> {
        let excess = force_n - self.c3;
        if excess < 0.0 {
            return (self.c2 > 0.0).then(|| excess / self.c2);
        }
        let discriminant = self.c2 * self.c2 + 4.0 * self.c1 * excess;
        if discriminant < 0.0 {
            return None;
        }
        let denominator = self.c2 + discriminant.sqrt();
        if denominator <= 0.0 {
            return None;
        }
        Some(2.0 * excess / denominator)
    }

    pub fn check_finite(&self, frame: usize) -> Result<()> {
        if [self.c1, self.c2, self.c3].iter().all(|c| c.is_finite()) {
            Ok(())
        } else {
            Err(KernelError::Value {
                argument: "profiles",
                message: format!("frame {frame}: coefficients (c1, c2, c3) must be finite"),
            })
        }
    }
}
