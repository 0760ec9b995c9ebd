//! The vessel part of a vessel-anchored model: a cubic B-spline on a square window that follows
//! each frame's lumen, added to the model's field in image coordinates.
//!
//! The window has the half-width `window_radii` lumen radii around the lumen's centre; pixel
//! `(x, y)` sits at the window coordinates `u = (x - cx) / w + 1/2`, `v = (y - cy) / w + 1/2` with
//! `w = 2 window_radii r`. The part is `sum_ij B_i(v) B_j(u) (a_ij I1 + b_ij Ih + c_ij Ih2)` per
//! component over the inner `n` functions of a clamped cubic basis of `n + 4` over [0, 1] (zero
//! outside the window), scaled by `r / reference_radius` and the model's output scales: the same
//! force terms as the image part ([`ForceTerms`]).

use std::ops::Range;

use crate::bspline::nonzero_basis;
use crate::error::{check_finite, check_len, KernelError, Result};
use crate::terms::{ForceTerms, Normalization};

/// A lumen in a frame: centre `(x, y)` and equivalent radius, pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    pub centre_x: f64,
    pub centre_y: f64,
    pub radius: f64,
}

impl Anchor {
    /// Anchors from `(x, y, radius)` triples (pixels): finite, radius positive.
    pub fn from_triples(argument: &'static str, values: &[f64]) -> Result<Vec<Anchor>> {
        check_finite(argument, values)?;
        values
            .chunks_exact(3)
            .enumerate()
            .map(|(index, triple)| {
                if triple[2] > 0.0 {
                    Ok(Anchor {
                        centre_x: triple[0],
                        centre_y: triple[1],
                        radius: triple[2],
                    })
                } else {
                    Err(KernelError::Value {
                        argument,
                        message: format!(
                            "the radius of anchor {index} must be positive, got {}",
                            triple[2]
                        ),
                    })
                }
            })
            .collect()
    }
}

/// The vessel part's coefficients (2, 3, n, n): component, force term (`1`, `h`, `h^2`), `y` and
/// `x` inner function; with the reference radius and the window's half-width in radii.
#[derive(Debug, Clone, PartialEq)]
pub struct VesselPart {
    coefficients: Vec<f64>,
    n_inner: usize,
    reference_radius: f64,
    window_radii: f64,
}

impl VesselPart {
    /// `coefficients` flat in the order (2, 3, n, n), `n >= 1`; `reference_radius` (pixels) and
    /// `window_radii` positive.
    pub fn new(
        coefficients: &[f64],
        n_inner: usize,
        reference_radius: f64,
        window_radii: f64,
    ) -> Result<Self> {
        if n_inner == 0 {
            return Err(KernelError::Empty {
                argument: "vessel_coefficients",
            });
        }
        check_len("vessel_coefficients", coefficients, 6 * n_inner * n_inner)?;
        check_finite("vessel_coefficients", coefficients)?;
        for (argument, value) in [
            ("reference_radius_px", reference_radius),
            ("window_radii", window_radii),
        ] {
            if !(value.is_finite() && value > 0.0) {
                return Err(KernelError::Value {
                    argument,
                    message: format!("expected a positive number, got {value}"),
                });
            }
        }
        Ok(VesselPart {
            coefficients: coefficients.to_vec(),
            n_inner,
            reference_radius,
            window_radii,
        })
    }

    /// The part of one frame placed on `anchor`, for its force terms, on a grid of `cols` columns.
    pub fn frame(
        &self,
        terms: ForceTerms,
        anchor: Anchor,
        normalization: &Normalization,
        cols: usize,
    ) -> FrameVessel {
        let n = self.n_inner;
        let size = n * n;
        let ratio = anchor.radius / self.reference_radius;
        let mut grid = vec![0.0; 2 * size];
        for (component, scale) in [normalization.lateral_scale, normalization.axial_scale]
            .into_iter()
            .enumerate()
        {
            let k = &self.coefficients[component * 3 * size..(component + 1) * 3 * size];
            let (one, h, h2) = (&k[..size], &k[size..2 * size], &k[2 * size..]);
            for (j, out) in grid[component * size..(component + 1) * size]
                .iter_mut()
                .enumerate()
            {
                *out = (one[j] * terms.one + h[j] * terms.h + h2[j] * terms.h2) * ratio * scale;
            }
        }
        let width = 2.0 * self.window_radii * anchor.radius;
        let columns = (0..cols)
            .filter_map(|col| {
                inner_basis((col as f64 - anchor.centre_x) / width + 0.5, n).map(|b| (col, b))
            })
            .collect();
        FrameVessel {
            grid,
            n_inner: n,
            columns,
            centre_y: anchor.centre_y,
            width,
        }
    }
}

/// The non-zero inner functions at window coordinate `u`: the first one's index among the `n_inner`
/// inner functions (may be below 0 or run past the end: those are left out) and the 4 values; None
/// outside [0, 1].
fn inner_basis(u: f64, n_inner: usize) -> Option<(isize, [f64; 4])> {
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let (first, values) = nonzero_basis(u, n_inner + 4);
    Some((first as isize - 2, values))
}

/// The vessel part of one frame: its coefficient grid (2, n, n) in pixels (force terms, radius
/// ratio and output scales applied) and the columns inside its window with their `x` functions.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameVessel {
    grid: Vec<f64>,
    n_inner: usize,
    columns: Vec<(usize, (isize, [f64; 4]))>,
    centre_y: f64,
    width: f64,
}

impl FrameVessel {
    /// Add the part along `row` to `out`, whose entry `k` is column `cols.start + k` (columns of
    /// `cols` only).
    #[inline(always)]
    pub fn add_row(&self, row: usize, cols: Range<usize>, out: &mut [[f64; 2]]) {
        let Some((first_y, weights_y)) = inner_basis(
            (row as f64 - self.centre_y) / self.width + 0.5,
            self.n_inner,
        ) else {
            return;
        };
        let n = self.n_inner;
        let size = n * n;
        // The y functions applied: one coefficient per x function and component, in `padded`
        // between `PADDING` zeros either side for the functions outside the inner ones (a
        // product with zero adds nothing to a sum begun at +0).
        let mut row_coefficients = [[0.0; 2]; 64];
        let mut heap = Vec::new();
        let padded: &mut [[f64; 2]] = if n + 2 * PADDING <= row_coefficients.len() {
            &mut row_coefficients[..n + 2 * PADDING]
        } else {
            heap.resize(n + 2 * PADDING, [0.0; 2]);
            &mut heap
        };
        let coefficients = &mut padded[PADDING..PADDING + n];
        for (offset, weight) in weights_y.iter().enumerate() {
            let Some(i) = inner_index(first_y + offset as isize, n) else {
                continue;
            };
            for component in 0..2 {
                let start = component * size + i * n;
                for (out, c) in coefficients.iter_mut().zip(&self.grid[start..start + n]) {
                    out[component] += weight * c;
                }
            }
        }
        // `columns` is in column order.
        let inside = self.columns.partition_point(|&(col, _)| col < cols.start)
            ..self.columns.partition_point(|&(col, _)| col < cols.end);
        for &(col, (first_x, weights_x)) in &self.columns[inside] {
            // `first_x` lies within [-PADDING, n - PADDING]: the 4 functions are within `padded`.
            let around = &padded[(first_x + PADDING as isize) as usize..][..4];
            let mut value = [0.0; 2];
            for (weight, c) in weights_x.iter().zip(around) {
                value[0] += weight * c[0];
                value[1] += weight * c[1];
            }
            let target = &mut out[col - cols.start];
            target[0] += value[0];
            target[1] += value[1];
        }
    }
}

/// Zeros either side of a row's inner coefficients in [`FrameVessel::add_row`]: the non-zero
/// functions at a point start at most this many before the first inner one.
const PADDING: usize = 2;

/// `index` as an inner function's index, None outside `0..n_inner`.
#[inline]
fn inner_index(index: isize, n_inner: usize) -> Option<usize> {
    usize::try_from(index).ok().filter(|&i| i < n_inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_anchors_and_vessel_parts_are_rejected() {
        let err = Anchor::from_triples("anchors", &[1.0, 2.0, 0.0]).unwrap_err();
        assert!(err.to_string().starts_with("anchors:"), "{err}");
        assert!(VesselPart::new(&[0.0; 6], 1, -1.0, 2.0).is_err());
    }
}
