//! `usdeform._core.Model`: the deformation model, converted and checked once, then passed to
//! every kernel (as pydantic-core's SchemaValidator is built once and called many times).

use numpy::{PyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::bspline::BSplineModel;
use usdeform_core::field::SpatialModel;
use usdeform_core::model::{Coupling, DeformationModel};
use usdeform_core::quadratic::QuadraticModel;
use usdeform_core::terms::{ForceTerms, Integral, IntegrationVariable, Normalization};

use crate::conversion::{as_slice, check_grid, field_array, profile_from, typed_array};
use crate::errors::{input_error, run_kernel, CoreError};

fn normalization_from(py: Python<'_>, normalization: &Bound<'_, PyAny>) -> PyResult<Normalization> {
    let normalization = typed_array::<f64>(py, "normalization", normalization, &[Some(6)], "(6,)")?;
    Ok(Normalization::from_slice(as_slice("normalization", &normalization)?).map_err(CoreError)?)
}

/// The integral of the rate: `integration` "force" (paper eq. 8) or "displacement" (over lambda).
fn integral_from(n_intervals: usize, integration: &str) -> PyResult<Integral> {
    let variable = match integration {
        "force" => IntegrationVariable::Force,
        "displacement" => IntegrationVariable::ProbeDisplacement,
        other => {
            return Err(input_error(format!(
                "integration: expected 'force' or 'displacement', got {other:?}"
            )))
        }
    };
    Ok(Integral {
        variable,
        n_intervals,
    })
}

fn coupling_from(coupling: &str) -> PyResult<Coupling> {
    match coupling {
        "stiffness" => Ok(Coupling::Stiffness),
        "force" => Ok(Coupling::Force),
        other => Err(input_error(format!(
            "coupling: expected 'stiffness' or 'force', got {other:?}"
        ))),
    }
}

/// The spatial basis `basis` ("quadratic": coefficients (2, 10), the paper's regression;
/// "bspline": (2, 3, n_y, n_x), component, force term 1/h/h^2, y and x function).
fn spatial_from(
    py: Python<'_>,
    basis: &str,
    coefficients: &Bound<'_, PyAny>,
    normalization: Normalization,
) -> PyResult<SpatialModel> {
    let (expected, layout): (&[Option<usize>], &str) = match basis {
        "quadratic" => (&[Some(2), Some(10)], "(2, 10) for the quadratic basis"),
        "bspline" => (
            &[Some(2), Some(3), None, None],
            "(2, 3, n_y, n_x) with n_y, n_x >= 4 for the B-spline basis",
        ),
        other => {
            return Err(input_error(format!(
                "basis: expected 'quadratic' or 'bspline', got {other:?}"
            )))
        }
    };
    let array = typed_array::<f64>(py, "coefficients", coefficients, expected, layout)?;
    let values = as_slice("coefficients", &array)?;
    let model = if basis == "bspline" {
        let shape = array.shape();
        BSplineModel::new(values, shape[2], shape[3], normalization).map(SpatialModel::BSpline)
    } else {
        QuadraticModel::new(values, normalization).map(SpatialModel::Quadratic)
    };
    Ok(model.map_err(CoreError)?)
}

/// A fitted deformation model: spatial basis and coefficients, normalisation, the integral of the
/// rate, the force/stiffness coupling and the frame shape it was fitted on.
#[pyclass(frozen, module = "usdeform._core")]
pub struct Model {
    pub inner: DeformationModel,
    basis: &'static str,
}

#[pymethods]
impl Model {
    #[new]
    #[pyo3(signature = (basis, coefficients, normalization, *, n_intervals, coupling, integration, frame_shape))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        basis: &str,
        coefficients: &Bound<'_, PyAny>,
        normalization: &Bound<'_, PyAny>,
        n_intervals: usize,
        coupling: &str,
        integration: &str,
        frame_shape: (usize, usize),
    ) -> PyResult<Self> {
        let normalization = normalization_from(py, normalization)?;
        let spatial = spatial_from(py, basis, coefficients, normalization)?;
        let inner = DeformationModel::new(
            spatial,
            integral_from(n_intervals, integration)?,
            coupling_from(coupling)?,
            [frame_shape.0, frame_shape.1],
        )
        .map_err(CoreError)?;
        let basis = if basis == "bspline" {
            "bspline"
        } else {
            "quadratic"
        };
        Ok(Model { inner, basis })
    }

    #[getter]
    fn basis(&self) -> &'static str {
        self.basis
    }

    #[getter]
    fn frame_shape(&self) -> (usize, usize) {
        let [rows, cols] = self.inner.frame_shape;
        (rows, cols)
    }

    #[getter]
    fn n_intervals(&self) -> usize {
        self.inner.integral.n_intervals
    }

    #[getter]
    fn coupling(&self) -> &'static str {
        match self.inner.coupling {
            Coupling::Stiffness => "stiffness",
            Coupling::Force => "force",
        }
    }

    #[getter]
    fn integration(&self) -> &'static str {
        match self.inner.integral.variable {
            IntegrationVariable::Force => "force",
            IntegrationVariable::ProbeDisplacement => "displacement",
        }
    }

    /// The regression rate d(x, y, h) on a rows x cols grid, shape (2, rows, cols), pixels per unit
    /// normalised force (paper eq. 7).
    fn rate<'py>(
        &self,
        py: Python<'py>,
        h_mm: f64,
        rows: usize,
        cols: usize,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        check_grid(rows, cols)?;
        let field = run_kernel(py, None, || self.inner.rate_field(h_mm, rows, cols))?;
        field_array(py, field, rows, cols)
    }

    /// The displacement D(x, y, F) in pixels on a rows x cols grid, shape (2, rows, cols), with the
    /// model's coupling applied to `profile` (paper eq. 8).
    fn displacement<'py>(
        &self,
        py: Python<'py>,
        force_n: f64,
        profile: (f64, f64, f64),
        rows: usize,
        cols: usize,
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        check_grid(rows, cols)?;
        let profile = profile_from(profile);
        let field = run_kernel(py, None, || {
            self.inner.displacement_field(force_n, &profile, rows, cols)
        })?;
        field_array(py, field, rows, cols)
    }

    /// The normalised integrals of 1, h and h^2 from 0 to `force_n` with the model's coupling.
    fn force_integrals(
        &self,
        py: Python<'_>,
        force_n: f64,
        profile: (f64, f64, f64),
    ) -> PyResult<(f64, f64, f64)> {
        let profile = self.inner.coupled_profile(&profile_from(profile));
        let inner = &self.inner;
        let terms = run_kernel(py, None, || {
            ForceTerms::integrated(
                force_n,
                &profile,
                inner.integral,
                inner.spatial.normalization(),
                0,
            )
        })?;
        Ok((terms.one, terms.h, terms.h2))
    }
}

/// The three normalised force integrals (of 1, h and h^2) from 0 to `force_n` (paper eq. 8), for
/// fitting, before a model exists.
#[pyfunction]
#[pyo3(signature = (force_n, profile, normalization, n_intervals, integration="force"))]
pub fn force_integrals(
    py: Python<'_>,
    force_n: f64,
    profile: (f64, f64, f64),
    normalization: &Bound<'_, PyAny>,
    n_intervals: usize,
    integration: &str,
) -> PyResult<(f64, f64, f64)> {
    let integral = integral_from(n_intervals, integration)?;
    let normalization = normalization_from(py, normalization)?;
    let profile = profile_from(profile);
    let terms = run_kernel(py, None, || {
        ForceTerms::integrated(force_n, &profile, integral, &normalization, 0)
    })?;
    Ok((terms.one, terms.h, terms.h2))
}

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Model>()?;
    module.add_function(wrap_pyfunction!(force_integrals, module)?)?;
    Ok(())
}
