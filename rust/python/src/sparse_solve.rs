//! Binding of the sparse symmetric solve (`usdeform_core::sparse_solve`): `SymmetricSolver` and
//! the factor it makes, `SymmetricFactor`.

use numpy::PyArray1;
use std::sync::Arc;

use pyo3::prelude::*;

use usdeform_core::sparse_solve::{SymmetricFactor as CoreFactor, SymmetricPattern};

use crate::conversion::{as_slice, typed_array};
use crate::errors::{input_error, run_kernel};

fn offsets(py: Python<'_>, name: &str, array: &Bound<'_, PyAny>) -> PyResult<Vec<usize>> {
    let array = typed_array::<i64>(py, name, array, &[None], "(n,) of int64")?;
    as_slice(name, &array)?
        .iter()
        .enumerate()
        .map(|(index, &value)| {
            usize::try_from(value).map_err(|_| {
                input_error(format!(
                    "{name}: expected non-negative values, got {value} at index {index}"
                ))
            })
        })
        .collect()
}

/// A symmetric sparse matrix pattern in CSC form (`indptr`, `indices`, as SciPy stores them; both
/// triangles, only the lower one read), factorised symbolically once; `solve(values, rhs)` then
/// solves `A x = rhs` for any matrix of this pattern by a sparse LDL^T, and `factorize(values)`
/// keeps that factorisation for several right-hand sides.
#[pyclass(frozen, module = "usdeform._core")]
pub struct SymmetricSolver {
    pattern: Arc<SymmetricPattern>,
}

/// The LDL^T factor of one matrix of a `SymmetricSolver`'s pattern: `solve(rhs)`.
#[pyclass(frozen, module = "usdeform._core")]
pub struct SymmetricFactor {
    factor: CoreFactor,
}

#[pymethods]
impl SymmetricFactor {
    /// The solution x (float64, n) of A x = `rhs` for the factorised A.
    fn solve<'py>(
        &self,
        py: Python<'py>,
        rhs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let rhs = typed_array::<f64>(py, "rhs", rhs, &[None], "(n,) of float64")?;
        let rhs = as_slice("rhs", &rhs)?;
        let solution = run_kernel(py, None, || self.factor.solve(rhs))?;
        Ok(PyArray1::from_vec(py, solution))
    }
}

#[pymethods]
impl SymmetricSolver {
    #[new]
    fn new(
        py: Python<'_>,
        indptr: &Bound<'_, PyAny>,
        indices: &Bound<'_, PyAny>,
    ) -> PyResult<Self> {
        let col_ptr = offsets(py, "indptr", indptr)?;
        let row_idx = offsets(py, "indices", indices)?;
        let pattern = run_kernel(py, None, || SymmetricPattern::new(col_ptr, row_idx))?;
        Ok(SymmetricSolver { pattern })
    }

    /// Rows (= columns) of the matrix.
    #[getter]
    fn size(&self) -> usize {
        self.pattern.size()
    }

    /// The solution x (float64, n) of A x = `rhs` for A with the stored entries `values`.
    fn solve<'py>(
        &self,
        py: Python<'py>,
        values: &Bound<'py, PyAny>,
        rhs: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let values = typed_array::<f64>(py, "values", values, &[None], "(nnz,) of float64")?;
        let rhs = typed_array::<f64>(py, "rhs", rhs, &[None], "(n,) of float64")?;
        let (values, rhs) = (as_slice("values", &values)?, as_slice("rhs", &rhs)?);
        let solution = run_kernel(py, None, || self.pattern.solve(values, rhs))?;
        Ok(PyArray1::from_vec(py, solution))
    }

    /// The LDL^T factorisation of A with the stored entries `values`, for solves with it.
    fn factorize(&self, py: Python<'_>, values: &Bound<'_, PyAny>) -> PyResult<SymmetricFactor> {
        let values = typed_array::<f64>(py, "values", values, &[None], "(nnz,) of float64")?;
        let values = as_slice("values", &values)?;
        let factor = run_kernel(py, None, || self.pattern.factorize(values))?;
        Ok(SymmetricFactor { factor })
    }
}

/// Adds `SymmetricSolver` to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<SymmetricSolver>()?;
    module.add_class::<SymmetricFactor>()?;
    Ok(())
}
