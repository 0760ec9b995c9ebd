//! Binding of the hole filling (`usdeform_core::holes`): `fill_holes`.

use numpy::{PyArrayDyn, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::holes::{self, HoleFillingElement, VoxelValue};

use crate::conversion::{as_slice, frames_array, type_name, typed_array};
use crate::errors::{input_error, run_kernel};

/// One element as Python passes it: (kind, size, stdev, min_known_ratio, stick_length_limit,
/// sticks_to_use); each kind reads the fields it needs.
type ElementTuple = (String, usize, f64, f64, usize, usize);

fn element_from(index: usize, element: &ElementTuple) -> PyResult<HoleFillingElement> {
    let (kind, size, stdev, min_known_ratio, length_limit, sticks_to_use) = element;
    let (size, stdev, min_known_ratio) = (*size, *stdev, *min_known_ratio);
    Ok(match kind.as_str() {
        "gaussian" => HoleFillingElement::Gaussian {
            size,
            stdev,
            min_known_ratio,
        },
        "gaussian_accumulation" => HoleFillingElement::GaussianAccumulation {
            size,
            stdev,
            min_known_ratio,
        },
        "distance_weight_inverse" => HoleFillingElement::DistanceWeightInverse {
            size,
            min_known_ratio,
        },
        "nearest_neighbor" => HoleFillingElement::NearestNeighbor {
            size,
            min_known_ratio,
        },
        "stick" => HoleFillingElement::Stick {
            length_limit: *length_limit,
            sticks_to_use: *sticks_to_use,
        },
        other => {
            return Err(input_error(format!(
                "elements: element {index}: expected kind 'gaussian', 'gaussian_accumulation', \
                     'distance_weight_inverse', 'nearest_neighbor' or 'stick', got {other:?}"
            )))
        }
    })
}

/// The arguments of a call besides the image, checked.
struct Settings<'a> {
    weight: &'a [f32],
    shape: [usize; 3],
    elements: &'a [HoleFillingElement],
    min_known_weight: f32,
    max_bytes: u128,
    threads: Option<usize>,
}

fn fill_typed<'py, T: VoxelValue + numpy::Element>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    settings: &Settings<'_>,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = settings.shape;
    let layout = format!("{shape:?} like weight");
    let image = typed_array::<T>(py, "image", image, &shape.map(Some), &layout)?;
    let values = as_slice("image", &image)?;
    let out = run_kernel(py, settings.threads, || {
        holes::fill_holes(
            values,
            settings.weight,
            shape,
            settings.elements,
            settings.min_known_weight,
            settings.max_bytes,
        )
    })?;
    frames_array(py, out, shape)
}

/// The volume `image` (z, y, x; uint8 or float32) with its holes filled by `elements` in order:
/// voxels whose coverage `weight` (float32, same shape) is 0 or below `min_known_weight` are holes.
#[pyfunction]
#[pyo3(signature = (image, weight, elements, min_known_weight, max_bytes, threads=None))]
fn fill_holes<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    weight: &Bound<'py, PyAny>,
    elements: Vec<ElementTuple>,
    min_known_weight: f32,
    max_bytes: u128,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let weight = typed_array::<f32>(
        py,
        "weight",
        weight,
        &[None, None, None],
        "(z, y, x) of float32",
    )?;
    let shape = weight.shape();
    let shape = [shape[0], shape[1], shape[2]];
    let weight_values = as_slice("weight", &weight)?;
    let elements = elements
        .iter()
        .enumerate()
        .map(|(index, element)| element_from(index, element))
        .collect::<PyResult<Vec<_>>>()?;
    let settings = Settings {
        weight: weight_values,
        shape,
        elements: &elements,
        min_known_weight,
        max_bytes,
        threads,
    };
    if image.cast::<PyArrayDyn<u8>>().is_ok() {
        fill_typed::<u8>(py, image, &settings)
    } else if image.cast::<PyArrayDyn<f32>>().is_ok() {
        fill_typed::<f32>(py, image, &settings)
    } else {
        let got = image
            .cast::<PyUntypedArray>()
            .map(|a| a.dtype().str().map(|s| s.to_string()).unwrap_or_default())
            .unwrap_or_else(|_| type_name(image));
        Err(input_error(format!(
            "image: expected a (z, y, x) array of uint8 or float32, got {got}"
        )))
    }
}

/// Adds the hole-filling functions to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(fill_holes, module)?)?;
    Ok(())
}
