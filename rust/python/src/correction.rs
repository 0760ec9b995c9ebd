//! `warp_frames`: frames warped back to zero force, and the panic hook the tests use.

use pyo3::prelude::*;

use usdeform_core::warp::{self, Pixel};
use usdeform_core::KernelError;

use crate::conversion::{frames_array, with_frame_stack, FrameInputs, Frames};
use crate::errors::run_kernel;
use crate::model::Model;

/// Warp frames back to zero force: output pixel (x, y) is the input frame sampled bilinearly at
/// (x, y) + D(x, y, F_frame); samples outside the frame give `fill`. Same dtype as the input.
#[pyfunction]
#[pyo3(signature = (frames, forces, profiles, model, *, fill=0.0, threads=None))]
fn warp_frames<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    forces: &Bound<'py, PyAny>,
    profiles: &Bound<'py, PyAny>,
    model: &Bound<'py, Model>,
    fill: f64,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let frames = Frames::extract(py, frames)?;
    let inputs = FrameInputs::extract(py, forces, profiles)?;
    let correction = inputs.correction(&model.get().inner)?;
    let shape = frames.shape();
    frames.check_fill(fill)?;
    with_frame_stack!(&frames, |stack| {
        let out = run_kernel(py, threads, || {
            warp::warp_frames(&stack, &correction, Pixel::from_f64(fill))
        })?;
        frames_array(py, out, shape)
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
    module.add_function(wrap_pyfunction!(_panic_for_tests, module)?)?;
    Ok(())
}
