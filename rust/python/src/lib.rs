//! The compiled module `usdeform._core`: a thin pyo3 layer over `usdeform-core`.
//!
//! Each function validates its arrays (naming the argument and what was expected), releases the GIL
//! around the kernel, and turns kernel errors and panics into the `usdeform.errors` hierarchy, so
//! neither a Rust error nor a panic reaches the interpreter as anything else. One file per concern:
//! [`errors`] (the crossing of errors), [`conversion`] (arrays in and out), [`model`] (the typed
//! model every kernel takes), [`correction`] (warping), [`anchored`] (the vessel part of a vessel-anchored model and the lumen search that places it), [`accumulator`] (compounding, and for a vessel-anchored model the search overlapped with it), [`crc`] (the OpenIGTLink CRC-64), [`hyperelastic`] (the FEM's element loop), [`sparse_solve`] (the FEM's linear solves), [`tracking`] (the tracker's affine Lucas-Kanade, patch correlation and block matching), [`imaging`] (the B-mode simulator's bilinear splat). Each file
//! with Python names has one `register` function, called below.

mod accumulator;
mod anchored;
mod conversion;
mod correction;
mod crc;
mod errors;
mod holes;
mod hyperelastic;
mod imaging;
mod model;
mod sparse_solve;
mod tracking;

use pyo3::prelude::*;

#[pymodule]
fn _core(module: &Bound<'_, PyModule>) -> PyResult<()> {
    model::register(module)?;
    correction::register(module)?;
    anchored::register(module)?;
    accumulator::register(module)?;
    crc::register(module)?;
    holes::register(module)?;
    hyperelastic::register(module)?;
    sparse_solve::register(module)?;
    tracking::register(module)?;
    imaging::register(module)?;
    Ok(())
}
