//! Binding of the tracker's affine Lucas-Kanade refinement (`usdeform_core::affine_lk`):
//! `affine_lucas_kanade`.

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::affine_lk::{self, AffineSettings, Image, TrackingImages};

use crate::conversion::{as_slice, typed_array};
use crate::errors::{input_error, run_kernel};

/// (x, y) points of an (N, 2) float32 array.
fn points(values: &[f32]) -> Vec<[f32; 2]> {
    values
        .chunks_exact(2)
        .map(|point| [point[0], point[1]])
        .collect()
}

/// A count the caller passed as a Python int: an error naming `name` if it is negative.
fn count(name: &str, value: i64, expected: &str) -> PyResult<usize> {
    usize::try_from(value)
        .map_err(|_| input_error(format!("{name}: expected {expected}, got {value}")))
}

/// Where the `window_px` (width, height) window of `before` around each of the (N, 2) float32 points
/// `start` (x, y) lies in `after`, with an affine warp of the window, starting at `initial` (N, 2):
/// inverse compositional Gauss-Newton on zero-mean windows, cut where they leave either frame, until
/// both components of the step's translation are below `epsilon` pixels or after `max_iterations`.
/// `before`, its gradients `gradient_x`, `gradient_y` (pixel units) and `after` are (rows, cols)
/// float32, sampled bilinearly (edge replicated). Returns the tracked points (N, 2) float32
/// (`initial` where not ok), ok (N,) bool and the correlation of each window with its match (N,)
/// float64 (0 where not ok).
#[pyfunction]
#[pyo3(signature = (
    before, gradient_x, gradient_y, after, start, initial, window_px, *,
    max_iterations=30, epsilon=0.01, threads=None
))]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn affine_lucas_kanade<'py>(
    py: Python<'py>,
    before: &Bound<'py, PyAny>,
    gradient_x: &Bound<'py, PyAny>,
    gradient_y: &Bound<'py, PyAny>,
    after: &Bound<'py, PyAny>,
    start: &Bound<'py, PyAny>,
    initial: &Bound<'py, PyAny>,
    window_px: (i64, i64),
    max_iterations: i64,
    epsilon: f64,
    threads: Option<usize>,
) -> PyResult<(
    Bound<'py, PyAny>,
    Bound<'py, PyArray1<bool>>,
    Bound<'py, PyArray1<f64>>,
)> {
    let before = typed_array::<f32>(
        py,
        "before",
        before,
        &[None, None],
        "(rows, cols) of float32",
    )?;
    let shape = [before.shape()[0], before.shape()[1]];
    let layout = format!("{shape:?} of float32, as before");
    let image_like = |name: &str, object: &Bound<'py, PyAny>| {
        typed_array::<f32>(py, name, object, &shape.map(Some), &layout)
    };
    let (gradient_x, gradient_y, after) = (
        image_like("gradient_x", gradient_x)?,
        image_like("gradient_y", gradient_y)?,
        image_like("after", after)?,
    );
    let start: PyReadonlyArrayDyn<'py, f32> = typed_array(
        py,
        "start",
        start,
        &[None, Some(2)],
        "(N, 2) of float32 (x, y)",
    )?;
    let n = start.shape()[0];
    let initial: PyReadonlyArrayDyn<'py, f32> = typed_array(
        py,
        "initial",
        initial,
        &[Some(n), Some(2)],
        &format!("({n}, 2) of float32 (x, y), as start"),
    )?;
    let window_sides = "odd (width, height) sides >= 3";
    let settings = AffineSettings {
        window: [
            count("window_px", window_px.0, window_sides)?,
            count("window_px", window_px.1, window_sides)?,
        ],
        max_iterations: count("max_iterations", max_iterations, "an integer >= 0")?,
        epsilon,
    };
    let [rows, cols] = shape;
    let image = |name, array| -> PyResult<Image<'_>> {
        Ok(Image {
            pixels: as_slice(name, array)?,
            rows,
            cols,
        })
    };
    let images = TrackingImages {
        before: image("before", &before)?,
        gradient_x: image("gradient_x", &gradient_x)?,
        gradient_y: image("gradient_y", &gradient_y)?,
        after: image("after", &after)?,
    };
    let (start, initial) = (
        points(as_slice("start", &start)?),
        points(as_slice("initial", &initial)?),
    );
    let tracks = run_kernel(py, threads, || {
        affine_lk::affine_lucas_kanade(&images, &start, &initial, &settings)
    })?;
    let tracked: Vec<f32> = tracks.tracked.into_iter().flatten().collect();
    Ok((
        PyArray1::from_vec(py, tracked)
            .reshape(vec![n, 2])?
            .into_any(),
        PyArray1::from_vec(py, tracks.ok),
        PyArray1::from_vec(py, tracks.correlation),
    ))
}

/// Adds the tracking functions to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(affine_lucas_kanade, module)?)?;
    Ok(())
}
