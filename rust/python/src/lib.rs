//! The compiled module `usdeform._core`: a thin pyo3 layer over `usdeform-core`.
//!
//! Each function validates its arrays (naming the argument and what was expected), releases the GIL
//! around the kernel, and turns kernel errors and panics into the `usdeform.errors` hierarchy, so
//! neither a Rust error nor a panic reaches the interpreter as anything else.

use std::panic::{catch_unwind, AssertUnwindSafe};

mod holes;

use numpy::ndarray::Dim;
use numpy::{
    Element, PyArray, PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn, PyUntypedArray,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyType;

use usdeform_core::bspline::BSplineModel;
use usdeform_core::compound::{self, Compounding, Interpolation};
use usdeform_core::regression::{
    self, Integral, IntegrationVariable, Normalization, QuadraticModel, SpatialModel,
};
use usdeform_core::stiffness::StiffnessProfile;
use usdeform_core::warp::{self, Correction, FrameStack, Pixel};
use usdeform_core::KernelError;

/// An instance of the exception class `name` of `usdeform.errors`.
fn usdeform_error(py: Python<'_>, name: &str, message: String) -> PyErr {
    let class = py
        .import("usdeform.errors")
        .and_then(|module| module.getattr(name))
        .and_then(|class| class.cast_into::<PyType>().map_err(PyErr::from));
    match class {
        Ok(class) => PyErr::from_type(class, message),
        Err(import_error) => import_error,
    }
}

fn input_error(py: Python<'_>, message: String) -> PyErr {
    usdeform_error(py, "InputError", message)
}

fn kernel_error(py: Python<'_>, error: KernelError) -> PyErr {
    let class = match error {
        KernelError::MemoryLimit { .. } | KernelError::Allocation { .. } => "MemoryLimitError",
        _ => "InputError",
    };
    usdeform_error(py, class, error.to_string())
}

/// Run `kernel` without the GIL on `threads` threads (None: rayon's default pool), mapping kernel
/// errors and panics to Python exceptions.
fn run_kernel<T: Send>(
    py: Python<'_>,
    threads: Option<usize>,
    kernel: impl FnOnce() -> Result<T, KernelError> + Send,
) -> PyResult<T> {
    let pool = match threads {
        None => None,
        Some(0) => {
            return Err(input_error(
                py,
                "threads: must be at least 1 (or None for all cores)".into(),
            ))
        }
        Some(n) => Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| {
                    usdeform_error(
                        py,
                        "InternalError",
                        format!("cannot start {n} threads: {e}"),
                    )
                })?,
        ),
    };
    let outcome = py.detach(|| {
        catch_unwind(AssertUnwindSafe(|| match &pool {
            Some(pool) => pool.install(kernel),
            None => kernel(),
        }))
    });
    match outcome {
        Ok(result) => result.map_err(|e| kernel_error(py, e)),
        Err(panic) => {
            let detail = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(usdeform_error(
                py,
                "InternalError",
                format!("internal error in usdeform._core: {detail}"),
            ))
        }
    }
}

/// A C-contiguous array of element `T` with `ndim` dimensions, each checked against `expected`
/// (None: any length). `layout` describes the expected shape in error messages.
fn typed_array<'py, T: Element>(
    py: Python<'py>,
    name: &str,
    object: &Bound<'py, PyAny>,
    expected: &[Option<usize>],
    layout: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let untyped = object.cast::<PyUntypedArray>().map_err(|_| {
        input_error(
            py,
            format!(
                "{name}: expected a numpy array {layout}, got {}",
                type_name(object)
            ),
        )
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
        input_error(py, format!("{name}: expected dtype {wanted}, got {got}"))
    })?;
    let shape = array.shape();
    let shape_ok = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(&n, e)| e.is_none_or(|e| e == n));
    if !shape_ok {
        return Err(input_error(
            py,
            format!("{name}: expected shape {layout}, got {shape:?}"),
        ));
    }
    if !array.is_c_contiguous() {
        return Err(input_error(
            py,
            format!("{name}: expected a C-contiguous array"),
        ));
    }
    Ok(array.readonly())
}

fn type_name(object: &Bound<'_, PyAny>) -> String {
    object
        .get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "an unknown type".into())
}

fn as_slice<'a, T: Element>(
    py: Python<'_>,
    name: &str,
    array: &'a PyReadonlyArrayDyn<'_, T>,
) -> PyResult<&'a [T]> {
    array
        .as_slice()
        .map_err(|_| input_error(py, format!("{name}: expected a C-contiguous array")))
}

fn normalization_from(py: Python<'_>, normalization: &Bound<'_, PyAny>) -> PyResult<Normalization> {
    let normalization = typed_array::<f64>(py, "normalization", normalization, &[Some(6)], "(6,)")?;
    Normalization::from_slice(as_slice(py, "normalization", &normalization)?)
        .map_err(|e| kernel_error(py, e))
}

const COEFFICIENTS_LAYOUT: &str =
    "(2, 10) for the quadratic model or (2, 3, n_y, n_x) with n_y, n_x >= 4 for the B-spline model";

/// The spatial model whose basis the shape of `coefficients` tells: (2, 10) the paper's quadratic
/// regression, (2, 3, n_y, n_x) a cubic B-spline (component, force term 1/h/h^2, y, x function).
fn model_from(
    py: Python<'_>,
    coefficients: &Bound<'_, PyAny>,
    normalization: &Bound<'_, PyAny>,
) -> PyResult<SpatialModel> {
    let is_spline = coefficients
        .cast::<PyUntypedArray>()
        .is_ok_and(|array| array.ndim() == 4);
    let expected: &[Option<usize>] = if is_spline {
        &[Some(2), Some(3), None, None]
    } else {
        &[Some(2), Some(10)]
    };
    let array = typed_array::<f64>(
        py,
        "coefficients",
        coefficients,
        expected,
        COEFFICIENTS_LAYOUT,
    )?;
    let values = as_slice(py, "coefficients", &array)?;
    let normalization = normalization_from(py, normalization)?;
    let model = if is_spline {
        let shape = array.shape();
        BSplineModel::new(values, shape[2], shape[3], normalization).map(SpatialModel::BSpline)
    } else {
        QuadraticModel::new(values, normalization).map(SpatialModel::Quadratic)
    };
    model.map_err(|e| kernel_error(py, e))
}

fn profiles_from(py: Python<'_>, profiles: &Bound<'_, PyAny>) -> PyResult<Vec<StiffnessProfile>> {
    let profiles = typed_array::<f64>(
        py,
        "profiles",
        profiles,
        &[None, Some(3)],
        "(n_frames, 3) of (c1, c2, c3)",
    )?;
    Ok(as_slice(py, "profiles", &profiles)?
        .chunks(3)
        .map(|c| StiffnessProfile {
            c1: c[0],
            c2: c[1],
            c3: c[2],
        })
        .collect())
}

fn field_array<'py>(
    py: Python<'py>,
    values: Vec<f64>,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    PyArray1::from_vec(py, values).reshape(vec![2, rows, cols])
}

/// The integral of the rate: `integration` "force" (paper eq. 8) or "displacement" (over lambda).
fn integral_from(py: Python<'_>, n_intervals: usize, integration: &str) -> PyResult<Integral> {
    let variable = match integration {
        "force" => IntegrationVariable::Force,
        "displacement" => IntegrationVariable::ProbeDisplacement,
        other => {
            return Err(input_error(
                py,
                format!("integration: expected 'force' or 'displacement', got {other:?}"),
            ))
        }
    };
    Ok(Integral {
        variable,
        n_intervals,
    })
}

fn check_grid(py: Python<'_>, rows: usize, cols: usize) -> PyResult<()> {
    if rows == 0 || cols == 0 {
        return Err(input_error(
            py,
            format!("rows, cols: expected a non-empty pixel grid, got {rows} x {cols}"),
        ));
    }
    Ok(())
}

/// The regression rate d(x, y, h) on a rows x cols grid, shape (2, rows, cols), pixels per unit
/// normalised force (paper eq. 7).
#[pyfunction]
#[pyo3(signature = (coefficients, normalization, h_mm, rows, cols))]
fn regression_rate<'py>(
    py: Python<'py>,
    coefficients: &Bound<'py, PyAny>,
    normalization: &Bound<'py, PyAny>,
    h_mm: f64,
    rows: usize,
    cols: usize,
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    check_grid(py, rows, cols)?;
    let model = model_from(py, coefficients, normalization)?;
    let field = run_kernel(py, Some(1), || {
        regression::rate_field(&model, h_mm, rows, cols)
    })?;
    field_array(py, field, rows, cols)
}

/// The three normalised force integrals (of 1, h and h^2) from 0 to `force_n` (paper eq. 8).
#[pyfunction]
#[pyo3(signature = (force_n, profile, normalization, n_intervals, integration="force"))]
fn force_integrals(
    py: Python<'_>,
    force_n: f64,
    profile: (f64, f64, f64),
    normalization: &Bound<'_, PyAny>,
    n_intervals: usize,
    integration: &str,
) -> PyResult<(f64, f64, f64)> {
    let integral = integral_from(py, n_intervals, integration)?;
    let normalization = normalization_from(py, normalization)?;
    let profile = StiffnessProfile {
        c1: profile.0,
        c2: profile.1,
        c3: profile.2,
    };
    let terms = run_kernel(py, Some(1), || {
        regression::ForceTerms::integrated(force_n, &profile, integral, &normalization, 0)
    })?;
    Ok((terms.one, terms.h, terms.h2))
}

/// The displacement D(x, y, F) in pixels on a rows x cols grid, shape (2, rows, cols) (paper eq. 8).
#[pyfunction]
#[pyo3(signature = (coefficients, normalization, force_n, profile, n_intervals, rows, cols, integration="force"))]
#[allow(clippy::too_many_arguments)]
fn integrated_displacement<'py>(
    py: Python<'py>,
    coefficients: &Bound<'py, PyAny>,
    normalization: &Bound<'py, PyAny>,
    force_n: f64,
    profile: (f64, f64, f64),
    n_intervals: usize,
    rows: usize,
    cols: usize,
    integration: &str,
) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    check_grid(py, rows, cols)?;
    let integral = integral_from(py, n_intervals, integration)?;
    let model = model_from(py, coefficients, normalization)?;
    let profile = StiffnessProfile {
        c1: profile.0,
        c2: profile.1,
        c3: profile.2,
    };
    let field = run_kernel(py, Some(1), || {
        regression::displacement_field(&model, force_n, &profile, integral, rows, cols)
    })?;
    field_array(py, field, rows, cols)
}

/// The frames of a call: uint8 or float32, (n_frames, rows, cols).
enum Frames<'py> {
    U8(PyReadonlyArrayDyn<'py, u8>),
    F32(PyReadonlyArrayDyn<'py, f32>),
}

const FRAMES_LAYOUT: &str = "(n_frames, rows, cols) of uint8 or float32";

impl<'py> Frames<'py> {
    fn extract(py: Python<'py>, frames: &Bound<'py, PyAny>) -> PyResult<Self> {
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
            Err(input_error(
                py,
                format!("frames: expected an array {FRAMES_LAYOUT}, got {dtype}"),
            ))
        }
    }

    fn shape(&self) -> [usize; 3] {
        let shape = match self {
            Frames::U8(a) => a.shape(),
            Frames::F32(a) => a.shape(),
        };
        [shape[0], shape[1], shape[2]]
    }
}

fn stack<'a, P: Pixel + Element>(
    py: Python<'_>,
    array: &'a PyReadonlyArrayDyn<'_, P>,
) -> PyResult<FrameStack<'a, P>> {
    let shape = array.shape();
    FrameStack::new(as_slice(py, "frames", array)?, shape[0], shape[1], shape[2])
        .map_err(|e| kernel_error(py, e))
}

/// Evaluate `$body` with `$stack` bound to the frames' [`FrameStack`], whichever pixel type they hold.
macro_rules! with_frame_stack {
    ($py:expr, $frames:expr, |$stack:ident| $body:expr) => {
        match $frames {
            Frames::U8(array) => {
                let $stack = stack($py, array)?;
                $body
            }
            Frames::F32(array) => {
                let $stack = stack($py, array)?;
                $body
            }
        }
    };
}

fn frames_array<'py, P: Element>(
    py: Python<'py>,
    pixels: Vec<P>,
    shape: [usize; 3],
) -> PyResult<Bound<'py, PyAny>> {
    let array: Bound<'py, PyArray<P, Dim<[usize; 1]>>> = PyArray1::from_vec(py, pixels);
    Ok(array.reshape(shape.to_vec())?.into_any())
}

fn check_fill(py: Python<'_>, fill: f64, frames: &Frames<'_>) -> PyResult<()> {
    let is_u8 = matches!(frames, Frames::U8(_));
    if !fill.is_finite() || (is_u8 && !(0.0..=255.0).contains(&fill)) {
        let range = if is_u8 {
            " in [0, 255] for uint8 frames"
        } else {
            ""
        };
        return Err(input_error(
            py,
            format!("fill: expected a finite value{range}, got {fill}"),
        ));
    }
    Ok(())
}

/// The correction arguments of a call, converted and checked; [`CorrectionInputs::correction`]
/// borrows them for the kernels.
struct CorrectionInputs<'py> {
    model: SpatialModel,
    forces: PyReadonlyArrayDyn<'py, f64>,
    profiles: Vec<StiffnessProfile>,
    integral: Integral,
}

impl<'py> CorrectionInputs<'py> {
    #[allow(clippy::too_many_arguments)]
    fn extract(
        py: Python<'py>,
        forces: &Bound<'py, PyAny>,
        profiles: &Bound<'py, PyAny>,
        coefficients: &Bound<'py, PyAny>,
        normalization: &Bound<'py, PyAny>,
        n_intervals: usize,
        integration: &str,
    ) -> PyResult<Self> {
        Ok(CorrectionInputs {
            model: model_from(py, coefficients, normalization)?,
            forces: typed_array::<f64>(py, "forces", forces, &[None], "(n_frames,)")?,
            profiles: profiles_from(py, profiles)?,
            integral: integral_from(py, n_intervals, integration)?,
        })
    }

    fn correction(&self, py: Python<'_>) -> PyResult<Correction<'_>> {
        Ok(Correction {
            model: &self.model,
            forces: as_slice(py, "forces", &self.forces)?,
            profiles: &self.profiles,
            integral: self.integral,
        })
    }
}

/// One row-major 4x4 `image_to_world` pose per frame, (n_frames, 4, 4), mm.
fn poses_from<'py>(
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

/// Warp frames back to zero force: output pixel (x, y) is the input frame sampled bilinearly at
/// (x, y) + D(x, y, F_frame); samples outside the frame give `fill`. Same dtype as the input.
#[pyfunction]
#[pyo3(signature = (frames, forces, profiles, coefficients, normalization, n_intervals, integration="force", fill=0.0, threads=None))]
#[allow(clippy::too_many_arguments)]
fn warp_frames<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    forces: &Bound<'py, PyAny>,
    profiles: &Bound<'py, PyAny>,
    coefficients: &Bound<'py, PyAny>,
    normalization: &Bound<'py, PyAny>,
    n_intervals: usize,
    integration: &str,
    fill: f64,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let frames = Frames::extract(py, frames)?;
    let inputs = CorrectionInputs::extract(
        py,
        forces,
        profiles,
        coefficients,
        normalization,
        n_intervals,
        integration,
    )?;
    let correction = inputs.correction(py)?;
    let shape = frames.shape();
    check_fill(py, fill, &frames)?;
    with_frame_stack!(py, &frames, |stack| {
        let out = run_kernel(py, threads, || {
            warp::warp_frames(&stack, &correction, Pixel::from_f64(fill))
        })?;
        frames_array(py, out, shape)
    })
}

fn parse_interpolation(py: Python<'_>, name: &str) -> PyResult<Interpolation> {
    match name {
        "nearest" => Ok(Interpolation::Nearest),
        "linear" => Ok(Interpolation::Linear),
        other => Err(input_error(
            py,
            format!("interpolation: expected 'nearest' or 'linear', got {other:?}"),
        )),
    }
}

fn parse_compounding(py: Python<'_>, name: &str) -> PyResult<Compounding> {
    match name {
        "mean" => Ok(Compounding::Mean),
        "max" => Ok(Compounding::Maximum),
        "latest" => Ok(Compounding::Latest),
        other => Err(input_error(
            py,
            format!("compounding: expected 'mean', 'max' or 'latest', got {other:?}"),
        )),
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
            as_slice(py, "index_to_world", &index_to_world)?,
            parse_interpolation(py, interpolation)?,
            parse_compounding(py, compounding)?,
            max_bytes,
        )
        .map_err(|e| kernel_error(py, e))?;
        Ok(Accumulator { inner })
    }

    /// Insert frames (n_frames, rows, cols) at their `image_to_world` poses (n_frames, 4, 4), mm.
    #[pyo3(signature = (frames, image_to_world, threads=None))]
    fn insert(
        &mut self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        threads: Option<usize>,
    ) -> PyResult<()> {
        let frames = Frames::extract(py, frames)?;
        let poses = poses_from(py, image_to_world, frames.shape()[0])?;
        let poses = as_slice(py, "image_to_world", &poses)?;
        let inner = &mut self.inner;
        with_frame_stack!(py, &frames, |stack| run_kernel(py, threads, || inner
            .insert(&stack, poses)))
    }

    /// Warp frames back to zero force (as `warp_frames`) and insert them, without keeping the
    /// corrected frames.
    #[pyo3(signature = (frames, image_to_world, forces, profiles, coefficients, normalization, n_intervals, integration="force", fill=0.0, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn insert_corrected(
        &mut self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        forces: &Bound<'_, PyAny>,
        profiles: &Bound<'_, PyAny>,
        coefficients: &Bound<'_, PyAny>,
        normalization: &Bound<'_, PyAny>,
        n_intervals: usize,
        integration: &str,
        fill: f64,
        threads: Option<usize>,
    ) -> PyResult<()> {
        let frames = Frames::extract(py, frames)?;
        let poses = poses_from(py, image_to_world, frames.shape()[0])?;
        let poses = as_slice(py, "image_to_world", &poses)?;
        let inputs = CorrectionInputs::extract(
            py,
            forces,
            profiles,
            coefficients,
            normalization,
            n_intervals,
            integration,
        )?;
        let correction = inputs.correction(py)?;
        check_fill(py, fill, &frames)?;
        let inner = &mut self.inner;
        with_frame_stack!(py, &frames, |stack| {
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

/// Panics on purpose inside a kernel run; lets the tests check that panics become InternalError.
#[pyfunction]
fn _panic_for_tests(py: Python<'_>) -> PyResult<()> {
    run_kernel(py, Some(2), || -> Result<(), KernelError> {
        panic!("deliberate panic for the tests")
    })
}

#[pymodule]
fn _core(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(regression_rate, module)?)?;
    module.add_function(wrap_pyfunction!(force_integrals, module)?)?;
    module.add_function(wrap_pyfunction!(integrated_displacement, module)?)?;
    module.add_function(wrap_pyfunction!(warp_frames, module)?)?;
    module.add_function(wrap_pyfunction!(_panic_for_tests, module)?)?;
    module.add_class::<Accumulator>()?;
    module.add("BYTES_PER_VOXEL", compound::BYTES_PER_VOXEL)?;
    holes::register(module)?;
    Ok(())
}
