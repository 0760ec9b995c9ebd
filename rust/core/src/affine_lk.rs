//! Affine Lucas-Kanade refinement of tracked windows: where a `(width, height)` window of `before`
//! lies in `after`, with a six-parameter affine warp of the window (the step and the local
//! displacement gradient), by inverse compositional Gauss-Newton (Baker & Matthews 2004, IJCV
//! 56:221) on zero-mean windows. The Python twin is `usdeform.reference.affine_lucas_kanade`.
//!
//! Each window is refined on its own (in parallel over windows, each serially), so the result is
//! the same for any thread count. Images are float32, sampled by exact bilinear interpolation with
//! the edge replicated beyond the frame; sums, the Hessian and its inverse are float64.

use nalgebra::{Matrix6, SymmetricEigen, Vector6};
use rayon::prelude::*;

use crate::error::{KernelError, Result};
use crate::simd::{compiled_for, Level, Simd};
use crate::terms::filled;

/// A float32 image of `rows x cols` pixels, C order.
#[derive(Debug, Clone, Copy)]
pub struct Image<'a> {
    pub pixels: &'a [f32],
    pub rows: usize,
    pub cols: usize,
}

impl Image<'_> {
    /// Whether `(x, y)` lies in `[0, cols - 1] x [0, rows - 1]` (false for NaN).
    #[inline]
    fn contains(&self, x: f64, y: f64) -> bool {
        x >= 0.0 && y >= 0.0 && x <= (self.cols - 1) as f64 && y <= (self.rows - 1) as f64
    }

    /// The bilinear sample at `(x, y)`, the edge replicated beyond the frame (as OpenCV's
    /// `BORDER_REPLICATE`): the position is clamped into the frame first (NaN to 0).
    #[inline(always)]
    fn sample(&self, x: f64, y: f64) -> f64 {
        self.interpolate(&Cell::at(x, y, self.rows, self.cols))
    }

    /// The bilinear interpolation in `cell` (of an image of this one's size).
    #[inline(always)]
    fn interpolate(&self, cell: &Cell) -> f64 {
        debug_assert!(cell.corner + cell.step_y + cell.step_x < self.pixels.len());
        // SAFETY: a cell of `Cell::at` lies in its `rows x cols` frame (its lower-right pixel is at
        // most the last), and every image here holds `rows * cols` pixels (`check_inputs`).
        let at = |index: usize| f64::from(unsafe { *self.pixels.get_unchecked(index) });
        let (upper_left, upper_right) = (at(cell.corner), at(cell.corner + cell.step_x));
        let lower = cell.corner + cell.step_y;
        let (lower_left, lower_right) = (at(lower), at(lower + cell.step_x));
        let upper = upper_left + (upper_right - upper_left) * cell.fx;
        let lower = lower_left + (lower_right - lower_left) * cell.fx;
        upper + (lower - upper) * cell.fy
    }
}

/// Where a bilinear sample of a `rows x cols` image reads: the flat index of the upper-left pixel of
/// its cell, the steps to the right and lower pixels, and the fractions across the cell.
struct Cell {
    corner: usize,
    step_x: usize,
    step_y: usize,
    fx: f64,
    fy: f64,
}

impl Cell {
    /// The cell of `(x, y)` clamped into the frame (NaN to 0): the edge replicated beyond it.
    #[inline(always)]
    fn at(x: f64, y: f64, rows: usize, cols: usize) -> Cell {
        let x = x.max(0.0).min((cols - 1) as f64);
        let y = y.max(0.0).min((rows - 1) as f64);
        // At most one pixel before the last along each axis (0 along an axis of one pixel, where
        // the cell has no second pixel: step 0).
        // SAFETY: 0 <= x <= cols - 1 and 0 <= y <= rows - 1 after the clamp (`max` maps NaN to 0),
        // so both truncate to their floor within i64 (a slice holds fewer than 2^63 pixels);
        // unchecked, the conversion is one instruction (and i64 to f64 another, where usize to f64
        // takes several).
        let (left, top) = unsafe { (x.to_int_unchecked::<i64>(), y.to_int_unchecked::<i64>()) };
        let left = left.min(cols.saturating_sub(2) as i64);
        let top = top.min(rows.saturating_sub(2) as i64);
        Cell {
            corner: top as usize * cols + left as usize,
            step_x: usize::from(cols > 1),
            step_y: if rows > 1 { cols } else { 0 },
            fx: x - left as f64,
            fy: y - top as f64,
        }
    }
}

/// The images of one refinement, all `rows x cols`: the template frame `before`, its x and y
/// gradients (pixel units, e.g. OpenCV's Scharr scaled by 1/32) and the frame `after` searched.
#[derive(Debug, Clone, Copy)]
pub struct TrackingImages<'a> {
    pub before: Image<'a>,
    pub gradient_x: Image<'a>,
    pub gradient_y: Image<'a>,
    pub after: Image<'a>,
}

/// The window and the stopping rule: `window` is `(width, height)`, odd sides >= 3; the iteration
/// stops after `max_iterations` steps or once both components of the translation update are
/// below `epsilon` pixels (OpenCV's `TERM_CRITERIA_COUNT | TERM_CRITERIA_EPS`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AffineSettings {
    pub window: [usize; 2],
    pub max_iterations: usize,
    pub epsilon: f64,
}

/// The refinement of `N` windows: `tracked` the positions in `after` (x, y; `initial` where not
/// ok), `ok` where the window's texture determines all six parameters, the result is finite and
/// moved less than half the window's smaller side from `initial`, and `correlation` the normalised
/// correlation of the template and its warped match (0 where not ok).
#[derive(Debug, Clone, PartialEq)]
pub struct AffineTracks {
    pub tracked: Vec<[f32; 2]>,
    pub ok: Vec<bool>,
    pub correlation: Vec<f64>,
}

/// Smallest eigenvalue of a determined Hessian, relative to its largest.
const DETERMINED_RATIO: f64 = 1e-6;

/// Refine each window of `before` centred on `start[i]` (x, y), starting in `after` at
/// `initial[i]`. The window is cut where it leaves `before` or, warped, `after` (its weights; the
/// Hessian is prepared again after a cut). A step that undoes the previous one (translation
/// within `epsilon`) is halved and ends the iteration, as in OpenCV's Lucas-Kanade.
pub fn affine_lucas_kanade(
    images: &TrackingImages,
    start: &[[f32; 2]],
    initial: &[[f32; 2]],
    settings: &AffineSettings,
) -> Result<AffineTracks> {
    check_inputs(images, start, initial, settings)?;
    let [width, height] = settings.window;
    let (half_width, half_height) = ((width / 2) as f64, (height / 2) as f64);
    let mut offsets = filled("window", width * height, [0.0; 2])?;
    for (index, offset) in offsets.iter_mut().enumerate() {
        *offset = [
            (index % width) as f64 - half_width,
            (index / width) as f64 - half_height,
        ];
    }
    let simd = Simd::detected();
    let windows = start
        .par_iter()
        .zip(initial)
        .map(|(&start, &initial)| match simd.level() {
            // SAFETY: a `Simd` of a level exists only where the CPU supports it.
            #[cfg(target_arch = "x86_64")]
            Level::Avx2 | Level::Avx512 => unsafe {
                refine_avx2(images, &offsets, start, initial, settings)
            },
            _ => refine(images, &offsets, start, initial, settings),
        })
        .collect::<Result<Vec<_>>>()?;
    let mut tracks = AffineTracks {
        tracked: Vec::with_capacity(windows.len()),
        ok: Vec::with_capacity(windows.len()),
        correlation: Vec::with_capacity(windows.len()),
    };
    for (tracked, ok, correlation) in windows {
        tracks.tracked.push(tracked);
        tracks.ok.push(ok);
        tracks.correlation.push(correlation);
    }
    Ok(tracks)
}

fn check_inputs(
    images: &TrackingImages,
    start: &[[f32; 2]],
    initial: &[[f32; 2]],
    settings: &AffineSettings,
) -> Result<()> {
    let (rows, cols) = (images.before.rows, images.before.cols);
    if rows == 0 || cols == 0 {
        return Err(KernelError::Empty { argument: "before" });
    }
    let named = [
        ("before", images.before),
        ("gradient_x", images.gradient_x),
        ("gradient_y", images.gradient_y),
        ("after", images.after),
    ];
    for (argument, image) in named {
        if image.rows != rows || image.cols != cols || image.pixels.len() != rows * cols {
            return Err(KernelError::Shape {
                argument,
                expected: format!("{rows} x {cols} pixels, as before"),
                got: format!(
                    "{} x {} ({} pixels)",
                    image.rows,
                    image.cols,
                    image.pixels.len()
                ),
            });
        }
        check_finite_f32(argument, image.pixels.iter().copied())?;
    }
    if initial.len() != start.len() {
        return Err(KernelError::Shape {
            argument: "initial",
            expected: format!("{} points, as start", start.len()),
            got: format!("{} points", initial.len()),
        });
    }
    check_finite_f32("start", start.iter().flatten().copied())?;
    check_finite_f32("initial", initial.iter().flatten().copied())?;
    if settings
        .window
        .iter()
        .any(|&side| side < 3 || side % 2 == 0 || side > MAX_WINDOW_SIDE)
    {
        return Err(KernelError::Value {
            argument: "window_px",
            message: format!(
                "expected odd (width, height) sides from 3 to {MAX_WINDOW_SIDE}, got {:?}",
                settings.window
            ),
        });
    }
    if !(settings.epsilon.is_finite() && settings.epsilon >= 0.0) {
        return Err(KernelError::Value {
            argument: "epsilon",
            message: format!(
                "expected a finite number >= 0 of pixels, got {}",
                settings.epsilon
            ),
        });
    }
    Ok(())
}

/// Largest window side: a window of 1025 x 1025 pixels needs 60 MB of scratch per thread.
pub const MAX_WINDOW_SIDE: usize = 1025;

/// Fails with [`KernelError::NonFinite`] at the first NaN or infinity (flat index).
fn check_finite_f32(argument: &'static str, values: impl Iterator<Item = f32>) -> Result<()> {
    match values.enumerate().find(|(_, v)| !v.is_finite()) {
        Some((index, _)) => Err(KernelError::NonFinite { argument, index }),
        None => Ok(()),
    }
}

/// An affine warp of window offsets into `after`: `[[a, b, c], [d, e, f]]`, (x, y) -> (a x + b y + c,
/// d x + e y + f).
type Warp = [[f64; 3]; 2];

/// One window under refinement: its samples, weights and Gauss-Newton state.
struct Window<'a> {
    images: &'a TrackingImages<'a>,
    /// (x, y) offset of each pixel from the window's centre, row by row.
    offsets: &'a [[f64; 2]],
    /// The number of pixels in a row of the window.
    width: usize,
    /// `before` and its gradients sampled at the window's pixels.
    sampled: Vec<f64>,
    gradient_x: Vec<f64>,
    gradient_y: Vec<f64>,
    /// Whether each pixel is in the window (not cut).
    weight: Vec<bool>,
    /// The number of weighted pixels (at least 1).
    count: f64,
    /// The zero-mean template (0 where cut).
    template: Vec<f64>,
    /// `after` sampled at the warped window's pixels (0 where cut), as is: not zero mean.
    matched: Vec<f64>,
    inverse_hessian: Matrix6<f64>,
    determined: bool,
}

/// Adds `value` times 1, x and y to `sums`. The steepest-descent vector of a pixel at offset (x, y)
/// is gx and gy times 1, x and y (parameters dx, d(dx)/dx, d(dx)/dy, dy, d(dy)/dx, d(dy)/dy in this
/// order), so its sums against any value follow from these.
#[inline]
fn linear_sums(sums: &mut [f64; 3], value: f64, [x, y]: [f64; 2]) {
    sums[0] += value;
    sums[1] += value * x;
    sums[2] += value * y;
}

/// The six sums of a descent vector from its x and y halves.
fn join(x: [f64; 3], y: [f64; 3]) -> Vector6<f64> {
    Vector6::new(x[0], x[1], x[2], y[0], y[1], y[2])
}

impl Window<'_> {
    /// `values` minus their mean over the weighted pixels, 0 where cut (in place).
    #[inline(always)]
    fn zero_mean(weight: &[bool], count: f64, values: &mut [f64]) {
        let sum: f64 = values
            .iter()
            .zip(weight)
            .filter(|(_, &w)| w)
            .map(|(v, _)| v)
            .sum();
        let mean = sum / count;
        for (value, &w) in values.iter_mut().zip(weight) {
            *value = if w { *value - mean } else { 0.0 };
        }
    }

    /// The template and the inverse Gauss-Newton Hessian of the weighted pixels.
    #[inline(always)]
    fn prepare(&mut self) {
        let weighted = self.weight.iter().filter(|&&w| w).count();
        self.count = (weighted as f64).max(1.0);
        self.template.copy_from_slice(&self.sampled);
        Self::zero_mean(&self.weight, self.count, &mut self.template);
        // The Hessian's 3 x 3 blocks are sums of gx gx, gx gy and gy gy times the products of 1, x
        // and y: the monomials 1, x, y, x^2, xy, y^2.
        let mut monomials = [[0.0; 6]; 3];
        let (mut sum_x, mut sum_y) = ([0.0; 3], [0.0; 3]);
        let pixels = self
            .offsets
            .iter()
            .zip(&self.weight)
            .zip(self.gradient_x.iter().zip(&self.gradient_y));
        for ((&offset, &w), (&gx, &gy)) in pixels {
            if w {
                let [x, y] = offset;
                for (sums, product) in monomials.iter_mut().zip([gx * gx, gx * gy, gy * gy]) {
                    let (px, py) = (product * x, product * y);
                    sums[0] += product;
                    sums[1] += px;
                    sums[2] += py;
                    sums[3] += px * x;
                    sums[4] += px * y;
                    sums[5] += py * y;
                }
                linear_sums(&mut sum_x, gx, offset);
                linear_sums(&mut sum_y, gy, offset);
            }
        }
        const MONOMIAL: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];
        let mut hessian = Matrix6::<f64>::zeros();
        for i in 0..3 {
            for j in 0..3 {
                let m = MONOMIAL[i][j];
                hessian[(i, j)] = monomials[0][m];
                hessian[(i, j + 3)] = monomials[1][m];
                hessian[(i + 3, j)] = monomials[1][m];
                hessian[(i + 3, j + 3)] = monomials[2][m];
            }
        }
        // Zero-mean windows: remove the part of the descent images a change of brightness explains.
        let descent_sum = join(sum_x, sum_y);
        hessian -= descent_sum * descent_sum.transpose() / self.count;
        self.determined = false;
        self.inverse_hessian = Matrix6::identity();
        if let Some(eigen) = SymmetricEigen::try_new(hessian, f64::EPSILON, 1000) {
            let values = eigen.eigenvalues;
            if values.min() > DETERMINED_RATIO * values.max().max(1e-12) {
                if let Some(inverse) = hessian.try_inverse() {
                    self.inverse_hessian = inverse;
                    self.determined = true;
                }
            }
        }
    }

    /// Cut the window where, warped, it leaves `after` (and prepare it again if it was cut). Only a
    /// window with a corner near or beyond the edge can be cut: an affine window's extreme points
    /// are its corners.
    #[inline(always)]
    fn cut(&mut self, warp: &Warp) {
        // A copy: its size stays in registers across the stores to `weight`.
        let after = self.images.after;
        let [[a, b, c], [d, e, f]] = *warp;
        let (first, last) = (self.offsets[0], self.offsets[self.offsets.len() - 1]);
        let margin = 1e-6;
        let (max_x, max_y) = (
            (after.cols - 1) as f64 - margin,
            (after.rows - 1) as f64 - margin,
        );
        let clear = [first[0], last[0]].iter().all(|&x| {
            [first[1], last[1]].iter().all(|&y| {
                let (moved_x, moved_y) = (a * x + b * y + c, d * x + e * y + f);
                moved_x >= margin && moved_y >= margin && moved_x <= max_x && moved_y <= max_y
            })
        });
        if clear {
            return;
        }
        let mut cut = false;
        for (weight, &[x, y]) in self.weight.iter_mut().zip(self.offsets) {
            if *weight && !after.contains(a * x + b * y + c, d * x + e * y + f) {
                *weight = false;
                cut = true;
            }
        }
        if cut {
            self.prepare();
        }
    }

    /// The Gauss-Newton gradient at `warp`: the sum of the descent vectors times the zero-mean
    /// warped window minus the template, after cutting the window where it left `after`. Cut pixels
    /// are skipped: their difference is 0, and adding 0 leaves the sums as they are.
    #[inline(always)]
    fn gradient(&mut self, warp: &Warp) -> Vector6<f64> {
        let mean = self.sample_warped(warp);
        let (mut along_x, mut along_y) = ([0.0; 3], [0.0; 3]);
        let pixels = self
            .offsets
            .iter()
            .zip(&self.weight)
            .zip(self.matched.iter().zip(&self.template))
            .zip(self.gradient_x.iter().zip(&self.gradient_y));
        for (((&offset, &w), (&matched, &template)), (&gx, &gy)) in pixels {
            if w {
                let difference = (matched - mean) - template;
                linear_sums(&mut along_x, gx * difference, offset);
                linear_sums(&mut along_y, gy * difference, offset);
            }
        }
        join(along_x, along_y)
    }

    /// The normalised correlation of the template and the zero-mean window warped into `after`
    /// (0 where cut), after cutting the window where it left `after`: the three sums in one pass.
    #[inline(always)]
    fn correlation(&mut self, warp: &Warp) -> f64 {
        let mean = self.sample_warped(warp);
        let (mut products, mut template_norm, mut matched_norm) = (-0.0, -0.0, -0.0);
        let pixels = self.template.iter().zip(&self.matched).zip(&self.weight);
        for ((&template, &matched), &w) in pixels {
            let matched = if w { matched - mean } else { 0.0 };
            products += template * matched;
            template_norm += template * template;
            matched_norm += matched * matched;
        }
        let norms = (template_norm * matched_norm).sqrt();
        products / norms.max(1e-12)
    }

    /// `after` sampled at the warped window's pixels into `matched` (0 where cut), after cutting the
    /// window where it left `after`; returns their mean over the weighted pixels. Row by row: the
    /// row's terms of the warp (`b y`, `e y`) are computed once.
    #[inline(always)]
    fn sample_warped(&mut self, warp: &Warp) -> f64 {
        self.cut(warp);
        // A copy: its size stays in registers across the stores to `matched`.
        let after = self.images.after;
        let [[a, b, c], [d, e, f]] = *warp;
        let mut sum = -0.0;
        let rows = self
            .offsets
            .chunks_exact(self.width)
            .zip(self.matched.chunks_exact_mut(self.width))
            .zip(self.weight.chunks_exact(self.width));
        for ((offsets, matched), weight) in rows {
            let y = offsets[0][1];
            let (by, ey) = (b * y, e * y);
            for ((&[x, _], value), &w) in offsets.iter().zip(matched).zip(weight) {
                *value = if w {
                    let sample = after.sample(a * x + by + c, d * x + ey + f);
                    sum += sample;
                    sample
                } else {
                    0.0
                };
            }
        }
        sum / self.count
    }
}

compiled_for!(
    fn refine(
        images: &TrackingImages,
        offsets: &[[f64; 2]],
        start: [f32; 2],
        initial: [f32; 2],
        settings: &AffineSettings,
    ) -> Result<([f32; 2], bool, f64)>;
    refine_avx2: "avx2",
);

/// The (x, y) position of one refined window, whether it is ok, and its correlation.
#[inline(always)]
fn refine(
    images: &TrackingImages,
    offsets: &[[f64; 2]],
    start: [f32; 2],
    initial: [f32; 2],
    settings: &AffineSettings,
) -> Result<([f32; 2], bool, f64)> {
    let n = offsets.len();
    let (start_x, start_y) = (f64::from(start[0]), f64::from(start[1]));
    let (initial_x, initial_y) = (f64::from(initial[0]), f64::from(initial[1]));
    let mut window = Window {
        images,
        offsets,
        width: settings.window[0],
        sampled: filled("window", n, 0.0)?,
        gradient_x: filled("window", n, 0.0)?,
        gradient_y: filled("window", n, 0.0)?,
        weight: filled("window", n, false)?,
        count: 1.0,
        template: filled("window", n, 0.0)?,
        matched: filled("window", n, 0.0)?,
        inverse_hessian: Matrix6::identity(),
        determined: false,
    };
    // Copies: their sizes and pixel pointers stay in registers across the stores to the window.
    let TrackingImages {
        before,
        gradient_x,
        gradient_y,
        after,
    } = *images;
    let pixels = offsets
        .iter()
        .zip(&mut window.weight)
        .zip(window.sampled.iter_mut())
        .zip(
            window
                .gradient_x
                .iter_mut()
                .zip(window.gradient_y.iter_mut()),
        );
    for (((&[x, y], weight), sampled), (sampled_gx, sampled_gy)) in pixels {
        let (template_x, template_y) = (start_x + x, start_y + y);
        let cell = Cell::at(template_x, template_y, before.rows, before.cols);
        *sampled = before.interpolate(&cell);
        *sampled_gx = gradient_x.interpolate(&cell);
        *sampled_gy = gradient_y.interpolate(&cell);
        *weight =
            before.contains(template_x, template_y) && after.contains(initial_x + x, initial_y + y);
    }
    window.prepare();
    let mut warp: Warp = [[1.0, 0.0, initial_x], [0.0, 1.0, initial_y]];
    let mut previous = Vector6::<f64>::zeros();
    let epsilon = settings.epsilon;
    for _ in 0..settings.max_iterations {
        if !window.determined {
            break;
        }
        let gradient = window.gradient(&warp);
        if !window.determined {
            break; // cut down to a window that no longer determines the warp: not ok
        }
        let mut update = window.inverse_hessian * gradient;
        // A step that undoes the previous one oscillates about the optimum: take half of it and stop
        // (as OpenCV's Lucas-Kanade does).
        let oscillates =
            (update[0] + previous[0]).abs() < epsilon && (update[3] + previous[3]).abs() < epsilon;
        if oscillates {
            update *= 0.5;
        }
        warp = composed_with_inverse(&warp, &update);
        previous = update;
        if oscillates || !(update[0].abs() >= epsilon || update[3].abs() >= epsilon) {
            break;
        }
    }
    let tracked = [warp[0][2] as f32, warp[1][2] as f32];
    let moved = (tracked[0] - initial[0])
        .abs()
        .max((tracked[1] - initial[1]).abs());
    let [width, height] = settings.window;
    let ok = window.determined
        && tracked.iter().all(|v| v.is_finite())
        && f64::from(moved) < width.min(height) as f64 / 2.0;
    if !ok {
        return Ok((initial, false, 0.0));
    }
    Ok((tracked, true, window.correlation(&warp)))
}

/// `warp` composed with the inverse of the increment `[[1 + p1, p2, p0], [p4, 1 + p5, p3]]`
/// (closed form): the inverse compositional update.
fn composed_with_inverse(warp: &Warp, p: &Vector6<f64>) -> Warp {
    let [[l00, l01], [l10, l11]] = [[1.0 + p[1], p[2]], [p[4], 1.0 + p[5]]];
    let determinant = l00 * l11 - l01 * l10;
    let inverse = [
        [l11 / determinant, -l01 / determinant],
        [-l10 / determinant, l00 / determinant],
    ];
    let shift = [
        -(inverse[0][0] * p[0] + inverse[0][1] * p[3]),
        -(inverse[1][0] * p[0] + inverse[1][1] * p[3]),
    ];
    let mut out = [[0.0; 3]; 2];
    for (out, row) in out.iter_mut().zip(warp) {
        for column in 0..2 {
            out[column] = row[0] * inverse[0][column] + row[1] * inverse[1][column];
        }
        out[2] = row[0] * shift[0] + row[1] * shift[1] + row[2];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pseudo-random numbers in [0, 1) for the tests (a 64-bit LCG, high bits).
    fn uniform(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A smooth random texture: a sum of random plane waves (periods 12-30 px), as a function.
    fn texture(seed: u64) -> impl Fn(f64, f64) -> f64 {
        let mut state = seed;
        let waves: Vec<[f64; 4]> = (0..24)
            .map(|_| {
                let angle = uniform(&mut state) * std::f64::consts::TAU;
                let frequency = std::f64::consts::TAU / (12.0 + 18.0 * uniform(&mut state));
                [
                    frequency * angle.cos(),
                    frequency * angle.sin(),
                    uniform(&mut state) * std::f64::consts::TAU,
                    10.0 + 20.0 * uniform(&mut state),
                ]
            })
            .collect();
        move |x, y| {
            waves
                .iter()
                .map(|[kx, ky, phase, amplitude]| amplitude * (kx * x + ky * y + phase).sin())
                .sum::<f64>()
                + 100.0
        }
    }

    /// The texture sampled on a `rows x cols` grid, at (x, y) -> `map(x, y)`.
    fn rendered(
        rows: usize,
        cols: usize,
        value: &impl Fn(f64, f64) -> f64,
        map: impl Fn(f64, f64) -> (f64, f64),
    ) -> Vec<f32> {
        (0..rows * cols)
            .map(|i| {
                let (x, y) = map((i % cols) as f64, (i / cols) as f64);
                value(x, y) as f32
            })
            .collect()
    }

    /// Central-difference gradients of `pixels` (edge replicated).
    fn gradients(pixels: &[f32], rows: usize, cols: usize) -> (Vec<f32>, Vec<f32>) {
        let at = |r: usize, c: usize| pixels[r.min(rows - 1) * cols + c.min(cols - 1)];
        let (mut gx, mut gy) = (vec![0.0; rows * cols], vec![0.0; rows * cols]);
        for r in 0..rows {
            for c in 0..cols {
                gx[r * cols + c] = (at(r, c + 1) - at(r, c.saturating_sub(1))) / 2.0;
                gy[r * cols + c] = (at(r + 1, c) - at(r.saturating_sub(1), c)) / 2.0;
            }
        }
        (gx, gy)
    }

    fn image(pixels: &[f32], rows: usize, cols: usize) -> Image<'_> {
        Image { pixels, rows, cols }
    }

    const SETTINGS: AffineSettings = AffineSettings {
        window: [41, 35],
        max_iterations: 30,
        epsilon: 0.01,
    };

    /// `before` rendered from the texture, `after` the texture moved by the affine map `x' = A x + t`
    /// (`after(x') = before(x)`), and the central-difference gradients of `before`.
    struct Scene {
        rows: usize,
        cols: usize,
        before: Vec<f32>,
        gradient_x: Vec<f32>,
        gradient_y: Vec<f32>,
        after: Vec<f32>,
    }

    impl Scene {
        fn new(rows: usize, cols: usize, linear: [[f64; 2]; 2], shift: [f64; 2]) -> Scene {
            let value = texture(11);
            let before = rendered(rows, cols, &value, |x, y| (x, y));
            // after(x') = before(A^-1 (x' - t)).
            let determinant = linear[0][0] * linear[1][1] - linear[0][1] * linear[1][0];
            let after = rendered(rows, cols, &value, |x, y| {
                let (u, v) = (x - shift[0], y - shift[1]);
                (
                    (linear[1][1] * u - linear[0][1] * v) / determinant,
                    (-linear[1][0] * u + linear[0][0] * v) / determinant,
                )
            });
            let (gradient_x, gradient_y) = gradients(&before, rows, cols);
            Scene {
                rows,
                cols,
                before,
                gradient_x,
                gradient_y,
                after,
            }
        }

        fn images(&self) -> TrackingImages<'_> {
            let image = |pixels| image(pixels, self.rows, self.cols);
            TrackingImages {
                before: image(&self.before),
                gradient_x: image(&self.gradient_x),
                gradient_y: image(&self.gradient_y),
                after: image(&self.after),
            }
        }
    }

    #[test]
    fn a_known_affine_warp_is_recovered() {
        let linear = [[1.03, 0.02], [-0.015, 0.94]];
        let shift = [2.3, -1.7];
        let scene = Scene::new(96, 112, linear, shift);
        let points: Vec<[f32; 2]> = [[40.0, 45.0], [60.5, 50.25], [70.0, 40.0]]
            .into_iter()
            .collect();
        let expected: Vec<[f64; 2]> = points
            .iter()
            .map(|&[x, y]| {
                let (x, y) = (f64::from(x), f64::from(y));
                [
                    linear[0][0] * x + linear[0][1] * y + shift[0],
                    linear[1][0] * x + linear[1][1] * y + shift[1],
                ]
            })
            .collect();
        // Started 1.5 px off in both directions.
        let initial: Vec<[f32; 2]> = expected
            .iter()
            .map(|&[x, y]| [(x + 1.5) as f32, (y - 1.5) as f32])
            .collect();
        let settings = AffineSettings {
            epsilon: 1e-4,
            ..SETTINGS
        };
        let tracks = affine_lucas_kanade(&scene.images(), &points, &initial, &settings).unwrap();
        for (i, expected) in expected.iter().enumerate() {
            assert!(tracks.ok[i], "window {i}");
            let error = (f64::from(tracks.tracked[i][0]) - expected[0])
                .abs()
                .max((f64::from(tracks.tracked[i][1]) - expected[1]).abs());
            // What limits the match is bilinear interpolation, which blurs `after` a little (0.002-0.01 px
            // on this texture), not the solver.
            assert!(error < 0.01, "window {i}: error {error} px");
            assert!(tracks.correlation[i] > 0.99, "{}", tracks.correlation[i]);
        }
    }

    #[test]
    fn a_window_at_the_frame_edge_is_cut_and_still_tracked() {
        let linear = [[1.0, 0.0], [0.0, 0.97]];
        let shift = [0.6, -0.8];
        let scene = Scene::new(80, 90, linear, shift);
        // Half of the window lies left of the frame, its lower part below it; started 1 px off.
        let points = [[3.0f32, 76.0f32], [0.0, 40.0]];
        let truth: Vec<[f32; 2]> = points
            .iter()
            .map(|&[x, y]| [x + shift[0] as f32, 0.97 * y + shift[1] as f32])
            .collect();
        let initial: Vec<[f32; 2]> = truth.iter().map(|&[x, y]| [x + 0.8, y - 0.6]).collect();
        let tracks = affine_lucas_kanade(&scene.images(), &points, &initial, &SETTINGS).unwrap();
        for (i, (tracked, truth)) in tracks.tracked.iter().zip(&truth).enumerate() {
            assert!(tracks.ok[i], "window {i}");
            let error = (tracked[0] - truth[0])
                .abs()
                .max((tracked[1] - truth[1]).abs());
            assert!(error < 0.05, "window {i}: error {error} px");
        }
        // A window wholly outside the frame has nothing to track.
        let far = affine_lucas_kanade(
            &scene.images(),
            &[[-30.0, 40.0]],
            &[[-30.0, 40.0]],
            &SETTINGS,
        )
        .unwrap();
        assert_eq!(far.ok, [false]);
        assert_eq!(far.tracked, [[-30.0, 40.0]]);
        assert_eq!(far.correlation, [0.0]);
    }

    #[test]
    fn an_untextured_window_is_not_ok() {
        let (rows, cols) = (40, 50);
        // Texture only on the left; the right half is flat, and a horizontal ramp only fixes x.
        let flat: Vec<f32> = (0..rows * cols)
            .map(|i| {
                if i % cols < 20 {
                    ((i * 37) % 11) as f32
                } else {
                    5.0
                }
            })
            .collect();
        let ramp: Vec<f32> = (0..rows * cols).map(|i| (i % cols) as f32).collect();
        for pixels in [&flat, &ramp] {
            let (gx, gy) = gradients(pixels, rows, cols);
            let image = |pixels| image(pixels, rows, cols);
            let images = TrackingImages {
                before: image(pixels),
                gradient_x: image(&gx),
                gradient_y: image(&gy),
                after: image(pixels),
            };
            let tracks =
                affine_lucas_kanade(&images, &[[38.0, 20.0]], &[[38.5, 20.0]], &SETTINGS).unwrap();
            assert_eq!(tracks.ok, [false]);
            assert_eq!(tracks.tracked, [[38.5, 20.0]]);
            assert_eq!(tracks.correlation, [0.0]);
        }
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_avx2_path_gives_the_baseline_results() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let scene = Scene::new(64, 64, [[1.03, 0.02], [-0.01, 0.94]], [0.7, 1.3]);
        let images = scene.images();
        let settings = AffineSettings {
            window: [11, 9],
            ..SETTINGS
        };
        let offsets: Vec<[f64; 2]> = (0..11 * 9)
            .map(|index| [(index % 11) as f64 - 5.0, (index / 11) as f64 - 4.0])
            .collect();
        let mut state = 5;
        for _ in 0..200 {
            let start = [
                (uniform(&mut state) * 74.0 - 5.0) as f32,
                (uniform(&mut state) * 74.0 - 5.0) as f32,
            ];
            let initial = [start[0] + 1.0, start[1] + 0.8];
            let expected = refine(&images, &offsets, start, initial, &settings).unwrap();
            // SAFETY: AVX2 was detected above.
            let got = unsafe { refine_avx2(&images, &offsets, start, initial, &settings) }.unwrap();
            assert_eq!(expected.0.map(f32::to_bits), got.0.map(f32::to_bits));
            assert_eq!((expected.1, expected.2.to_bits()), (got.1, got.2.to_bits()));
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let scene = Scene::new(64, 64, [[1.02, 0.01], [0.0, 0.95]], [1.2, -0.4]);
        let mut state = 3;
        let points: Vec<[f32; 2]> = (0..40)
            .map(|_| {
                [
                    (uniform(&mut state) * 70.0 - 3.0) as f32,
                    (uniform(&mut state) * 70.0 - 3.0) as f32,
                ]
            })
            .collect();
        let initial: Vec<[f32; 2]> = points.iter().map(|&[x, y]| [x + 1.0, y - 0.5]).collect();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    affine_lucas_kanade(&scene.images(), &points, &initial, &SETTINGS).unwrap()
                })
        };
        let one = run(1);
        assert!(one.ok.iter().any(|&ok| ok));
        assert_eq!(one, run(3));
    }

    #[test]
    fn bad_inputs_are_errors_naming_the_argument() {
        let scene = Scene::new(20, 24, [[1.0, 0.0], [0.0, 1.0]], [0.0, 0.0]);
        let images = scene.images();
        let point = [[10.0f32, 10.0f32]];
        let argument = |result: Result<AffineTracks>| match result.unwrap_err() {
            KernelError::Shape { argument, .. }
            | KernelError::NonFinite { argument, .. }
            | KernelError::Empty { argument }
            | KernelError::Value { argument, .. } => argument,
            other => panic!("unexpected {other:?}"),
        };
        for window in [[4, 5], [1, 3], [3, 2], [MAX_WINDOW_SIDE + 2, 3]] {
            let settings = AffineSettings { window, ..SETTINGS };
            assert_eq!(
                argument(affine_lucas_kanade(&images, &point, &point, &settings)),
                "window_px"
            );
        }
        let settings = AffineSettings {
            epsilon: f64::NAN,
            ..SETTINGS
        };
        assert_eq!(
            argument(affine_lucas_kanade(&images, &point, &point, &settings)),
            "epsilon"
        );
        assert_eq!(
            argument(affine_lucas_kanade(&images, &point, &[], &SETTINGS)),
            "initial"
        );
        let nan = [[f32::NAN, 1.0]];
        assert_eq!(
            argument(affine_lucas_kanade(&images, &nan, &point, &SETTINGS)),
            "start"
        );
        assert_eq!(
            argument(affine_lucas_kanade(&images, &point, &nan, &SETTINGS)),
            "initial"
        );
        let mut bad = scene.after.clone();
        bad[7] = f32::INFINITY;
        let with_bad_after = TrackingImages {
            after: Image {
                pixels: &bad,
                ..images.after
            },
            ..images
        };
        assert_eq!(
            argument(affine_lucas_kanade(
                &with_bad_after,
                &point,
                &point,
                &SETTINGS
            )),
            "after"
        );
        let short = TrackingImages {
            gradient_y: Image {
                pixels: &scene.gradient_y[1..],
                ..images.gradient_y
            },
            ..images
        };
        assert_eq!(
            argument(affine_lucas_kanade(&short, &point, &point, &SETTINGS)),
            "gradient_y"
        );
        let empty = Image {
            pixels: &[],
            rows: 0,
            cols: 5,
        };
        let empty = TrackingImages {
            before: empty,
            gradient_x: empty,
            gradient_y: empty,
            after: empty,
        };
        assert_eq!(
            argument(affine_lucas_kanade(&empty, &point, &point, &SETTINGS)),
            "before"
        );
    }

    #[test]
    fn bilinear_samples_replicate_the_edge() {
        let pixels = [0.0f32, 1.0, 2.0, 10.0, 11.0, 12.0];
        let image = Image {
            pixels: &pixels,
            rows: 2,
            cols: 3,
        };
        assert_eq!(image.sample(0.5, 0.5), 5.5);
        assert_eq!(image.sample(2.0, 1.0), 12.0);
        assert_eq!(image.sample(-3.0, 0.25), 2.5);
        assert_eq!(image.sample(7.0, 9.0), 12.0);
        assert_eq!(image.sample(f64::NAN, 0.0), 0.0);
        let column = Image {
            pixels: &pixels[..2],
            rows: 2,
            cols: 1,
        };
        assert_eq!(column.sample(0.3, 0.5), 0.5);
    }
}
