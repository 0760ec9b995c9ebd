//! usdeform-core: the hot paths of deformation-aware robotic 3D ultrasound, in plain Rust.
//!
//! - [`regression`]: the coupled quadratic displacement model and its force-interval integral;
//! - [`bspline`]: a cubic B-spline spatial basis for the same model;
//! - [`warp`]: warping frames back to zero force;
//! - [`compound`]: inserting frames into a voxel volume.
//!
//! No Python here: the pyo3 binding lives in the `usdeform-python` crate.

pub mod bspline;
pub mod compound;
pub mod error;
pub mod holes;
pub mod regression;
pub mod stiffness;
pub mod warp;

pub use error::{KernelError, Result};
