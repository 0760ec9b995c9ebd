//! `usdeform._core.Accumulator`: frames inserted into a voxel volume, batch after batch.

use pyo3::prelude::*;

use usdeform_core::compound::{self, Compounding, Interpolation};
use usdeform_core::warp::Pixel;

use crate::conversion::{
    as_slice, frames_array, poses_from, typed_array, with_frame_stack, FrameInputs, Frames,
};
use crate::errors::{input_error, run_kernel, CoreError};
use crate::model::Model;

fn parse_interpolation(name: &str) -> PyResult<Interpolation> {
    match name {
        "nearest" => Ok(Interpolation::Nearest),
        "linear" => Ok(Interpolation::Linear),
        other => Err(input_error(format!(
            "interpolation: expected 'nearest' or 'linear', got {other:?}"
        ))),
    }
}

fn parse_compounding(name: &str) -> PyResult<Compounding> {
    match name {
        "mean" => Ok(Compounding::Mean),
        "max" => Ok(Compounding::Maximum),
        "latest" => Ok(Compounding::Latest),
        other => Err(input_error(format!(
            "compounding: expected 'mean', 'max' or 'latest', got {other:?}"
        ))),
    }
}

/// A voxel accumulator that frames are inserted into, batch after batch (PLUS-style compounding).
#[pyclass(module = "usdeform._core")]
struct Accumulator {
    inner: compound::Accumulator,
}

#[pymethods]
impl Accumulator {
    /// `shape` (z, y, x) voxels, `index_to_world` (4, 4) mm; fails before allocating beyond `max_bytes`.
    #[new]
    #[pyo3(signature = (shape, index_to_world, interpolation, compounding, max_bytes))]
    fn new(
        py: Python<'_>,
        shape: (usize, usize, usize),
        index_to_world: &Bound<'_, PyAny>,
        interpolation: &str,
        compounding: &str,
        max_bytes: u128,
    ) -> PyResult<Self> {
        let index_to_world = typed_array::<f64>(
            py,
            "index_to_world",
            index_to_world,
            &[Some(4), Some(4)],
            "(4, 4)",
        )?;
        let inner = compound::Accumulator::new(
            [shape.0, shape.1, shape.2],
            as_slice("index_to_world", &index_to_world)?,
            parse_interpolation(interpolation)?,
            parse_compounding(compounding)?,
            max_bytes,
        )
        .map_err(CoreError)?;
        Ok(Accumulator { inner })
    }

    /// Insert frames (n_frames, rows, cols) at their `image_to_world` poses (n_frames, 4, 4), mm.
    #[pyo3(signature = (frames, image_to_world, *, threads=None))]
    fn insert(
        &mut self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        threads: Option<usize>,
    ) -> PyResult<()> {
        let frames = Frames::extract(py, frames)?;
        let poses = poses_from(py, image_to_world, frames.shape()[0])?;
        let poses = as_slice("image_to_world", &poses)?;
        let inner = &mut self.inner;
        with_frame_stack!(&frames, |stack| run_kernel(py, threads, || inner
            .insert(&stack, poses)))
    }

    /// Warp frames back to zero force (as `warp_frames`) and insert them, without keeping the
    /// corrected frames.
    #[pyo3(signature = (frames, image_to_world, forces, profiles, model, *, fill=0.0, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn insert_corrected(
        &mut self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        forces: &Bound<'_, PyAny>,
        profiles: &Bound<'_, PyAny>,
        model: &Bound<'_, Model>,
        fill: f64,
        threads: Option<usize>,
    ) -> PyResult<()> {
        let frames = Frames::extract(py, frames)?;
        let poses = poses_from(py, image_to_world, frames.shape()[0])?;
        let poses = as_slice("image_to_world", &poses)?;
        let inputs = FrameInputs::extract(py, forces, profiles)?;
        let correction = inputs.correction(&model.get().inner)?;
        frames.check_fill(fill)?;
        let inner = &mut self.inner;
        with_frame_stack!(&frames, |stack| {
            run_kernel(py, threads, || {
                inner.insert_corrected(&stack, poses, &correction, Pixel::from_f64(fill))
            })
        })
    }

    /// The compounded image and the coverage weight, both float32 (z, y, x).
    fn volume<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let shape = self.inner.shape();
        let inner = &self.inner;
        let (image, weight) = run_kernel(py, None, || Ok(inner.volume()))?;
        Ok((
            frames_array(py, image, shape)?,
            frames_array(py, weight, shape)?,
        ))
    }

    #[getter]
    fn frames_inserted(&self) -> usize {
        self.inner.frames_inserted()
    }

    #[getter]
    fn shape(&self) -> (usize, usize, usize) {
        let [z, y, x] = self.inner.shape();
        (z, y, x)
    }
}

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Accumulator>()?;
    module.add("BYTES_PER_VOXEL", compound::BYTES_PER_VOXEL)?;
    Ok(())
}
