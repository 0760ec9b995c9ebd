//! The tracker's patch kernels: the normalised correlation of the patches around tracked points
//! ([`patch_correlation`], which checks each step) and the block matching of the coarse motion
//! ([`block_match`]). The Python twins are `usdeform.reference.patch_correlation` and
//! `usdeform.reference.block_match` (OpenCV's `remap` and `matchTemplate`).
//!
//! Each point or block is computed on its own (in parallel over them, each serially), so the result
//! is the same for any thread count. Sums are float64.

use rayon::prelude::*;

use crate::error::{KernelError, Result};
use crate::simd::{compiled_for, Level, Simd};

/// An image of `rows x cols` pixels of type `T`, C order.
#[derive(Debug, Clone, Copy)]
pub struct Image<'a, T> {
    pub pixels: &'a [T],
    pub rows: usize,
    pub cols: usize,
}

/// An 8-bit image.
pub type Image8<'a> = Image<'a, u8>;

/// A float32 image.
pub type Image32<'a> = Image<'a, f32>;

/// Where a bilinear sample reads along one axis: the two clamped indices (scaled by the axis'
/// stride) and the fraction across the cell.
#[derive(Debug, Clone, Copy, Default)]
struct Taps {
    low: usize,
    high: usize,
    fraction: f32,
}

impl Taps {
    /// The taps of coordinate `at` on an axis of `length` pixels `stride` apart, each index clamped
    /// into the axis (the edge replicated); NaN reads pixel 0.
    #[inline(always)]
    fn at(at: f32, length: usize, stride: usize) -> Taps {
        let floor = at.floor();
        // `as` saturates (and maps NaN to 0); the clamps bring both indices into the axis.
        let low = floor as i64;
        let clamped = |index: i64| index.clamp(0, length as i64 - 1) as usize * stride;
        Taps {
            low: clamped(low),
            high: clamped(low.saturating_add(1)),
            fraction: at - floor,
        }
    }
}

/// A float32 fused multiply-add, `a b + c` rounded once: the product of two float32 is exact in
/// float64, and so is its sum with `c` unless their exponents lie over 53 bits apart (a fraction
/// below 2^-30 of a pixel step), where the sum is rounded twice.
#[inline(always)]
fn fused(a: f32, b: f32, c: f32) -> f32 {
    (f64::from(a) * f64::from(b) + f64::from(c)) as f32
}

/// A value in [0, 2^23) rounded half to even, by adding and subtracting 2^23: one addition where
/// `round_ties_even` may be a call. Callers pass a bilinear sample of 8-bit pixels, in [0, 255].
#[inline(always)]
fn rounded(value: f32) -> u32 {
    const ROUNDING: f32 = 8_388_608.0;
    debug_assert!((0.0..ROUNDING).contains(&value));
    // SAFETY: a finite value in [0, 2^23) rounds to an integer in [0, 2^23], which u32 holds; the
    // unchecked conversion is one instruction where `as` adds the checks of a saturating one.
    unsafe { ((value + ROUNDING) - ROUNDING).to_int_unchecked::<u32>() }
}

/// The scratch of one patch: its columns' and rows' taps, the columns' fractions, its pixel rows
/// interpolated along x, and its samples.
#[derive(Debug, Clone, Default)]
struct PatchScratch {
    columns: Vec<Taps>,
    fractions: Vec<f32>,
    rows: Vec<Taps>,
    along_x: Vec<f32>,
    samples: Vec<u32>,
}

impl Image8<'_> {
    /// The `width x height` patch centred on `(x, y)` into `scratch.samples`, row by row, as
    /// OpenCV's `remap` (`INTER_LINEAR`, `BORDER_REPLICATE`) samples an 8-bit image: each column's
    /// and row's coordinate the centre plus the integer offset in float32; a float32 interpolation
    /// along x in the upper and the lower pixel row, then along y, each a fused multiply-add; the
    /// result rounded half to even (as `cv2.remap` on each of 3 million random samples). A pixel
    /// row shared by two patch rows is interpolated along x once (the same operation on the same
    /// values).
    #[inline(always)]
    fn patch(&self, [x, y]: [f32; 2], [width, height]: [usize; 2], scratch: &mut PatchScratch) {
        let (half_width, half_height) = ((width / 2) as f32, (height / 2) as f32);
        scratch.columns.clear();
        scratch.columns.extend(
            (0..width).map(|column| Taps::at(x + (column as f32 - half_width), self.cols, 1)),
        );
        scratch.rows.clear();
        scratch.rows.extend(
            (0..height).map(|row| Taps::at(y + (row as f32 - half_height), self.rows, self.cols)),
        );
        // The rows' taps never decrease: the pixel rows read lie from the first row's low tap to
        // the last row's high tap.
        let (first, last) = (scratch.rows[0].low, scratch.rows[height - 1].high);
        // Inside the frame the columns read consecutive pixels (each its low pixel and the next):
        // contiguous slices, which the compiler vectorises. The operations are the same.
        let leftmost = scratch.columns[0].low;
        let consecutive = scratch
            .columns
            .iter()
            .enumerate()
            .all(|(column, taps)| taps.low == leftmost + column && taps.high == taps.low + 1);
        scratch.fractions.clear();
        scratch
            .fractions
            .extend(scratch.columns.iter().map(|taps| taps.fraction));
        scratch.along_x.clear();
        for pixel_row in (first..=last).step_by(self.cols) {
            let pixels = &self.pixels[pixel_row..pixel_row + self.cols];
            if consecutive {
                let (lefts, rights) = (
                    &pixels[leftmost..leftmost + width],
                    &pixels[leftmost + 1..leftmost + 1 + width],
                );
                scratch
                    .along_x
                    .extend(lefts.iter().zip(rights).zip(&scratch.fractions).map(
                        |((&left, &right), &fraction)| {
                            let (left, right) = (f32::from(left), f32::from(right));
                            fused(fraction, right - left, left)
                        },
                    ));
            } else {
                scratch.along_x.extend(scratch.columns.iter().map(|taps| {
                    let (left, right) = (f32::from(pixels[taps.low]), f32::from(pixels[taps.high]));
                    fused(taps.fraction, right - left, left)
                }));
            }
        }
        scratch.samples.clear();
        for taps in &scratch.rows {
            let upper = &scratch.along_x[(taps.low - first) / self.cols * width..][..width];
            let lower = &scratch.along_x[(taps.high - first) / self.cols * width..][..width];
            scratch.samples.extend(
                upper
                    .iter()
                    .zip(lower)
                    .map(|(&upper, &lower)| rounded(fused(taps.fraction, lower - upper, upper))),
            );
        }
    }
}

impl Image32<'_> {
    /// The pixel at `(row, column)`, each clamped into the frame (the edge replicated).
    #[inline]
    fn replicated(&self, row: i64, column: i64) -> f64 {
        let row = row.clamp(0, self.rows as i64 - 1) as usize;
        let column = column.clamp(0, self.cols as i64 - 1) as usize;
        f64::from(self.pixels[row * self.cols + column])
    }
}

fn check_shape(argument: &'static str, pixels: usize, rows: usize, cols: usize) -> Result<()> {
    if rows == 0 || cols == 0 {
        return Err(KernelError::Empty { argument });
    }
    if pixels != rows * cols {
        return Err(KernelError::Shape {
            argument,
            expected: format!("{rows} x {cols} pixels"),
            got: format!("{pixels} pixels"),
        });
    }
    Ok(())
}

fn check_window(argument: &'static str, window: [usize; 2]) -> Result<()> {
    if window
        .iter()
        .any(|&side| side == 0 || side % 2 == 0 || side > MAX_WINDOW_SIDE)
    {
        return Err(KernelError::Value {
            argument,
            message: format!(
                "expected odd (width, height) sides from 1 to {MAX_WINDOW_SIDE}, got {window:?}"
            ),
        });
    }
    Ok(())
}

/// Largest window or patch side.
pub const MAX_WINDOW_SIDE: usize = 1025;

/// Samples summed in 32 bits before the sum is carried to 64: 65,536 products of 255^2 stay below
/// 2^32.
const SAMPLES_PER_SUM: usize = 65_536;

/// The normalised correlation of the `window` (width, height) patch of `before` centred on each
/// `start[i]` (x, y) and the patch of `after` centred on `end[i]`, their pixels sampled bilinearly
/// at the centre plus integer offsets and rounded to 8 bits, as OpenCV's `remap` samples them (see
/// [`Image8::patch`]). Zero-mean patches; 0 where either patch
/// is flat. Points must be finite.
pub fn patch_correlation(
    before: &Image8,
    after: &Image8,
    start: &[[f32; 2]],
    end: &[[f32; 2]],
    window: [usize; 2],
) -> Result<Vec<f64>> {
    check_shape("before", before.pixels.len(), before.rows, before.cols)?;
    check_shape("after", after.pixels.len(), before.rows, before.cols)?;
    if after.rows != before.rows || after.cols != before.cols {
        return Err(KernelError::Shape {
            argument: "after",
            expected: format!("{} x {} pixels, as before", before.rows, before.cols),
            got: format!("{} x {}", after.rows, after.cols),
        });
    }
    if end.len() != start.len() {
        return Err(KernelError::Shape {
            argument: "end",
            expected: format!("{} points, as start", start.len()),
            got: format!("{} points", end.len()),
        });
    }
    check_window("window_px", window)?;
    for (argument, points) in [("start", start), ("end", end)] {
        if let Some(index) = points.iter().flatten().position(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite { argument, index });
        }
    }
    let simd = Simd::detected();
    Ok(start
        .par_iter()
        .zip(end)
        .map_init(
            || [PatchScratch::default(), PatchScratch::default()],
            |scratch, (&start, &end)| match simd.level() {
                // SAFETY: a `Simd` of a level exists only where the CPU supports it.
                #[cfg(target_arch = "x86_64")]
                Level::Avx2 | Level::Avx512 => unsafe {
                    correlation_avx2(before, after, [start, end], window, scratch)
                },
                _ => correlation(before, after, [start, end], window, scratch),
            },
        )
        .collect())
}

/// The normalised correlation of one pair of patches (see [`patch_correlation`]).
#[inline(always)]
fn correlation(
    before: &Image8,
    after: &Image8,
    [start, end]: [[f32; 2]; 2],
    window: [usize; 2],
    [first, second]: &mut [PatchScratch; 2],
) -> f64 {
    let count = (window[0] * window[1]) as f64;
    before.patch(start, window, first);
    after.patch(end, window, second);
    let (mut first_sum, mut second_sum) = (0u64, 0u64);
    let (mut first_squares, mut second_squares, mut products) = (0u64, 0u64, 0u64);
    let chunks = first
        .samples
        .chunks(SAMPLES_PER_SUM)
        .zip(second.samples.chunks(SAMPLES_PER_SUM));
    for (first_chunk, second_chunk) in chunks {
        let (mut chunk_sums, mut chunk_squares, mut chunk_products) = ([0u32; 2], [0u32; 2], 0u32);
        for (&first, &second) in first_chunk.iter().zip(second_chunk) {
            chunk_sums[0] += first;
            chunk_sums[1] += second;
            chunk_squares[0] += first * first;
            chunk_squares[1] += second * second;
            chunk_products += first * second;
        }
        first_sum += u64::from(chunk_sums[0]);
        second_sum += u64::from(chunk_sums[1]);
        first_squares += u64::from(chunk_squares[0]);
        second_squares += u64::from(chunk_squares[1]);
        products += u64::from(chunk_products);
    }
    // Integer sums are exact; the centred sums follow in float64.
    let (first_sum, second_sum) = (first_sum as f64, second_sum as f64);
    let centred_products = products as f64 - first_sum * second_sum / count;
    let first_norm = first_squares as f64 - first_sum * first_sum / count;
    let second_norm = second_squares as f64 - second_sum * second_sum / count;
    let norms = (first_norm.max(0.0) * second_norm.max(0.0)).sqrt();
    if norms > 0.0 {
        centred_products / norms.max(1e-12)
    } else {
        0.0
    }
}

compiled_for!(
    fn correlation(
        before: &Image8,
        after: &Image8,
        points: [[f32; 2]; 2],
        window: [usize; 2],
        scratch: &mut [PatchScratch; 2],
    ) -> f64;
    correlation_avx2: "avx2",
);

/// The block matching of one pair: per node, the motion (dx, dy) of the best match, in pixels of
/// these images, its correlation, and whether it lies on the edge of the search range.
#[derive(Debug, Clone, PartialEq)]
pub struct BlockMatches {
    pub flow: Vec<[f32; 2]>,
    pub peak: Vec<f32>,
    pub on_edge: Vec<bool>,
}

/// Where each `patch x patch` block of `before` centred on the nodes `(x, y)` = `(half + j spacing,
/// half + i spacing)` (`half = patch / 2`, nodes whose block lies in the frame, row by row) lies in
/// `after`, searched over +-`search` pixels: the peak of the normalised correlation of zero-mean
/// blocks (OpenCV's `TM_CCOEFF_NORMED`, `after` replicated beyond its edges) refined by a parabola
/// through its neighbours along each axis (within half a pixel; none on the search range's edge).
/// A flat block of `before` scores 1 everywhere and a flat block of `after` 0, as in OpenCV. The
/// first of equal peaks in row-major order wins. Returns the nodes' (rows, cols) and matches.
pub fn block_match(
    before: &Image32,
    after: &Image32,
    patch: usize,
    spacing: usize,
    search: usize,
) -> Result<((usize, usize), BlockMatches)> {
    check_shape("before", before.pixels.len(), before.rows, before.cols)?;
    check_shape("after", after.pixels.len(), after.rows, after.cols)?;
    if after.rows != before.rows || after.cols != before.cols {
        return Err(KernelError::Shape {
            argument: "after",
            expected: format!("{} x {} pixels, as before", before.rows, before.cols),
            got: format!("{} x {}", after.rows, after.cols),
        });
    }
    check_window("patch", [patch, patch])?;
    if spacing == 0 {
        return Err(KernelError::Value {
            argument: "spacing",
            message: "expected a positive number of pixels, got 0".into(),
        });
    }
    if search > MAX_WINDOW_SIDE {
        return Err(KernelError::Value {
            argument: "search",
            message: format!("expected at most {MAX_WINDOW_SIDE} pixels, got {search}"),
        });
    }
    for (argument, image) in [("before", before), ("after", after)] {
        if let Some(index) = image.pixels.iter().position(|v| !v.is_finite()) {
            return Err(KernelError::NonFinite { argument, index });
        }
    }
    let half = patch / 2;
    let nodes = |length: usize| {
        if length < 2 * half + 1 {
            0
        } else {
            (length - 2 * half - 1) / spacing + 1
        }
    };
    let (node_rows, node_cols) = (nodes(before.rows), nodes(before.cols));
    let side = 2 * search + 1;
    let simd = Simd::detected();
    let matches: Vec<([f32; 2], f32, bool)> = (0..node_rows * node_cols)
        .into_par_iter()
        .map(|node| {
            let (y, x) = (
                half + (node / node_cols) * spacing,
                half + (node % node_cols) * spacing,
            );
            let corner = (x - half, y - half);
            match simd.level() {
                // SAFETY: a `Simd` of a level exists only where the CPU supports it.
                #[cfg(target_arch = "x86_64")]
                Level::Avx2 | Level::Avx512 => unsafe {
                    match_block_avx2(before, after, corner, patch, search, side)
                },
                _ => match_block(before, after, corner, patch, search, side),
            }
        })
        .collect();
    let mut result = BlockMatches {
        flow: Vec::with_capacity(matches.len()),
        peak: Vec::with_capacity(matches.len()),
        on_edge: Vec::with_capacity(matches.len()),
    };
    for (flow, peak, on_edge) in matches {
        result.flow.push(flow);
        result.peak.push(peak);
        result.on_edge.push(on_edge);
    }
    Ok(((node_rows, node_cols), result))
}

compiled_for!(
    fn match_block(
        before: &Image32,
        after: &Image32,
        corner: (usize, usize),
        patch: usize,
        search: usize,
        side: usize,
    ) -> ([f32; 2], f32, bool);
    match_block_avx2: "avx2",
);

/// One block (upper-left pixel `corner`) searched over `side x side` shifts: see [`block_match`].
#[inline(always)]
fn match_block(
    before: &Image32,
    after: &Image32,
    corner: (usize, usize),
    patch: usize,
    search: usize,
    side: usize,
) -> ([f32; 2], f32, bool) {
    let count = (patch * patch) as f64;
    let mut template = Vec::with_capacity(patch * patch);
    for row in 0..patch {
        let start = (corner.1 + row) * before.cols + corner.0;
        template.extend(
            before.pixels[start..start + patch]
                .iter()
                .map(|&v| f64::from(v)),
        );
    }
    let template_mean = template.iter().sum::<f64>() / count;
    template.iter_mut().for_each(|v| *v -= template_mean);
    let template_norm = template.iter().map(|v| v * v).sum::<f64>().sqrt();
    // The search region of `after`, replicated beyond the frame, as float64 rows.
    let region_side = patch + 2 * search;
    let mut region = Vec::with_capacity(region_side * region_side);
    let (left, top) = (
        corner.0 as i64 - search as i64,
        corner.1 as i64 - search as i64,
    );
    for row in 0..region_side as i64 {
        for column in 0..region_side as i64 {
            region.push(after.replicated(top + row, left + column));
        }
    }
    // Sums of the region's values and squares over every block-sized window, from summed-area tables.
    let table_side = region_side + 1;
    let (mut sums, mut squares) = (
        vec![0.0f64; table_side * table_side],
        vec![0.0f64; table_side * table_side],
    );
    for row in 0..region_side {
        let (mut row_sum, mut row_squares) = (0.0, 0.0);
        for column in 0..region_side {
            let value = region[row * region_side + column];
            row_sum += value;
            row_squares += value * value;
            let at = (row + 1) * table_side + column + 1;
            sums[at] = sums[at - table_side] + row_sum;
            squares[at] = squares[at - table_side] + row_squares;
        }
    }
    let window_sum = |table: &[f64], top: usize, left: usize| {
        table[(top + patch) * table_side + left + patch]
            - table[top * table_side + left + patch]
            - table[(top + patch) * table_side + left]
            + table[top * table_side + left]
    };
    let template_f32: Vec<f32> = template.iter().map(|&v| v as f32).collect();
    let region_f32: Vec<f32> = region.iter().map(|&v| v as f32).collect();
    let mut scores = vec![0.0f64; side * side];
    // A flat template (variance below float64's epsilon, as OpenCV tests it) matches everywhere.
    let flat_template = template_norm * template_norm / count < f64::EPSILON;
    for (shift, score) in scores.iter_mut().enumerate() {
        if flat_template {
            *score = 1.0;
            continue;
        }
        let (shift_y, shift_x) = (shift / side, shift % side);
        // Eight float32 partial sums per row: independent additions, which the compiler vectorises;
        // each row's sum is added in float64.
        let mut products = 0.0f64;
        for row in 0..patch {
            let window = &region_f32[(shift_y + row) * region_side + shift_x..][..patch];
            let weights = &template_f32[row * patch..][..patch];
            let (window_chunks, weight_chunks) = (window.chunks_exact(8), weights.chunks_exact(8));
            let tail = window_chunks
                .remainder()
                .iter()
                .zip(weight_chunks.remainder());
            let mut lanes = [0.0f32; 8];
            for (values, weights) in window_chunks.zip(weight_chunks) {
                for lane in 0..8 {
                    lanes[lane] += weights[lane] * values[lane];
                }
            }
            for (&value, &weight) in tail {
                lanes[0] += weight * value;
            }
            products += f64::from(lanes.iter().sum::<f32>());
        }
        let (sum, sum_squares) = (
            window_sum(&sums, shift_y, shift_x),
            window_sum(&squares, shift_y, shift_x),
        );
        let norm = (sum_squares - sum * sum / count).max(0.0).sqrt() * template_norm;
        *score = if products.abs() < norm {
            products / norm
        } else if products.abs() < norm * 1.125 {
            products.signum()
        } else {
            0.0
        };
    }
    let (best_index, best) =
        scores
            .iter()
            .enumerate()
            .fold((0, f64::NEG_INFINITY), |(index, best), (i, &score)| {
                if score > best {
                    (i, score)
                } else {
                    (index, best)
                }
            });
    let (row, column) = (best_index / side, best_index % side);
    let edge = 2 * search;
    let refined = |position: usize, below: f64, above: f64| {
        if 0 < position && position < edge {
            position as f64 + parabola_peak(below, best, above)
        } else {
            position as f64
        }
    };
    let dx = refined(
        column,
        scores[best_index.saturating_sub(1)],
        scores[(best_index + 1).min(scores.len() - 1)],
    );
    let dy = refined(
        row,
        scores[best_index.saturating_sub(side)],
        scores[(best_index + side).min(scores.len() - 1)],
    );
    let on_edge = row.min(column) == 0 || row.max(column) == edge;
    (
        [(dx - search as f64) as f32, (dy - search as f64) as f32],
        best as f32,
        on_edge,
    )
}

/// Subpixel offset (within +-0.5) of the maximum of a parabola through three equally spaced
/// samples; 0 where they do not curve down.
fn parabola_peak(below: f64, peak: f64, above: f64) -> f64 {
    let curvature = below - 2.0 * peak + above;
    if curvature >= 0.0 {
        0.0
    } else {
        (0.5 * (below - above) / curvature).clamp(-0.5, 0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn speckle(rows: usize, cols: usize, seed: u64) -> Vec<u8> {
        let mut state = seed;
        (0..rows * cols)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (state >> 56) as u8
            })
            .collect()
    }

    #[test]
    fn a_patch_correlates_fully_with_itself_and_its_shifted_copy() {
        let (rows, cols) = (40, 50);
        let pixels = speckle(rows, cols, 3);
        let shifted: Vec<u8> = (0..rows * cols)
            .map(|i| pixels[(i / cols) * cols + (i % cols).saturating_sub(3)])
            .collect();
        let before = Image8 {
            pixels: &pixels,
            rows,
            cols,
        };
        let after = Image8 {
            pixels: &shifted,
            rows,
            cols,
        };
        let correlation =
            patch_correlation(&before, &after, &[[20.0, 20.0]], &[[23.0, 20.0]], [9, 9]).unwrap();
        assert!((correlation[0] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn block_matching_finds_an_integer_shift() {
        let (rows, cols) = (60, 60);
        let pixels: Vec<f32> = speckle(rows, cols, 5).into_iter().map(f32::from).collect();
        let shifted: Vec<f32> = (0..rows * cols)
            .map(|i| {
                let (r, c) = (i / cols, i % cols);
                pixels[r.saturating_sub(2) * cols + c.saturating_sub(4)]
            })
            .collect();
        let before = Image32 {
            pixels: &pixels,
            rows,
            cols,
        };
        let after = Image32 {
            pixels: &shifted,
            rows,
            cols,
        };
        let ((node_rows, node_cols), matches) = block_match(&before, &after, 11, 12, 6).unwrap();
        assert_eq!((node_rows, node_cols), (5, 5));
        let centre = 2 * node_cols + 2;
        // The subpixel parabola through an asymmetric speckle peak lands within hundredths of a pixel of the
        // integer shift (4.0037 here), not on it.
        assert!((matches.flow[centre][0] - 4.0).abs() < 0.01);
        assert!((matches.flow[centre][1] - 2.0).abs() < 0.01);
        assert!(matches.peak[centre] > 0.999);
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_avx2_paths_give_the_baseline_results() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let (rows, cols) = (64, 72);
        let (first, second) = (speckle(rows, cols, 7), speckle(rows, cols, 8));
        let image = |pixels| Image8 { pixels, rows, cols };
        let (before, after) = (image(&first), image(&second));
        let mut state = 11u64;
        let mut coordinate = |length: usize| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            // From 8 pixels beyond one edge to 8 beyond the other: patches inside and cut by the edge.
            (state >> 40) as f32 / (1u64 << 24) as f32 * (length + 16) as f32 - 8.0
        };
        for _ in 0..500 {
            let points = [
                [coordinate(cols), coordinate(rows)],
                [coordinate(cols), coordinate(rows)],
            ];
            let (mut baseline, mut avx2) = Default::default();
            let expected = correlation(&before, &after, points, [9, 7], &mut baseline);
            // SAFETY: AVX2 was detected above.
            let got = unsafe { correlation_avx2(&before, &after, points, [9, 7], &mut avx2) };
            assert_eq!(expected.to_bits(), got.to_bits());
        }
        let (first, second): (Vec<f32>, Vec<f32>) = (
            first.iter().map(|&v| f32::from(v)).collect(),
            second.iter().map(|&v| f32::from(v)).collect(),
        );
        let image = |pixels| Image32 { pixels, rows, cols };
        let (before, after) = (image(&first), image(&second));
        for corner in [(0, 0), (20, 17), (50, 40)] {
            let expected = match_block(&before, &after, corner, 13, 6, 13);
            // SAFETY: AVX2 was detected above.
            let got = unsafe { match_block_avx2(&before, &after, corner, 13, 6, 13) };
            assert_eq!(expected, got);
        }
    }

    #[test]
    fn bad_windows_and_points_are_errors() {
        let pixels = vec![0u8; 16];
        let image = Image8 {
            pixels: &pixels,
            rows: 4,
            cols: 4,
        };
        assert!(patch_correlation(&image, &image, &[[1.0, 1.0]], &[[1.0, 1.0]], [4, 3]).is_err());
        assert!(
            patch_correlation(&image, &image, &[[f32::NAN, 1.0]], &[[1.0, 1.0]], [3, 3]).is_err()
        );
        assert!(patch_correlation(&image, &image, &[[1.0, 1.0]], &[], [3, 3]).is_err());
    }
}
