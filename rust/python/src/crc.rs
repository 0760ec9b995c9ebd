//! Binding of the OpenIGTLink CRC-64 (`usdeform_core::crc64`): `crc64`.

use pyo3::prelude::*;

use usdeform_core::crc64::crc64_ecma182;

use crate::conversion::{as_slice, typed_array};
use crate::errors::run_kernel;

/// The CRC-64 (ECMA-182, as OpenIGTLink) of `data`, a 1-D C-contiguous uint8 array, continued from
/// `crc` (the CRC of the bytes before it; 0 to start). Computed without the GIL.
#[pyfunction]
#[pyo3(signature = (data, crc = 0))]
fn crc64(py: Python<'_>, data: &Bound<'_, PyAny>, crc: u64) -> PyResult<u64> {
    let data = typed_array::<u8>(py, "data", data, &[None], "(n,) uint8")?;
    let bytes = as_slice("data", &data)?;
    run_kernel(py, None, || Ok(crc64_ecma182(bytes, crc)))
}

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_function(wrap_pyfunction!(crc64, module)?)?;
    Ok(())
}
