//! Binding of the FEM mechanics' element loop (`usdeform_core::hyperelastic`): `HyperelasticSection`.

use numpy::{PyArray1, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::hyperelastic::{HyperelasticSection as Section, Materials};

use crate::conversion::{as_slice, typed_array};
use crate::errors::{input_error, run_kernel};

fn floats(
    py: Python<'_>,
    name: &str,
    array: &Bound<'_, PyAny>,
    shape: &[Option<usize>],
    layout: &str,
) -> PyResult<Vec<f64>> {
    let array = typed_array::<f64>(py, name, array, shape, layout)?;
    Ok(as_slice(name, &array)?.to_vec())
}

/// A discretised section of the compressible Yeoh material on P2 triangles: `assemble(u,
/// pressure_fraction, with_tangent)` gives its internal nodal forces and the free-free entries of
/// its tangent matrix at displacement `u`.
///
/// `element_dofs` (n_elements, 12) int64: the vector DOF of element entry (i, c) at 2 i + c;
/// `gradients` (n_elements, n_points, 6, 2): d(shape i)/d(x_k) in 1/mm; `weights` (n_elements,
/// n_points): quadrature weights in mm^2; `shear_modulus`, `yeoh_c2`, `yeoh_c3`, `bulk_modulus`,
/// `lumen_pressure` (n_elements,): moduli and pressure in N/mm^2; `entry_slots` (n_elements, 144)
/// int64: where element-matrix entry (a, b) goes among the `n_entries` tangent entries (-1: not
/// in the free-free block).
/// What `assemble` returns: forces, tangent entries (or None) and the smallest det F.
type Assembled<'py> = (
    Bound<'py, PyArray1<f64>>,
    Option<Bound<'py, PyArray1<f64>>>,
    f64,
);

#[pyclass(frozen, module = "usdeform._core")]
pub struct HyperelasticSection {
    section: Section,
}

#[pymethods]
impl HyperelasticSection {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        n_dofs: usize,
        element_dofs: &Bound<'_, PyAny>,
        gradients: &Bound<'_, PyAny>,
        weights: &Bound<'_, PyAny>,
        shear_modulus: &Bound<'_, PyAny>,
        yeoh_c2: &Bound<'_, PyAny>,
        yeoh_c3: &Bound<'_, PyAny>,
        bulk_modulus: &Bound<'_, PyAny>,
        lumen_pressure: &Bound<'_, PyAny>,
        entry_slots: &Bound<'_, PyAny>,
        n_entries: usize,
    ) -> PyResult<Self> {
        let dofs = typed_array::<i64>(
            py,
            "element_dofs",
            element_dofs,
            &[None, Some(12)],
            "(n_elements, 12) of int64",
        )?;
        let n_elements = dofs.shape()[0];
        let element_dofs = as_slice("element_dofs", &dofs)?
            .iter()
            .enumerate()
            .map(|(index, &dof)| {
                usize::try_from(dof).map_err(|_| {
                    input_error(format!(
                        "element_dofs: expected non-negative DOFs, got {dof} at index {index}"
                    ))
                })
            })
            .collect::<PyResult<Vec<usize>>>()?;
        let per_element = [Some(n_elements)];
        let materials = Materials {
            shear_modulus: floats(
                py,
                "shear_modulus",
                shear_modulus,
                &per_element,
                "(n_elements,) of float64",
            )?,
            yeoh_c2: floats(
                py,
                "yeoh_c2",
                yeoh_c2,
                &per_element,
                "(n_elements,) of float64",
            )?,
            yeoh_c3: floats(
                py,
                "yeoh_c3",
                yeoh_c3,
                &per_element,
                "(n_elements,) of float64",
            )?,
            bulk_modulus: floats(
                py,
                "bulk_modulus",
                bulk_modulus,
                &per_element,
                "(n_elements,) of float64",
            )?,
            lumen_pressure: floats(
                py,
                "lumen_pressure",
                lumen_pressure,
                &per_element,
                "(n_elements,) of float64",
            )?,
        };
        let weights_array = typed_array::<f64>(
            py,
            "weights",
            weights,
            &[Some(n_elements), None],
            "(n_elements, n_points) of float64",
        )?;
        let n_points = weights_array.shape()[1];
        let weights = as_slice("weights", &weights_array)?.to_vec();
        let gradients = floats(
            py,
            "gradients",
            gradients,
            &[Some(n_elements), Some(n_points), Some(6), Some(2)],
            "(n_elements, n_points, 6, 2) of float64",
        )?;
        let slots = typed_array::<i64>(
            py,
            "entry_slots",
            entry_slots,
            &[Some(n_elements), Some(144)],
            "(n_elements, 144) of int64",
        )?;
        let entry_slots = as_slice("entry_slots", &slots)?.to_vec();
        let section = run_kernel(py, None, || {
            Section::new(
                n_dofs,
                element_dofs,
                gradients,
                weights,
                materials,
                entry_slots,
                n_entries,
            )
        })?;
        Ok(HyperelasticSection { section })
    }

    /// (force (n_dofs,) in N/mm, tangent entries (n_entries,) or None, smallest det F): the internal
    /// nodal forces at displacement `u` (n_dofs,) in mm with `pressure_fraction` of the lumen
    /// pressure applied and, with `with_tangent`, the tangent's entries. A smallest det F that is
    /// not positive means an inverted element; the outputs are then incomplete.
    fn assemble<'py>(
        &self,
        py: Python<'py>,
        u: &Bound<'py, PyAny>,
        pressure_fraction: f64,
        with_tangent: bool,
    ) -> PyResult<Assembled<'py>> {
        let u = typed_array::<f64>(
            py,
            "u",
            u,
            &[Some(self.section.dofs())],
            "(n_dofs,) of float64",
        )?;
        let u = as_slice("u", &u)?;
        let assembly = run_kernel(py, None, || {
            self.section.assemble(u, pressure_fraction, with_tangent)
        })?;
        let tangent = with_tangent.then(|| PyArray1::from_vec(py, assembly.tangent));
        Ok((
            PyArray1::from_vec(py, assembly.force),
            tangent,
            assembly.min_jacobian,
        ))
    }
}

/// Adds `HyperelasticSection` to the module.
pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<HyperelasticSection>()?;
    Ok(())
}
