//! The deformation model as the kernels use it: a spatial basis, the integral of its rate, how
//! force and tissue are coupled, and the frame shape the model was fitted on. Built once per model
//! and shared by every call; the coupling is decided here and nowhere else.

use crate::error::{KernelError, Result};
use crate::field::{self, SpatialModel};
use crate::stiffness::StiffnessProfile;
use crate::terms::{check_intervals, ForceTerms, Integral};

/// How the model couples force and tissue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coupling {
    /// `h = F / k`, the paper's stiffness coupling: each frame's stiffness profile is used.
    Stiffness,
    /// `h = F` (Sun et al. 2010): every frame gets the unit profile, whatever profile it is given.
    Force,
}

/// A fitted deformation model, checked once.
#[derive(Debug, Clone, PartialEq)]
pub struct DeformationModel {
    pub spatial: SpatialModel,
    pub integral: Integral,
    pub coupling: Coupling,
    /// `[rows, cols]` of the frames the model was fitted on (its pixel normalisation refers to them).
    pub frame_shape: [usize; 2],
}

impl DeformationModel {
    pub fn new(
        spatial: SpatialModel,
        integral: Integral,
        coupling: Coupling,
        frame_shape: [usize; 2],
    ) -> Result<Self> {
        check_intervals(integral.n_intervals)?;
        if frame_shape.contains(&0) {
            return Err(KernelError::Value {
                argument: "frame_shape",
                message: format!(
                    "expected a non-empty (rows, cols), got {} x {}",
                    frame_shape[0], frame_shape[1]
                ),
            });
        }
        Ok(DeformationModel {
            spatial,
            integral,
            coupling,
            frame_shape,
        })
    }

    /// The profile the model uses for a frame given `profile`.
    pub fn coupled_profile(&self, profile: &StiffnessProfile) -> StiffnessProfile {
        match self.coupling {
            Coupling::Stiffness => *profile,
            Coupling::Force => StiffnessProfile::UNIT,
        }
    }

    /// An error unless frames of `rows x cols` pixels have the model's frame shape.
    pub fn check_frame_shape(&self, rows: usize, cols: usize) -> Result<()> {
        let [model_rows, model_cols] = self.frame_shape;
        if [rows, cols] != self.frame_shape {
            return Err(KernelError::Shape {
                argument: "frames",
                expected: format!(
                    "frames of the model's frame shape {model_rows} x {model_cols} (rows x cols)"
                ),
                got: format!("{rows} x {cols}"),
            });
        }
        Ok(())
    }

    /// The rate `d(x, y, h)` on a `rows x cols` grid, see [`field::rate_field`].
    pub fn rate_field(&self, h_mm: f64, rows: usize, cols: usize) -> Result<Vec<f64>> {
        field::rate_field(&self.spatial, h_mm, rows, cols)
    }

    /// The force terms of a frame at `force_n` (N) with the coupled `profile`; `frame` labels errors.
    pub fn frame_terms(
        &self,
        force_n: f64,
        profile: &StiffnessProfile,
        frame: usize,
    ) -> Result<ForceTerms> {
        ForceTerms::integrated(
            force_n,
            &self.coupled_profile(profile),
            self.integral,
            self.spatial.normalization(),
            frame,
        )
    }

    /// The displacement `D(x, y, F)` on a `rows x cols` grid with the coupled `profile`, see
    /// [`field::displacement_field`].
    pub fn displacement_field(
        &self,
        force_n: f64,
        profile: &StiffnessProfile,
        rows: usize,
        cols: usize,
    ) -> Result<Vec<f64>> {
        let profile = self.coupled_profile(profile);
        field::displacement_field(&self.spatial, force_n, &profile, self.integral, rows, cols)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::quadratic::QuadraticModel;
    use crate::terms::Normalization;

    fn model(coupling: Coupling) -> DeformationModel {
        let normalization = Normalization::from_slice(&[3.0, 3.0, 1.0, 1.0, 1.0, 1.0]).unwrap();
        let mut coefficients = [0.0; 20];
        coefficients[2] = 1.0; // lateral h^2 term: the displacement depends on the stiffness
        let spatial =
            SpatialModel::Quadratic(QuadraticModel::new(&coefficients, normalization).unwrap());
        DeformationModel::new(spatial, Integral::over_force(8), coupling, [4, 4]).unwrap()
    }

    #[test]
    fn force_coupling_ignores_the_profile() {
        let soft = StiffnessProfile {
            c1: 0.0,
            c2: 0.25,
            c3: 0.0,
        };
        let by_force = model(Coupling::Force);
        let by_stiffness = model(Coupling::Stiffness);
        let unit = by_force
            .displacement_field(1.0, &StiffnessProfile::UNIT, 4, 4)
            .unwrap();
        assert_eq!(by_force.displacement_field(1.0, &soft, 4, 4).unwrap(), unit);
        assert_ne!(
            by_stiffness.displacement_field(1.0, &soft, 4, 4).unwrap(),
            unit
        );
    }

    #[test]
    fn frame_shape_is_checked() {
        let model = model(Coupling::Stiffness);
        assert!(model.check_frame_shape(4, 4).is_ok());
        let err = model.check_frame_shape(8, 4).unwrap_err();
        assert!(err.to_string().contains("frame shape 4 x 4"), "{err}");
        assert!(DeformationModel::new(
            model.spatial.clone(),
            model.integral,
            Coupling::Force,
            [0, 4]
        )
        .is_err());
    }
}
