//! NumPy arrays in and out: each argument checked (named, with the expected layout in the error).

use numpy::ndarray::Dim;
use numpy::{
    Element, PyArray, PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;

use usdeform_core::frame_correction::{Correction, PlacedVessel};
use usdeform_core::model::DeformationModel;
use usdeform_core::stiffness::StiffnessProfile;
use usdeform_core::warp::{FrameStack, Pixel};

use crate::errors::{input_error, CoreError};

/// A C-contiguous array of element `T` with `ndim` dimensions, each checked against `expected`
/// (None: any length). `layout` describes the expected shape in error messages.
pub fn typed_array<'py, T: Element>(
    py: Python<'py>,
    name: &str,
    object: &Bound<'py, PyAny>,
    expected: &[Option<usize>],
    layout: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let untyped = object.cast::<PyUntypedArray>().map_err(|_| {
        input_error(format!(
            "{name}: expected a numpy array {layout}, got {}",
            type_name(object)
        ))
    })?;
    let array = object.cast::<PyArrayDyn<T>>().map_err(|_| {
        let wanted = T::get_dtype(py)
            .str()
            .map(|s| s.to_string())
            .unwrap_or_default();
        let got = untyped
            .dtype()
            .str()
            .map(|s| s.to_string())
            .unwrap_or_default();
        input_error(format!("{name}: expected dtype {wanted}, got {got}"))
    })?;
    let shape = array.shape();
    let shape_ok = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(&n, e)| e.is_none_or(|e| e == n));
    if !shape_ok {
        return Err(input_error(format!(
            "{name}: expected shape {layout}, got {shape:?}"
        )));
    }
    if !array.is_c_contiguous() {
        return Err(input_error(format!(
            "{name}: expected a C-contiguous array"
        )));
    }
    Ok(array.readonly())
}

pub fn type_name(object: &Bound<'_, PyAny>) -> String {
    object
        .get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "an unknown type".into())
}

pub fn as_slice<'a, T: Element>(
    name: &str,
    array: &'a PyReadonlyArrayDyn<'_, T>,
) -> PyResult<&'a [T]> {
    array
        .as_slice()
        .map_err(|_| input_error(format!("{name}: expected a C-contiguous array")))
}

/// A `(c1, c2, c3)` tuple as a profile.
pub fn profile_from(profile: (f64, f64, f64)) -> StiffnessProfile {
    StiffnessProfile {
        c1: profile.0,
        c2: profile.1,
        c3: profile.2,
    }
}

fn profiles_from(py: Python<'_>, profiles: &Bound<'_, PyAny>) -> PyResult<Vec<StiffnessProfile>> {
    let profiles = typed_array::<f64>(
        py,
        "profiles",
        profiles,
        &[None, Some(3)],
        "(n_frames, 3) of (c1, c2, c3)",
    )?;
    Ok(as_slice("profiles", &profiles)?
        .chunks(3)
        .map(|c| profile_from((c[0], c[1], c[2])))
        .collect())
}

/// A field of `2 * rows * cols` values as an array (2, rows, cols).
pub fn field_array<'py>(
    py: Python<'py>,
    values: Vec<f64>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    PyArray1::from_vec(py, values).reshape(vec![2, rows, cols])
}

pub fn check_grid(rows: usize, cols: usize) -> PyResult<()> {
    if rows == 0 || cols == 0 {
        return Err(input_error(format!(
            "rows, cols: expected a non-empty pixel grid, got {rows} x {cols}"
        )));
    }
    Ok(())
}

/// The frames of a call: uint8 or float32, (n_frames, rows, cols).
pub enum Frames<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    F32(PyReadonlyArrayDyn<'py, f32>),
}

const FRAMES_LAYOUT: &str = "(n_frames, rows, cols) of uint8 or float32";

impl<'py> Frames<'py> {
    pub fn extract(py: Python<'py>, frames: &Bound<'py, PyAny>) -> PyResult<Self> {
        let expected = [None, None, None];
        if frames.cast::<PyArrayDyn<f32>>().is_ok() {
            Ok(Frames::F32(typed_array(
                py,
                "frames",
                frames,
                &expected,
                FRAMES_LAYOUT,
            )?))
        } else if frames.cast::<PyArrayDyn<u8>>().is_ok() {
            Ok(Frames::U8(typed_array(
                py,
                "frames",
                frames,
                &expected,
                FRAMES_LAYOUT,
            )?))
        } else {
            let dtype = frames
                .cast::<PyUntypedArray>()
                .map(|a| a.dtype().str().map(|s| s.to_string()).unwrap_or_default())
                .unwrap_or_else(|_| type_name(frames));
            Err(input_error(format!(
                "frames: expected an array {FRAMES_LAYOUT}, got {dtype}"
            )))
        }
    }

    pub fn shape(&self) -> [usize; 3] {
        let shape = match self {
            Frames::U8(a) => a.shape(),
            Frames::F32(a) => a.shape(),
        };
        [shape[0], shape[1], shape[2]]
    }

    /// An error unless `fill` is finite (and within [0, 255] for uint8 frames).
    pub fn check_fill(&self, fill: f64) -> PyResult<()> {
        let is_u8 = matches!(self, Frames::U8(_));
        if !fill.is_finite() || (is_u8 && !(0.0..=255.0).contains(&fill)) {
            let range = if is_u8 {
                " in [0, 255] for uint8 frames"
            } else {
                ""
            };
            return Err(input_error(format!(
                "fill: expected a finite value{range}, got {fill}"
            )));
        }
        Ok(())
    }
}

pub fn stack<'a, P: Pixel + Element>(
    array: &'a PyReadonlyArrayDyn<'_, P>,
) -> PyResult<FrameStack<'a, P>> {
    let shape = array.shape();
    Ok(
        FrameStack::new(as_slice("frames", array)?, shape[0], shape[1], shape[2])
            .map_err(CoreError)?,
    )
}

/// Evaluate `$body` with `$stack` bound to the frames' [`FrameStack`], whichever pixel type they hold.
macro_rules! with_frame_stack {
    ($frames:expr, |$stack:ident| $body:expr) => {
        match $frames {
            $crate::conversion::Frames::U8(array) => {
                let $stack = $crate::conversion::stack(array)?;
                $body
            }
            $crate::conversion::Frames::F32(array) => {
                let $stack = $crate::conversion::stack(array)?;
                $body
            }
        }
    };
}
pub(crate) use with_frame_stack;

pub fn frames_array<'py, P: Element>(
    py: Python<'py>,
    pixels: Vec<P>,
    shape: [usize; 3],
) -> PyResult<Bound<'py, PyAny>> {
    let array: Bound<'py, PyArray<P, Dim<[usize; 1]>>> = PyArray1::from_vec(py, pixels);
    Ok(array.reshape(shape.to_vec())?.into_any())
}

/// One row-major 4x4 `image_to_world` pose per frame, (n_frames, 4, 4), mm.
pub fn poses_from<'py>(
    py: Python<'py>,
    image_to_world: &Bound<'py, PyAny>,
    n_frames: usize,
) -> PyResult<PyReadonlyArrayDyn<'py, f64>> {
    typed_array::<f64>(
        py,
        "image_to_world",
        image_to_world,
        &[Some(n_frames), Some(4), Some(4)],
        "(n_frames, 4, 4)",
    )
}

/// The per-frame arguments of a correction, converted and checked; [`FrameInputs::correction`]
/// pairs them with a model for the kernels.
pub struct FrameInputs<'py> {
    forces: PyReadonlyArrayDyn<'py, f64>,
    profiles: Vec<StiffnessProfile>,
}

impl<'py> FrameInputs<'py> {
    pub fn extract(
        py: Python<'py>,
        forces: &Bound<'py, PyAny>,
        profiles: &Bound<'py, PyAny>,
    ) -> PyResult<Self> {
        Ok(FrameInputs {
            forces: typed_array::<f64>(py, "forces", forces, &[None], "(n_frames,)")?,
            profiles: profiles_from(py, profiles)?,
        })
    }

    pub fn correction<'a>(
        &'a self,
        model: &'a DeformationModel,
        vessel: Option<PlacedVessel<'a>>,
    ) -> PyResult<Correction<'a>> {
        Ok(Correction {
            model,
            forces: as_slice("forces", &self.forces)?,
            profiles: &self.profiles,
            vessel,
        })
    }
}
