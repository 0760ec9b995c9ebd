//! Bindings of the tracker's kernels: the affine Lucas-Kanade refinement (`usdeform_core::affine_lk`),
//! `affine_lucas_kanade`, and the patch kernels (`usdeform_core::patch_match`), `patch_correlation`
//! and `block_match`.

use numpy::{Element, PyArray1, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::affine_lk::{self, AffineSettings, Image, TrackingImages};
use usdeform_core::patch_match;

use crate::conversion::{as_slice, typed_array};
use crate::errors::{input_error, run_kernel};

/// (x, y) points of an (N, 2) float32 array.
fn points(values: &[f32]) -> Points {
    values
        .chunks_exact(2)
        .map(|point| [point[0], point[1]])
        .collect()
}

/// (x, y) points, one per row of an (N, 2) float32 array.
type Points = Vec<[f32; 2]>;

/// The (N, 2) float32 (x, y) points `first` and the as many points `second`, each with its name.
fn point_pairs<'py>(
    py: Python<'py>,
    (first_name, first): (&str, &Bound<'py, PyAny>),
    (second_name, second): (&str, &Bound<'py, PyAny>),
) -> PyResult<(Points, Points)> {
    let first: PyReadonlyArrayDyn<'py, f32> = typed_array(
        py,
        first_name,
        first,
        &[None, Some(2)],
        "(N, 2) of float32 (x, y)",
    )?;
    let n = first.shape()[0];
    let layout = format!("({n}, 2) of float32 (x, y), as {first_name}");
    let second: PyReadonlyArrayDyn<'py, f32> =
        typed_array(py, second_name, second, &[Some(n), Some(2)], &layout)?;
    Ok((
        points(as_slice(first_name, &first)?),
        points(as_slice(second_name, &second)?),
    ))
}

/// The (width, height) of `window_px`, an error naming it if a side is negative.
fn window_sides(window_px: (i64, i64), expected: &str) -> PyResult<[usize; 2]> {
    Ok([
        count("window_px", window_px.0, expected)?,
        count("window_px", window_px.1, expected)?,
    ])
}

/// The (rows, cols) frames `before` and `after` of `dtype` (`T`), `after` of `before`'s shape.
fn frame_pair<'py, T: Element>(
    py: Python<'py>,
    before: &Bound<'py, PyAny>,
    after: &Bound<'py, PyAny>,
    dtype: &str,
) -> PyResult<[PyReadonlyArrayDyn<'py, T>; 2]> {
    let before = typed_array::<T>(
        py,
        "before",
        before,
        &[None, None],
        &format!("(rows, cols) of {dtype}"),
    )?;
    let shape = [before.shape()[0], before.shape()[1]];
    let after = typed_array::<T>(
        py,
        "after",
        after,
        &shape.map(Some),
        &format!("{shape:?} of {dtype}, as before"),
    )?;
    Ok([before, after])
}

/// The (rows, cols) frame `array` (named `name` in errors) as a kernel image.
fn image<'a, T: Element>(
    name: &str,
    array: &'a PyReadonlyArrayDyn<'_, T>,
) -> PyResult<patch_match::Image<'a, T>> {
    Ok(patch_match::Image {
        pixels: as_slice(name, array)?,
        rows: array.shape()[0],
        cols: array.shape()[1],
    })
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
    let (start, initial) = point_pairs(py, ("start", start), ("initial", initial))?;
    let n = start.len();
    let settings = AffineSettings {
        window: window_sides(window_px, "odd (width, height) sides >= 3")?,
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

/// The normalised correlation (N,) float64 of the `window_px` (width, height) patches of the
/// (rows, cols) uint8 frames `before` around the (N, 2) float32 points `start` (x, y) and `after`
/// around `end`, each pixel sampled bilinearly and rounded to 8 bits as OpenCV's `remap`
/// (`INTER_LINEAR`, `BORDER_REPLICATE`) samples it; zero-mean patches, 0 where one is flat.
#[pyfunction]
#[pyo3(signature = (before, after, start, end, window_px, *, threads=None))]
#[allow(clippy::too_many_arguments)]
fn patch_correlation<'py>(
    py: Python<'py>,
    before: &Bound<'py, PyAny>,
    after: &Bound<'py, PyAny>,
    start: &Bound<'py, PyAny>,
    end: &Bound<'py, PyAny>,
    window_px: (i64, i64),
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyArray1<f64>>> {
    let [before, after] = frame_pair::<u8>(py, before, after, "uint8")?;
    let (start, end) = point_pairs(py, ("start", start), ("end", end))?;
    let window = window_sides(window_px, "odd (width, height) sides >= 1")?;
    let (before, after) = (image("before", &before)?, image("after", &after)?);
    let correlation = run_kernel(py, threads, || {
        patch_match::patch_correlation(&before, &after, &start, &end, window)
    })?;
    Ok(PyArray1::from_vec(py, correlation))
}

/// Block matching of the (rows, cols) float32 frames `before` and `after`: the `patch` x `patch`
/// blocks of `before` on nodes `spacing` apart (from `patch // 2`, blocks inside the frame) searched
/// over +-`search` pixels of `after` (edge replicated) by normalised correlation of zero-mean blocks
/// (OpenCV's `TM_CCOEFF_NORMED`), the peak refined by a parabola along each axis. Returns the flow
/// (node rows, node cols, 2) float32 (dx, dy), the peak correlation (node rows, node cols) float32
/// and whether the peak lies on the edge of the search range (node rows, node cols) bool.
#[pyfunction]
#[pyo3(signature = (before, after, patch, spacing, search, *, threads=None))]
#[allow(clippy::type_complexity)]
fn block_match<'py>(
    py: Python<'py>,
    before: &Bound<'py, PyAny>,
    after: &Bound<'py, PyAny>,
    patch: i64,
    spacing: i64,
    search: i64,
    threads: Option<usize>,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let [before, after] = frame_pair::<f32>(py, before, after, "float32")?;
    let patch = count("patch", patch, "an odd number of pixels >= 1")?;
    let spacing = count("spacing", spacing, "a positive number of pixels")?;
    let search = count("search", search, "a number of pixels >= 0")?;
    let (before, after) = (image("before", &before)?, image("after", &after)?);
    let ((node_rows, node_cols), matches) = run_kernel(py, threads, || {
        patch_match::block_match(&before, &after, patch, spacing, search)
    })?;
    let flow: Vec<f32> = matches.flow.into_iter().flatten().collect();
    Ok((
        PyArray1::from_vec(py, flow)
            .reshape(vec![node_rows, node_cols, 2])?
            .into_any(),
        PyArray1::from_vec(py, matches.peak)
            .reshape(vec![node_rows, node_cols])?
            .into_any(),
        PyArray1::from_vec(py, matches.on_edge)
            .reshape(vec![node_rows, node_cols])?
            .into_any(),
    ))
}

/// Adds the tracking functions to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(affine_lucas_kanade, module)?)?;
    module.add_function(wrap_pyfunction!(patch_correlation, module)?)?;
    module.add_function(wrap_pyfunction!(block_match, module)?)?;
    Ok(())
}
