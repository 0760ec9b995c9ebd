//! `warp_frames`: frames warped back to zero force; `warp_by_field`: frames warped by given fields;
//! and the panic hook the tests use.

use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;

use usdeform_core::terms::filled;
use usdeform_core::warp::{self, Pixel};
use usdeform_core::KernelError;

use crate::anchored::{anchors_from, placed, VesselPart};
use crate::conversion::{
    as_slice, frames_array, typed_array, with_frame_stack, FrameInputs, Frames,
};
use crate::errors::{frame_chunks, run_kernel, CoreError, Pool};
use crate::model::Model;

/// Warp frames back to zero force: output pixel (x, y) is the input frame sampled bilinearly at
/// (x, y) + D(x, y, F_frame); samples outside the frame give `fill`. Same dtype as the input; with
/// `return_mask`, also the validity mask (bool, True where the pixel was sampled inside its frame).
/// With `vessel` and `anchors` ((n_frames, 3) of (x, y, radius), pixels), D is the model's field
/// plus the vessel part on each frame's lumen.
#[pyfunction]
#[pyo3(signature = (frames, forces, profiles, model, *, fill=0.0, threads=None, return_mask=false, vessel=None, anchors=None))]
#[allow(clippy::too_many_arguments)]
fn warp_frames<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    forces: &Bound<'py, PyAny>,
    profiles: &Bound<'py, PyAny>,
    model: &Bound<'py, Model>,
    fill: f64,
    threads: Option<usize>,
    return_mask: bool,
    vessel: Option<&Bound<'py, VesselPart>>,
    anchors: Option<&Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyAny>> {
    let frames = Frames::extract(py, frames)?;
    let shape = frames.shape();
    let inputs = FrameInputs::extract(py, forces, profiles)?;
    let anchors = anchors_from(py, vessel, anchors, shape[0])?;
    let correction = inputs.correction(&model.get().inner, placed(vessel, &anchors))?;
    frames.check_fill(fill)?;
    let pool = Pool::new(threads)?;
    with_frame_stack!(&frames, |stack| {
        let fill = Pixel::from_f64(fill);
        let [n_frames, rows, cols] = shape;
        // Checked for all frames first, so that errors name the frame in the whole stack.
        pool.run(py, || {
            correction.frame_fields(n_frames, rows, cols).map(|_| ())
        })?;
        let mut out = filled("frames", stack.pixels.len(), fill).map_err(CoreError)?;
        let mut valid = filled("frames", stack.pixels.len(), false).map_err(CoreError)?;
        let frame_size = rows * cols;
        for chunk in frame_chunks(n_frames) {
            py.check_signals()?;
            let pixels = chunk.start * frame_size..chunk.end * frame_size;
            let (out, valid) = (&mut out[pixels.clone()], &mut valid[pixels]);
            let (chunk_stack, chunk_correction) =
                (stack.frames(chunk.clone()), correction.frames(chunk));
            pool.run(py, || {
                warp::warp_frames_into(&chunk_stack, &chunk_correction, fill, out, valid)
            })?;
        }
        let out = frames_array(py, out, shape)?;
        if return_mask {
            Ok((out, frames_array(py, valid, shape)?)
                .into_pyobject(py)?
                .into_any())
        } else {
            Ok(out)
        }
    })
}

/// Warp frames by given displacement fields: output pixel (x, y) of frame i is frame i sampled
/// bilinearly at (x, y) + displacements[i, :, y, x] (lateral, axial; pixels), as `warp_frames`
/// samples; outside gives `fill`. Returns the frames (same dtype) and the validity mask.
#[pyfunction]
#[pyo3(signature = (frames, displacements, *, fill=0.0, threads=None))]
fn warp_by_field<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    displacements: &Bound<'py, PyAny>,
    fill: f64,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let frames = Frames::extract(py, frames)?;
    let shape = frames.shape();
    let [n_frames, rows, cols] = shape;
    let displacements: PyReadonlyArrayDyn<'py, f64> = typed_array(
        py,
        "displacements",
        displacements,
        &[Some(n_frames), Some(2), Some(rows), Some(cols)],
        "(n_frames, 2, rows, cols) of float64, the frames' own",
    )?;
    frames.check_fill(fill)?;
    let pool = Pool::new(threads)?;
    with_frame_stack!(&frames, |stack| {
        let fill = Pixel::from_f64(fill);
        let field = as_slice("displacements", &displacements)?;
        let mut out = filled("frames", stack.pixels.len(), fill).map_err(CoreError)?;
        let mut valid = filled("frames", stack.pixels.len(), false).map_err(CoreError)?;
        pool.run(py, || {
            warp::warp_frames_by_field_into(&stack, field, fill, &mut out, &mut valid)
        })?;
        Ok((
            frames_array(py, out, shape)?,
            frames_array(py, valid, shape)?,
        )
            .into_pyobject(py)?
            .into_any())
    })
}

/// Panics on purpose inside a kernel run; lets the tests check that panics become InternalError.
#[pyfunction]
fn _panic_for_tests(py: Python<'_>) -> PyResult<()> {
    run_kernel(py, Some(2), || -> Result<(), KernelError> {
        panic!("deliberate panic for the tests")
    })
}

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(warp_frames, module)?)?;
    module.add_function(wrap_pyfunction!(warp_by_field, module)?)?;
    module.add_function(wrap_pyfunction!(_panic_for_tests, module)?)?;
    Ok(())
}
