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
use crate::model::DeformationModel;
use crate::stiffness::StiffnessProfile;
use crate::terms::{zeroed, ForceTerms, Normalization};
use crate::warp::FrameCorrection;

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

/// The model's displacement `D(x, y, F)` (pixels) on the window `rows x cols` of its frame, with the
/// vessel part on `anchor` (None: the image part alone), shape (2, window rows, window columns).
pub fn anchored_field(
    model: &DeformationModel,
    part: &VesselPart,
    force_n: f64,
    profile: &StiffnessProfile,
    anchor: Option<Anchor>,
    rows: Range<usize>,
    cols: Range<usize>,
) -> Result<Vec<f64>> {
    let [frame_rows, frame_cols] = model.frame_shape;
    if rows.start >= rows.end
        || cols.start >= cols.end
        || rows.end > frame_rows
        || cols.end > frame_cols
    {
        return Err(KernelError::Value {
            argument: "window",
            message: format!(
                "expected non-empty rows and columns within the model's {frame_rows} x \
                 {frame_cols} frame, got rows {rows:?}, columns {cols:?}"
            ),
        });
    }
    let terms = model.frame_terms(force_n, profile, 0)?;
    let field = FrameCorrection {
        field: model
            .spatial
            .frame_fields(&[terms], frame_rows, frame_cols)
            .remove(0),
        vessel: anchor.map(|a| part.frame(terms, a, model.spatial.normalization(), frame_cols)),
    };
    let (height, width) = (rows.len(), cols.len());
    let mut out = zeroed("window", Some(2 * height * width))?;
    let (mut coefficients, mut displacements) = (Vec::new(), Vec::new());
    for (index, row) in rows.enumerate() {
        field.tabulate_row(row, cols.clone(), &mut coefficients, &mut displacements);
        for (k, [lateral, axial]) in displacements.iter().enumerate() {
            out[index * width + k] = *lateral;
            out[(height + index) * width + k] = *axial;
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bspline::BSplineModel;
    use crate::field::SpatialModel;
    use crate::model::Coupling;
    use crate::terms::Integral;

    fn model(rows: usize, cols: usize) -> DeformationModel {
        let normalization =
            Normalization::from_slice(&[cols as f64, rows as f64, 10.0, 5.0, 3.0, -2.0]).unwrap();
        let coefficients: Vec<f64> = (0..2 * 3 * 16).map(|i| (i as f64 * 0.7).sin()).collect();
        let spatial =
            SpatialModel::BSpline(BSplineModel::new(&coefficients, 4, 4, normalization).unwrap());
        DeformationModel::new(
            spatial,
            Integral::over_force(8),
            Coupling::Stiffness,
            [rows, cols],
        )
        .unwrap()
    }

    fn part(n: usize) -> VesselPart {
        let coefficients: Vec<f64> = (0..6 * n * n).map(|i| (i as f64 * 0.3).cos()).collect();
        VesselPart::new(&coefficients, n, 4.0, 2.0).unwrap()
    }

    #[test]
    fn vessel_part_vanishes_outside_its_window_and_a_window_is_a_cut_of_the_frame() {
        let (rows, cols) = (40, 48);
        let (model, part) = (model(rows, cols), part(3));
        let profile = StiffnessProfile::UNIT;
        let anchor = Anchor {
            centre_x: 20.3,
            centre_y: 17.6,
            radius: 5.0,
        };
        let with = |anchor, r: Range<usize>, c: Range<usize>| {
            anchored_field(&model, &part, 2.0, &profile, anchor, r, c).unwrap()
        };
        let (full, image) = (
            with(Some(anchor), 0..rows, 0..cols),
            with(None, 0..rows, 0..cols),
        );
        for row in 0..rows {
            for col in 0..cols {
                let inside = (row as f64 - 17.6).abs() <= 10.0 && (col as f64 - 20.3).abs() <= 10.0;
                let differs = (full[row * cols + col] - image[row * cols + col]).abs() > 0.0;
                assert!(inside || !differs, "({row}, {col})");
            }
        }
        assert_ne!(full, image);
        let window = with(Some(anchor), 5..30, 10..33);
        for (k, row) in (5..30).enumerate() {
            for (j, col) in (10..33).enumerate() {
                for c in 0..2 {
                    assert_eq!(
                        window[(c * 25 + k) * 23 + j],
                        full[(c * rows + row) * cols + col]
                    );
                }
            }
        }
    }

    #[test]
    fn bad_windows_and_anchors_are_rejected() {
        let (model, part) = (model(10, 10), part(2));
        let profile = StiffnessProfile::UNIT;
        let err = anchored_field(&model, &part, 1.0, &profile, None, 0..11, 0..5).unwrap_err();
        assert!(err.to_string().starts_with("window:"), "{err}");
        let err = Anchor::from_triples("anchors", &[1.0, 2.0, 0.0]).unwrap_err();
        assert!(err.to_string().starts_with("anchors:"), "{err}");
        assert!(VesselPart::new(&[0.0; 6], 1, -1.0, 2.0).is_err());
    }
}
