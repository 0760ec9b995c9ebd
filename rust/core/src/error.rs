//! The one error type of the kernels. Every variant names the argument at fault.

use std::fmt;

/// An input the kernels cannot work with, or a limit the caller set.
#[derive(Debug, Clone, PartialEq)]
pub enum KernelError {
    /// An array has the wrong length or shape.
    Shape {
        argument: &'static str,
        expected: String,
        got: String,
    },
    /// An array holds NaN or infinity at `index` (flat index, or frame number where stated).
    NonFinite {
        argument: &'static str,
        index: usize,
    },
    /// An array that must not be empty is empty.
    Empty { argument: &'static str },
    /// A scalar or element is outside its valid range.
    Value {
        argument: &'static str,
        message: String,
    },
    /// The force is outside the rising branch of the profile's force-displacement curve.
    OutsideRisingBranch { frame: usize, force: f64 },
    /// An output of `bytes` bytes (u128::MAX: beyond any address space) cannot be allocated.
    Allocation { argument: &'static str, bytes: u128 },
    /// The output would need more memory than the caller allowed.
    MemoryLimit {
        needed_bytes: u128,
        limit_bytes: u128,
    },
}

impl fmt::Display for KernelError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            KernelError::Shape {
                argument,
                expected,
                got,
            } => {
                write!(f, "{argument}: expected {expected}, got {got}")
            }
            KernelError::NonFinite { argument, index } => {
                write!(
                    f,
                    "{argument}: non-finite value (NaN or infinity) at index {index}"
                )
            }
            KernelError::Empty { argument } => write!(f, "{argument}: must not be empty"),
            KernelError::Value { argument, message } => write!(f, "{argument}: {message}"),
            KernelError::OutsideRisingBranch { frame, force } => write!(
                f,
                "forces: frame {frame}: force {force:.6} N is outside the rising branch of the \
                 stiffness profile's force-displacement curve c1 lambda^2 + c2 lambda + c3 (below \
                 its minimum or beyond its maximum), where the stiffness 2 c1 lambda + c2 is not \
                 positive"
            ),
            KernelError::Allocation { argument, bytes } if *bytes == u128::MAX => write!(
                f,
                "{argument}: the output needs more bytes than any address space holds"
            ),
            KernelError::Allocation { argument, bytes } => write!(
                f,
                "{argument}: the output needs {bytes} bytes, which cannot be allocated"
            ),
            KernelError::MemoryLimit {
                needed_bytes,
                limit_bytes,
            } => write!(
                f,
                "the voxel grid needs {needed_bytes} bytes, over the limit of {limit_bytes} bytes; \
                 use a coarser grid or raise max_bytes"
            ),
        }
    }
}

impl std::error::Error for KernelError {}

pub type Result<T> = std::result::Result<T, KernelError>;

/// Fails with [`KernelError::Shape`] unless `values.len() == expected`.
pub fn check_len<T>(argument: &'static str, values: &[T], expected: usize) -> Result<()> {
    if values.len() == expected {
        Ok(())
    } else {
        Err(KernelError::Shape {
            argument,
            expected: format!("{expected} values"),
            got: format!("{} values", values.len()),
        })
    }
}

/// Fails with [`KernelError::NonFinite`] at the first NaN or infinity.
pub fn check_finite(argument: &'static str, values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(KernelError::NonFinite { argument, index }),
        None => Ok(()),
    }
}

/// An empty vector able to hold `len` items, or an error naming `argument` (an allocation failure
/// would abort the process, which no panic handler catches).
pub fn reserve<T>(argument: &'static str, len: usize) -> Result<Vec<T>> {
    let mut values = Vec::new();
    values
        .try_reserve_exact(len)
        .map_err(|_| KernelError::Allocation {
            argument,
            bytes: (len as u128) * (std::mem::size_of::<T>() as u128),
        })?;
    Ok(values)
}
