//! Errors crossing into Python: the `usdeform.errors` classes, imported once, one conversion from
//! [`KernelError`], and [`run_kernel`], which also turns a panic into `InternalError`.

use std::panic::{catch_unwind, AssertUnwindSafe};

use pyo3::prelude::*;
use usdeform_core::KernelError;

pyo3::import_exception!(usdeform.errors, InputError);
pyo3::import_exception!(usdeform.errors, MemoryLimitError);
pyo3::import_exception!(usdeform.errors, InternalError);
pyo3::import_exception!(usdeform.errors, UsdeformError);

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

/// Most worker threads a call may ask for.
pub const MAX_THREADS: usize = 1024;

/// `threads` checked: None (all cores) or 1 to [`MAX_THREADS`].
pub fn checked_threads(threads: Option<usize>) -> PyResult<Option<usize>> {
    match threads {
        Some(n) if n == 0 || n > MAX_THREADS => Err(input_error(format!(
            "threads: expected 1 to {MAX_THREADS} (or None for all cores), got {n}"
        ))),
        _ => Ok(threads),
    }
}

/// The worker threads of one call: rayon's default pool (None) or a pool of the asked size.
pub struct Pool(Option<rayon::ThreadPool>);

impl Pool {
    pub fn new(threads: Option<usize>) -> PyResult<Self> {
        match checked_threads(threads)? {
            None => Ok(Pool(None)),
            Some(n) => rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map(|pool| Pool(Some(pool)))
                .map_err(|e| InternalError::new_err(format!("cannot start {n} threads: {e}"))),
        }
    }

    /// Run `kernel` without the GIL on this pool, mapping kernel errors and panics to Python
    /// exceptions.
    pub fn run<T: Send>(
        &self,
        py: Python<'_>,
        kernel: impl FnOnce() -> Result<T, KernelError> + Send,
    ) -> PyResult<T> {
        let outcome = py.detach(|| {
            catch_unwind(AssertUnwindSafe(|| match &self.0 {
                Some(pool) => pool.install(kernel),
                None => kernel(),
            }))
        });
        match outcome {
            Ok(result) => Ok(result.map_err(CoreError)?),
            Err(panic) => Err(internal_error(panic)),
        }
    }
}

/// The InternalError of a kernel's panic (its message).
pub fn internal_error(panic: Box<dyn std::any::Any + Send>) -> PyErr {
    let detail = panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into());
    InternalError::new_err(format!("internal error in usdeform._core: {detail}"))
}

/// Run `kernel` without the GIL on `threads` threads (None: rayon's default pool; serial kernels
/// pass None and so start no pool), mapping kernel errors and panics to Python exceptions.
pub fn run_kernel<T: Send>(
    py: Python<'_>,
    threads: Option<usize>,
    kernel: impl FnOnce() -> Result<T, KernelError> + Send,
) -> PyResult<T> {
    Pool::new(threads)?.run(py, kernel)
}

/// Frames per call of a long kernel: between calls the interpreter's signals are checked, so that
/// Ctrl-C interrupts a long run (KeyboardInterrupt) within one chunk. A multiple of the
/// compounding batch, so the chunking never changes a result.
pub const FRAMES_PER_CHUNK: usize = 64;

/// The frame ranges of `n_frames` frames, chunk by chunk ([`FRAMES_PER_CHUNK`] each).
pub fn frame_chunks(n_frames: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    chunks_of(n_frames, FRAMES_PER_CHUNK)
}

/// The ranges of `n_frames` frames, `size` (> 0) at a time.
pub fn chunks_of(n_frames: usize, size: usize) -> impl Iterator<Item = std::ops::Range<usize>> {
    (0..n_frames)
        .step_by(size)
        .map(move |start| start..(start + size).min(n_frames))
}
