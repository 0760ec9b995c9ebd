//! usdeform-core: the hot paths of deformation-aware robotic 3D ultrasound, in plain Rust.
//!
//! - [`terms`]: normalisation, the force integrals of the rate (paper eq. 8, closed-form) and its force terms;
//! - [`quadratic`]: the paper's quadratic spatial basis (eq. 7);
//! - [`bspline`]: a cubic B-spline spatial basis for the same model;
//! - [`field`]: either basis as one displacement field (rate and displacement on a pixel grid);
//! - [`model`]: the deformation model the kernels take (basis, integral, coupling, frame shape);
//! - [`frame_correction`]: one frame's displacement, the model's field plus the placed vessel part;
//! - [`warp`]: warping frames back to zero force;
//! - [`anchored`]: the vessel part of a vessel-anchored model, placed on each frame's lumen;
//! - [`lumen`]: the lumen search that places it (each frame's zero-force lumen in a sweep);
//! - [`compound`]: inserting frames into a voxel volume;
//! - [`crc64`]: the CRC-64 of OpenIGTLink messages;
//! - [`affine_lk`]: the affine Lucas-Kanade refinement of the tracker's windows;
//! - [`patch_match`]: the tracker's patch correlation and block matching;
//! - [`hyperelastic`]: the FEM mechanics' element loop (internal forces and tangent of a Yeoh material);
//! - [`sparse_solve`]: the sparse symmetric solve of the FEM mechanics' Newton steps;
//! - [`splat`]: the bilinear splat of the B-mode simulator's complex point weights onto its grid;
//! - [`simd`]: the run-time choice of the vector instruction set of the warp and landing loops.
//!
//! No Python here: the pyo3 binding lives in the `usdeform-python` crate.

pub mod affine_lk;
pub mod anchored;
pub mod bspline;
pub mod compound;
pub mod crc64;
pub mod error;
pub mod field;
pub mod frame_correction;
pub mod holes;
pub mod hyperelastic;
pub mod lumen;
pub mod model;
pub mod patch_match;
pub mod quadratic;
pub mod simd;
pub mod sparse_solve;
pub mod splat;
pub mod stiffness;
pub mod terms;
pub mod warp;

pub use error::{KernelError, Result};
