//! Per-frame warping back to zero force (backward mapping, bilinear sampling).

use rayon::prelude::*;

use crate::error::{check_len, KernelError, Result};
use crate::field::FrameField;
use crate::frame_correction::{Correction, FrameCorrection};
use crate::simd::{compiled_for, dispatch, Simd};
use crate::terms::{filled, RowField};

/// A pixel type the kernels read and write (uint8 or float32 B-mode frames).
pub trait Pixel: Copy + Send + Sync + 'static {
    fn to_f64(self) -> f64;
    fn to_f32(self) -> f32;
    /// Convert an interpolated value back; uint8 rounds to nearest as `floor(value + 0.5)` and saturates.
    fn from_f64(value: f64) -> Self;
    /// An interpolated value as this type holds it, in float32: uint8 rounded as [`Pixel::from_f64`].
    fn rounded(value: f32) -> f32;
}

impl Pixel for u8 {
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn to_f32(self) -> f32 {
        self as f32
    }
    #[inline]
    fn from_f64(value: f64) -> Self {
        // `as` truncates toward zero and saturates (NaN -> 0), so for the non-negative values of
        // interpolated uint8 pixels this is floor(value + 0.5) without a libm call.
        (value + 0.5).max(0.0) as u8
    }
    #[inline]
    fn rounded(value: f32) -> f32 {
        (value + 0.5).floor().clamp(0.0, 255.0)
    }
}

impl Pixel for f32 {
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline]
    fn from_f64(value: f64) -> Self {
        value as f32
    }
    #[inline]
    fn rounded(value: f32) -> f32 {
        value
    }
}

/// A stack of `n_frames` frames of `rows x cols` pixels, C order.
#[derive(Debug, Clone, Copy)]
pub struct FrameStack<'a, P> {
    pub pixels: &'a [P],
    pub n_frames: usize,
    pub rows: usize,
    pub cols: usize,
}

impl<'a, P: Pixel> FrameStack<'a, P> {
    pub fn new(pixels: &'a [P], n_frames: usize, rows: usize, cols: usize) -> Result<Self> {
        if n_frames == 0 || rows == 0 || cols == 0 {
            return Err(KernelError::Empty { argument: "frames" });
        }
        if rows >= i32::MAX as usize || cols >= i32::MAX as usize {
            return Err(KernelError::Shape {
                argument: "frames",
                expected: format!("fewer than {} rows and columns", i32::MAX),
                got: format!("{rows} x {cols}"),
            });
        }
        let len = n_frames
            .checked_mul(rows)
            .and_then(|n| n.checked_mul(cols))
            .ok_or(KernelError::Allocation {
                argument: "frames",
                bytes: u128::MAX,
            })?;
        check_len("frames", pixels, len)?;
        Ok(FrameStack {
            pixels,
            n_frames,
            rows,
            cols,
        })
    }

    pub fn frame(&self, index: usize) -> &'a [P] {
        let size = self.rows * self.cols;
        &self.pixels[index * size..(index + 1) * size]
    }

    /// The frames `range` (a non-empty range within the stack) as a stack of their own.
    pub fn frames(&self, range: std::ops::Range<usize>) -> FrameStack<'a, P> {
        let size = self.rows * self.cols;
        FrameStack {
            pixels: &self.pixels[range.start * size..range.end * size],
            n_frames: range.len(),
            ..*self
        }
    }
}

/// One output row of a warp: the pixels, and per pixel whether it was sampled inside the frame
/// (false: the source lies outside and the pixel holds the fill value).
pub struct WarpedRow<'a, P> {
    pub pixels: &'a mut [P],
    pub valid: &'a mut [bool],
}

/// Per-thread buffers of [`warp_row`], reused from row to row (no allocation per row).
#[derive(Debug, Default)]
pub struct RowScratch {
    /// The B-spline row coefficients (one per `x` function).
    coefficients: Vec<[f64; 2]>,
    /// The row's displacement, one (lateral, axial) per column.
    displacements: Vec<[f64; 2]>,
}

/// Warp one row of a frame: output pixel (x, row) = frame sampled at (x, row) + D(x, row).
/// A B-spline row's or a vessel-anchored row's displacement is tabulated first, in a loop of its
/// own, so that the sampling loop reads it from memory instead of evaluating the basis between
/// gathers.
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn warp_row<P: Pixel>(
    frame: &[P],
    rows: usize,
    cols: usize,
    field: &FrameCorrection,
    row: usize,
    fill: P,
    out: WarpedRow<P>,
    scratch: &mut RowScratch,
) {
    match field {
        FrameCorrection {
            field: FrameField::Quadratic(polynomial),
            vessel: None,
        } => warp_row_dispatch(frame, rows, cols, &polynomial.row(row), row, fill, out),
        _ => {
            field.tabulate_row(
                row,
                0..cols,
                &mut scratch.coefficients,
                &mut scratch.displacements,
            );
            let tabulated = TabulatedRow(&scratch.displacements);
            warp_row_dispatch(frame, rows, cols, &tabulated, row, fill, out)
        }
    }
}

/// A row's displacement tabulated per column.
struct TabulatedRow<'a>(&'a [[f64; 2]]);

impl RowField for TabulatedRow<'_> {
    #[inline(always)]
    fn at(&self, col: usize) -> [f64; 2] {
        self.0[col]
    }
}

/// [`warp_row_with`] compiled for the widest instruction set the CPU has (see [`crate::simd`]).
#[inline(always)]
fn warp_row_dispatch<P: Pixel>(
    frame: &[P],
    rows: usize,
    cols: usize,
    row_field: &impl RowField,
    row: usize,
    fill: P,
    out: WarpedRow<P>,
) {
    warp_row_on(
        Simd::detected(),
        frame,
        rows,
        cols,
        row_field,
        row,
        fill,
        out,
    )
}

/// [`warp_row_with`] compiled for the instruction set `simd`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn warp_row_on<P: Pixel>(
    simd: Simd,
    frame: &[P],
    rows: usize,
    cols: usize,
    row_field: &impl RowField,
    row: usize,
    fill: P,
    out: WarpedRow<P>,
) {
    dispatch!(
        simd,
        [warp_row_with, warp_row_avx2, warp_row_avx512](
            frame, rows, cols, row_field, row, fill, out
        )
    )
}

compiled_for!(
    fn warp_row_with<P: Pixel>(
        frame: &[P],
        rows: usize,
        cols: usize,
        row_field: &impl RowField,
        row: usize,
        fill: P,
        out: WarpedRow<P>,
    );
    warp_row_avx2: "avx2",
    warp_row_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);

/// The sampling loop: a bilinear sample at (x, row) + D, valid where the source lies in
/// `[0, cols - 1] x [0, rows - 1]`. Branch-free (positions clamped into the frame, the fill
/// selected afterwards), with no call and no division, so that the compiler vectorises it.
#[inline(always)]
fn warp_row_with<P: Pixel>(
    frame: &[P],
    rows: usize,
    cols: usize,
    row_field: &impl RowField,
    row: usize,
    fill: P,
    out: WarpedRow<P>,
) {
    let (max_x, max_y) = ((cols - 1) as f64, (rows - 1) as f64);
    let (last_x0, last_y0) = (cols.saturating_sub(2), rows.saturating_sub(2));
    // Offsets of the right and lower neighbours (0 along an axis of one pixel).
    let right = usize::from(cols > 1);
    let down = if rows > 1 { cols } else { 0 };
    let row_position = row as f64;
    assert!(rows * cols <= frame.len(), "frame smaller than rows x cols");
    for (col, (out_pixel, valid)) in out.pixels.iter_mut().zip(out.valid).enumerate() {
        let [lateral, axial] = row_field.at(col);
        let x = col as f64 + lateral;
        let y = row_position + axial;
        let inside = x >= 0.0 && y >= 0.0 && x <= max_x && y <= max_y;
        // Inside, clamping changes nothing; outside, it keeps the reads in the frame.
        let (x, y) = (x.max(0.0).min(max_x), y.max(0.0).min(max_y));
        // SAFETY: 0 <= x <= cols - 1 and 0 <= y <= rows - 1 after the clamp (NaN cannot reach
        // here: `max` maps it to 0), and rows, cols < 2^31 (FrameStack::new), so both fit in i32.
        // Truncation is floor for them; the unchecked conversion is one packed instruction.
        let (x0, y0) = unsafe {
            (
                (x.to_int_unchecked::<i32>() as usize).min(last_x0),
                (y.to_int_unchecked::<i32>() as usize).min(last_y0),
            )
        };
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let index = y0 * cols + x0;
        // SAFETY: x0 + right <= cols - 1 and y0 * cols + down <= (rows - 1) * cols, so every index
        // is below rows * cols <= frame.len() (asserted above). Unchecked reads let the compiler
        // vectorise the loop.
        let [p00, p01, p10, p11] = unsafe {
            [
                *frame.get_unchecked(index),
                *frame.get_unchecked(index + right),
                *frame.get_unchecked(index + down),
                *frame.get_unchecked(index + down + right),
            ]
        };
        let top = p00.to_f64() * (1.0 - fx) + p01.to_f64() * fx;
        let bottom = p10.to_f64() * (1.0 - fx) + p11.to_f64() * fx;
        let value = P::from_f64(top * (1.0 - fy) + bottom * fy);
        *out_pixel = if inside { value } else { fill };
        *valid = inside;
    }
}

/// Warp every frame back to zero force: the frames (the input's shape) and the validity mask
/// (true where the pixel was sampled inside its frame). Rows run in parallel and each output pixel
/// depends on nothing else, so the result is the same for any thread count.
pub fn warp_frames<P: Pixel>(
    frames: &FrameStack<P>,
    correction: &Correction,
    fill: P,
) -> Result<(Vec<P>, Vec<bool>)> {
    let mut out = filled("frames", frames.pixels.len(), fill)?;
    let mut valid = filled("frames", frames.pixels.len(), false)?;
    warp_frames_into(frames, correction, fill, &mut out, &mut valid)?;
    Ok((out, valid))
}

/// [`warp_frames`] into `out` and `valid`, each of the frames' length.
pub fn warp_frames_into<P: Pixel>(
    frames: &FrameStack<P>,
    correction: &Correction,
    fill: P,
    out: &mut [P],
    valid: &mut [bool],
) -> Result<()> {
    let (rows, cols) = (frames.rows, frames.cols);
    check_len("out", out, frames.pixels.len())?;
    check_len("valid", valid, frames.pixels.len())?;
    let fields = correction.frame_fields(frames.n_frames, rows, cols)?;
    out.par_chunks_mut(cols)
        .zip(valid.par_chunks_mut(cols))
        .enumerate()
        .for_each_init(RowScratch::default, |scratch, (index, (pixels, valid))| {
            let (frame, row) = (index / rows, index % rows);
            warp_row(
                frames.frame(frame),
                rows,
                cols,
                &fields[frame],
                row,
                fill,
                WarpedRow { pixels, valid },
                scratch,
            );
        });
    Ok(())
}

/// Warp every frame by its own displacement field: output pixel (x, y) of frame i is frame i
/// sampled bilinearly at (x, y) + (lateral, axial), read from `displacements` (n_frames x 2 x rows x
/// cols, C order, pixels), with the sampling of [`warp_frames`]. For fields no model gives in
/// closed form (a vessel part that moves with each frame's lumen). Rows run in parallel and each
/// output pixel depends on nothing else, so the result is the same for any thread count.
pub fn warp_frames_by_field_into<P: Pixel>(
    frames: &FrameStack<P>,
    displacements: &[f64],
    fill: P,
    out: &mut [P],
    valid: &mut [bool],
) -> Result<()> {
    let (rows, cols) = (frames.rows, frames.cols);
    check_len("displacements", displacements, 2 * frames.pixels.len())?;
    check_len("out", out, frames.pixels.len())?;
    check_len("valid", valid, frames.pixels.len())?;
    let plane = rows * cols;
    out.par_chunks_mut(cols)
        .zip(valid.par_chunks_mut(cols))
        .enumerate()
        .for_each(|(index, (pixels, valid))| {
            let (frame, row) = (index / rows, index % rows);
            let lateral = frame * 2 * plane + row * cols;
            let axial = lateral + plane;
            let row_field = PlanarRow(
                &displacements[lateral..lateral + cols],
                &displacements[axial..axial + cols],
            );
            warp_row_dispatch(
                frames.frame(frame),
                rows,
                cols,
                &row_field,
                row,
                fill,
                WarpedRow { pixels, valid },
            );
        });
    Ok(())
}

/// A row's displacement as its lateral and its axial plane.
struct PlanarRow<'a>(&'a [f64], &'a [f64]);

impl RowField for PlanarRow<'_> {
    #[inline(always)]
    fn at(&self, col: usize) -> [f64; 2] {
        [self.0[col], self.1[col]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::SpatialModel;
    use crate::model::{Coupling, DeformationModel};
    use crate::quadratic::QuadraticModel;
    use crate::stiffness::StiffnessProfile;
    use crate::terms::{ForceTerms, Integral, Normalization};

    fn deformation(
        spatial: SpatialModel,
        n_intervals: usize,
        frame_shape: [usize; 2],
    ) -> DeformationModel {
        DeformationModel::new(
            spatial,
            Integral::over_force(n_intervals),
            Coupling::Stiffness,
            frame_shape,
        )
        .unwrap()
    }

    /// One frame at force 1 with the unit stiffness profile: the model's displacement itself.
    fn one_frame_at_unit_force(model: &DeformationModel) -> Correction<'_> {
        Correction {
            model,
            forces: &[1.0],
            profiles: &[StiffnessProfile::UNIT],
            vessel: None,
        }
    }

    fn model_with_constant_shift(dx: f64, dy: f64) -> SpatialModel {
        // Only the constant term: D = (dx, dy) * F_n for F_n = 1.
        let mut coefficients = [0.0; 20];
        coefficients[9] = dx;
        coefficients[19] = dy;
        SpatialModel::Quadratic(QuadraticModel::new(&coefficients, Normalization::UNIT).unwrap())
    }

    #[test]
    fn integer_shift_moves_pixels_and_fills_outside() {
        let (rows, cols) = (4, 5);
        let pixels: Vec<f32> = (0..rows * cols).map(|v| v as f32).collect();
        let frames = FrameStack::new(&pixels, 1, rows, cols).unwrap();
        let model = deformation(model_with_constant_shift(1.0, 2.0), 4, [rows, cols]);
        let correction = one_frame_at_unit_force(&model);
        let (out, valid) = warp_frames(&frames, &correction, -1.0).unwrap();
        for row in 0..rows {
            for col in 0..cols {
                let expected = if col + 1 < cols && row + 2 < rows {
                    ((row + 2) * cols + col + 1) as f32
                } else {
                    -1.0
                };
                assert_eq!(out[row * cols + col], expected, "pixel ({row}, {col})");
                assert_eq!(
                    valid[row * cols + col],
                    expected != -1.0,
                    "mask ({row}, {col})"
                );
            }
        }
    }

    #[test]
    fn a_given_field_warps_as_the_model_that_gives_it() {
        // Two frames, each by its own field: frame 1 by the model's (1, 2) shift, frame 0 by nothing.
        let (rows, cols) = (4, 5);
        let pixels: Vec<u8> = (0..2 * rows * cols).map(|v| (v * 7 % 251) as u8).collect();
        let frames = FrameStack::new(&pixels, 2, rows, cols).unwrap();
        let model = deformation(model_with_constant_shift(1.0, 2.0), 4, [rows, cols]);
        let correction = one_frame_at_unit_force(&model);
        let shifted = frames.frames(1..2);
        let (expected, expected_valid) = warp_frames(&shifted, &correction, 9).unwrap();
        let mut field = vec![0.0; 2 * rows * cols];
        field.extend(std::iter::repeat_n(1.0, rows * cols));
        field.extend(std::iter::repeat_n(2.0, rows * cols));
        let (mut out, mut valid) = (vec![0u8; 2 * rows * cols], vec![false; 2 * rows * cols]);
        warp_frames_by_field_into(&frames, &field, 9, &mut out, &mut valid).unwrap();
        assert_eq!(&out[..rows * cols], frames.frame(0));
        assert!(valid[..rows * cols].iter().all(|&v| v));
        assert_eq!(&out[rows * cols..], &expected[..]);
        assert_eq!(&valid[rows * cols..], &expected_valid[..]);
        let short = warp_frames_by_field_into(&frames, &field[1..], 9, &mut out, &mut valid);
        assert!(
            matches!(
                short,
                Err(KernelError::Shape {
                    argument: "displacements",
                    ..
                })
            ),
            "{short:?}"
        );
    }

    #[test]
    fn constant_bspline_warps_as_the_quadratic_constant_shift() {
        let (rows, cols, n_y, n_x) = (6, 9, 4, 5);
        let pixels: Vec<f32> = (0..rows * cols).map(|v| (v * 13 % 17) as f32).collect();
        let frames = FrameStack::new(&pixels, 1, rows, cols).unwrap();
        let size = n_y * n_x;
        let mut coefficients = vec![0.0; 6 * size];
        coefficients[..size].fill(1.25);
        coefficients[3 * size..4 * size].fill(-0.5);
        let SpatialModel::Quadratic(quadratic) = model_with_constant_shift(1.25, -0.5) else {
            unreachable!()
        };
        let spline =
            crate::bspline::BSplineModel::new(&coefficients, n_y, n_x, quadratic.normalization);
        let warp_with = |spatial: &SpatialModel| {
            let model = deformation(spatial.clone(), 4, [rows, cols]);
            let correction = one_frame_at_unit_force(&model);
            warp_frames(&frames, &correction, -1.0).unwrap().0
        };
        assert_eq!(
            warp_with(&SpatialModel::BSpline(spline.unwrap())),
            warp_with(&SpatialModel::Quadratic(quadratic))
        );
    }

    /// Pseudo-random numbers in [0, 1) for the tests (a 64-bit LCG, high bits).
    fn uniform(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    /// One row warped on the instruction set `simd`: the pixels and the validity flags.
    fn warped_row<P: Pixel>(
        simd: Simd,
        frame: &[P],
        (rows, cols): (usize, usize),
        row_field: &impl RowField,
        row: usize,
        fill: P,
    ) -> (Vec<P>, Vec<bool>) {
        let (mut pixels, mut valid) = (vec![fill; cols], vec![false; cols]);
        let out = WarpedRow {
            pixels: &mut pixels,
            valid: &mut valid,
        };
        warp_row_on(simd, frame, rows, cols, row_field, row, fill, out);
        (pixels, valid)
    }

    #[test]
    fn every_instruction_set_warps_identically() {
        let (rows, cols) = (23, 37);
        let mut state = 7;
        let frame: Vec<u8> = (0..rows * cols)
            .map(|_| (uniform(&mut state) * 256.0) as u8)
            .collect();
        let frame_f32: Vec<f32> = frame.iter().map(|&v| v as f32 * 1.37).collect();
        let levels = Simd::available();
        for trial in 0..50 {
            let mut coefficients = [0.0; 20];
            for c in coefficients.iter_mut() {
                *c = (uniform(&mut state) - 0.5) * 30.0;
            }
            let normalization = Normalization {
                x_scale: (cols - 1) as f64,
                y_scale: (rows - 1) as f64,
                ..Normalization::UNIT
            };
            let model = QuadraticModel::new(&coefficients, normalization).unwrap();
            let terms = ForceTerms {
                one: uniform(&mut state),
                h: uniform(&mut state),
                h2: uniform(&mut state),
            };
            let polynomial = model.frame_polynomial(terms);
            let row = trial % rows;
            let row_field = polynomial.row(row);
            let shape = (rows, cols);
            let baseline = warped_row(levels[0], &frame, shape, &row_field, row, 3);
            let baseline_f32 = warped_row(levels[0], &frame_f32, shape, &row_field, row, -1.0);
            assert!(baseline.1.iter().any(|&v| v) || trial > 0);
            for &simd in &levels[1..] {
                let (pixels, valid) = warped_row(simd, &frame, shape, &row_field, row, 3);
                assert_eq!((&pixels, &valid), (&baseline.0, &baseline.1), "{simd:?}");
                let (pixels, valid) = warped_row(simd, &frame_f32, shape, &row_field, row, -1.0);
                assert_eq!(valid, baseline_f32.1, "{simd:?}");
                let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&pixels), bits(&baseline_f32.0), "{simd:?}");
            }
        }
    }

    #[test]
    fn zero_force_is_the_identity() {
        let pixels: Vec<u8> = (0..60).map(|v| (v * 7 % 256) as u8).collect();
        let frames = FrameStack::new(&pixels, 3, 4, 5).unwrap();
        let model = deformation(model_with_constant_shift(3.0, -2.0), 8, [4, 5]);
        let profiles = [StiffnessProfile::UNIT; 3];
        let correction = Correction {
            model: &model,
            forces: &[0.0; 3],
            profiles: &profiles,
            vessel: None,
        };
        assert_eq!(warp_frames(&frames, &correction, 0).unwrap().0, pixels);
    }

    #[test]
    fn mismatched_forces_are_rejected() {
        let pixels = vec![0u8; 2 * 3 * 3];
        let frames = FrameStack::new(&pixels, 2, 3, 3).unwrap();
        let model = deformation(model_with_constant_shift(0.0, 0.0), 8, [3, 3]);
        let correction = Correction {
            model: &model,
            forces: &[1.0],
            profiles: &[StiffnessProfile::UNIT; 2],
            vessel: None,
        };
        let err = warp_frames(&frames, &correction, 0).unwrap_err();
        assert!(err.to_string().starts_with("forces:"), "{err}");
    }
}
