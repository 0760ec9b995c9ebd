//! Errors crossing into Python: the `usdeform.errors` classes, imported once, one conversion from
//! [`KernelError`], and [`run_kernel`], which also turns a panic into `InternalError`.

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;
use usdeform_core::KernelError;

pyo3::import_exception!(usdeform.errors, InputError);
pyo3::import_exception!(usdeform.errors, MemoryLimitError);
pyo3::import_exception!(usdeform.errors, InternalError);

/// A kernel error on its way to Python (a local type, so that `From` can be implemented here).
pub struct CoreError(pub KernelError);

impl From<KernelError> for CoreError {
    fn from(error: KernelError) -> Self {
        CoreError(error)
    }
}

impl From<CoreError> for PyErr {
    fn from(CoreError(error): CoreError) -> PyErr {
        match error {
            KernelError::MemoryLimit { .. } | KernelError::Allocation { .. } => {
                MemoryLimitError::new_err(error.to_string())
            }
            _ => InputError::new_err(error.to_string()),
        }
    }
}

/// `usdeform.errors.InputError(message)`.
pub fn input_error(message: impl Into<String>) -> PyErr {
    InputError::new_err(message.into())
}

/// Run `kernel` without the GIL on `threads` threads (None: rayon's default pool; serial kernels
/// pass None and so start no pool), mapping kernel errors and panics to Python exceptions.
pub fn run_kernel<T: Send>(
    py: Python<'_>,
    threads: Option<usize>,
    kernel: impl FnOnce() -> Result<T, KernelError> + Send,
) -> PyResult<T> {
    let pool = match threads {
        None => None,
        Some(0) => {
            return Err(input_error(
                "threads: must be at least 1 (or None for all cores)",
            ))
        }
        Some(n) => Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| InternalError::new_err(format!("cannot start {n} threads: {e}")))?,
        ),
    };
    let outcome = py.detach(|| {
        catch_unwind(AssertUnwindSafe(|| match &pool {
            Some(pool) => pool.install(kernel),
            None => kernel(),
        }))
    });
    match outcome {
        Ok(result) => Ok(result.map_err(CoreError)?),
        Err(panic) => {
            let detail = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            Err(InternalError::new_err(format!(
                "internal error in usdeform._core: {detail}"
            )))
        }
    }
}
