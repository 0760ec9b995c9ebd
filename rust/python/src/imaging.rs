//! Binding of the B-mode simulator's bilinear splat (`usdeform_core::splat`): `splat_bilinear`.

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::splat::{self, SplatGrids};

use crate::conversion::{as_slice, type_name, typed_array};
use crate::errors::{input_error, run_kernel};

/// The real and imaginary (rows, cols) float32 grids of the points (`fine_col`, `fine_row`) (grid
/// cells, fractional; (n,) float64) with the complex weights `weight_real + i weight_imag` ((n,)
/// float64) splatted bilinearly onto a grid of `grid_shape` (rows, cols) cells: the sums of
/// `np.bincount` over the four corners of all points, cast to float32, bit for bit. Points whose
/// four cells are not all on the grid are left out; every value must be finite. Without the GIL.
#[pyfunction]
#[pyo3(signature = (fine_col, fine_row, weight_real, weight_imag, grid_shape))]
#[allow(clippy::type_complexity)]
fn splat_bilinear<'py>(
    py: Python<'py>,
    fine_col: &Bound<'py, PyAny>,
    fine_row: &Bound<'py, PyAny>,
    weight_real: &Bound<'py, PyAny>,
    weight_imag: &Bound<'py, PyAny>,
    grid_shape: &Bound<'py, PyAny>,
) -> PyResult<(Bound<'py, PyArrayDyn<f32>>, Bound<'py, PyArrayDyn<f32>>)> {
    let fine_col = typed_array::<f64>(py, "fine_col", fine_col, &[None], "(n,) of float64")?;
    let n = fine_col.shape()[0];
    let layout = format!("({n},) of float64, as fine_col");
    let like_fine_col = |name: &str, object: &Bound<'py, PyAny>| {
        typed_array::<f64>(py, name, object, &[Some(n)], &layout)
    };
    let (fine_row, weight_real, weight_imag) = (
        like_fine_col("fine_row", fine_row)?,
        like_fine_col("weight_real", weight_real)?,
        like_fine_col("weight_imag", weight_imag)?,
    );
    let (rows, cols) = grid_shape
        .extract::<(i64, i64)>()
        .ok()
        .and_then(|(rows, cols)| Some((usize::try_from(rows).ok()?, usize::try_from(cols).ok()?)))
        .filter(|&(rows, cols)| rows > 0 && cols > 0)
        .ok_or_else(|| {
            let got = grid_shape
                .repr()
                .map(|r| r.to_string())
                .unwrap_or_else(|_| type_name(grid_shape));
            input_error(format!(
                "grid_shape: expected (rows, cols), two positive integers, got {got}"
            ))
        })?;
    let (fine_col, fine_row, weight_real, weight_imag) = (
        as_slice("fine_col", &fine_col)?,
        as_slice("fine_row", &fine_row)?,
        as_slice("weight_real", &weight_real)?,
        as_slice("weight_imag", &weight_imag)?,
    );
    let SplatGrids { real, imag } = run_kernel(py, None, || {
        splat::splat_bilinear(fine_col, fine_row, weight_real, weight_imag, [rows, cols])
    })?;
    Ok((
        PyArray1::from_vec(py, real).reshape(vec![rows, cols])?,
        PyArray1::from_vec(py, imag).reshape(vec![rows, cols])?,
    ))
}

/// Adds the imaging functions to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(splat_bilinear, module)?)?;
    Ok(())
}
