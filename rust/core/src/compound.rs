//! Voxel compounding of tracked frames (PLUS-style "insert slice": nearest or trilinear splat;
//! mean, maximum or latest compounding; a coverage volume of summed splat weights).
//!
//! Scattering pixels into voxels races when done in parallel, so each batch of frames is split by
//! voxel plane instead: slabs of planes are filled in parallel, each skipping the rows whose plane
//! range (in closed form, from the row's ends) misses it, landing the others (a vectorised pass
//! giving each pixel's lowest plane and voxel) and splatting the pixels that reach it in (frame,
//! row, column) order. Every voxel therefore sees its updates in the same order as a serial loop,
//! and the volume is bit-identical for any thread count. On one thread that serial loop runs as
//! such.

use nalgebra::Matrix4;
use rayon::prelude::*;

use crate::error::{check_finite, check_len, KernelError, Result};
use crate::frame_correction::Correction;
use crate::simd::{compiled_for, dispatch, Simd};
use crate::terms::filled;
use crate::warp::{warp_row, FrameStack, Pixel, RowScratch, WarpedRow};

/// How a pixel is spread over voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interpolation {
    /// The pixel goes to the nearest voxel centre with weight 1.
    Nearest,
    /// The pixel is spread over the 8 surrounding voxels with trilinear weights.
    Linear,
}

/// How the values landing in one voxel are combined.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Compounding {
    /// Weighted mean of the values.
    Mean,
    /// Largest value. With [`Interpolation::Linear`] a pixel updates only the voxels it gives a
    /// trilinear weight of at least [`MAXIMUM_MIN_WEIGHT`], as PLUS's trilinear maximum does.
    Maximum,
    /// Value of the last pixel (in frame, then row, then column order) that reached the voxel.
    Latest,
}

/// Smallest trilinear weight with which a pixel updates a voxel under linear maximum compounding
/// (PLUS's vtkTrilinearInterpolation, MAXIMUM_COMPOUNDING_MODE: lower-weight corners are left alone,
/// value and coverage). Without it a voxel takes the brightest pixel within a whole voxel of it, and
/// PLUS's LN_MAXI reference volume correlates 0.83 with ours over all voxels instead of 0.997.
pub const MAXIMUM_MIN_WEIGHT: f64 = 0.125;

/// Accumulator bytes per voxel (value and weight as f32) plus the returned image and weight.
pub const BYTES_PER_VOXEL: u128 = 16;

/// Frames processed per counting-sort batch: fixed, so results never depend on the thread count.
pub const FRAMES_PER_BATCH: usize = 16;

/// Rows 0..3 of a 4x4 affine mapping pixel (column, row, 0, 1) to a continuous voxel index (i, j, k).
type PixelToIndex = [[f64; 4]; 3];

/// One batch of frames to insert: pixels, optional validity flags (same layout), frame shape and
/// each frame's pixel-to-index affine.
struct Batch<'a, P> {
    pixels: &'a [P],
    valid: Option<&'a [bool]>,
    rows: usize,
    cols: usize,
    affines: &'a [PixelToIndex],
}

/// Continuous voxel index (i, j, k) of pixel (`col`, `row`).
#[inline]
fn voxel_position(affine: &PixelToIndex, col: usize, row: usize) -> [f64; 3] {
    let (x, y) = (col as f64, row as f64);
    [
        affine[0][0] * x + affine[0][1] * y + affine[0][3],
        affine[1][0] * x + affine[1][1] * y + affine[1][3],
        affine[2][0] * x + affine[2][1] * y + affine[2][3],
    ]
}

/// `floor(x)` as an integer. Baseline x86-64 has no rounding instruction, so `f64::floor` is a
/// libm call; this is exact for |x| < 2^63 and several times faster in the splat loops.
#[inline]
fn floor_i64(x: f64) -> i64 {
    let truncated = x as i64;
    if (truncated as f64) > x {
        truncated - 1
    } else {
        truncated
    }
}

/// Where a pixel lands, packed: `(lowest plane + 1) << 32 | voxel within the plane` (the voxel
/// for nearest interpolation only; the lowest plane of a trilinear splat may be -1), or [`MISSES`].
const MISSES: u64 = u64::MAX;

/// `floor(x)` through an i32 conversion (packed on AVX2, unlike f64 -> i64): exact for
/// |x| < 2^31 - 1; beyond, x is clamped first, to a value outside every grid axis (axes have
/// fewer than 2^31 - 1 voxels).
#[inline(always)]
#[allow(clippy::manual_clamp)] // `clamp` keeps NaN, which the unchecked conversion must not see
fn floor_i32(x: f64) -> i64 {
    const LIMIT: f64 = i32::MAX as f64;
    let clamped = x.max(-LIMIT).min(LIMIT);
    // SAFETY: `clamped` is within i32's range (and not NaN: `max` returns -LIMIT for NaN). An
    // unchecked conversion is one packed instruction; the checked `as` is not vectorised.
    let truncated = i64::from(unsafe { clamped.to_int_unchecked::<i32>() });
    truncated - i64::from((truncated as f64) > clamped)
}

/// Each pixel's packed landing along row `row` (pixels flagged false in `valid` miss).
/// Branch-free, so that the compiler vectorises it.
#[inline(always)]
fn land_row(
    shape: [usize; 3],
    interpolation: Interpolation,
    affine: &PixelToIndex,
    row: usize,
    valid: Option<&[bool]>,
    out: &mut [u64],
) {
    let [nz, ny, nx] = shape.map(|n| n as i64);
    match interpolation {
        Interpolation::Nearest => {
            for (col, landing) in out.iter_mut().enumerate() {
                let [i, j, k] = voxel_position(affine, col, row);
                let (i, j, k) = (floor_i32(i + 0.5), floor_i32(j + 0.5), floor_i32(k + 0.5));
                let hit = i >= 0 && i < nx && j >= 0 && j < ny && k >= 0 && k < nz;
                let packed =
                    ((k + 1) as u64) << 32 | (j.wrapping_mul(nx).wrapping_add(i) as u32 as u64);
                *landing = if hit { packed } else { MISSES };
            }
        }
        Interpolation::Linear => {
            for (col, landing) in out.iter_mut().enumerate() {
                let [i, j, k] = voxel_position(affine, col, row);
                let (i0, j0, k0) = (floor_i32(i), floor_i32(j), floor_i32(k));
                let hit = i0 >= -1 && i0 < nx && j0 >= -1 && j0 < ny && k0 >= -1 && k0 < nz;
                *landing = if hit { ((k0 + 1) as u64) << 32 } else { MISSES };
            }
        }
    }
    if let Some(valid) = valid {
        for (landing, &valid) in out.iter_mut().zip(valid) {
            if !valid {
                *landing = MISSES;
            }
        }
    }
}

/// [`land_row`] compiled for the instruction set `simd` (see [`crate::simd`]; integer and exactly
/// rounded operations only: the same result on every path).
fn land_row_on(
    simd: Simd,
    shape: [usize; 3],
    interpolation: Interpolation,
    affine: &PixelToIndex,
    row: usize,
    valid: Option<&[bool]>,
    out: &mut [u64],
) {
    dispatch!(
        simd,
        [land_row, land_row_avx2, land_row_avx512](shape, interpolation, affine, row, valid, out)
    )
}

compiled_for!(
    fn land_row(
        shape: [usize; 3],
        interpolation: Interpolation,
        affine: &PixelToIndex,
        row: usize,
        valid: Option<&[bool]>,
        out: &mut [u64],
    );
    land_row_avx2: "avx2",
    land_row_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);

/// A voxel's compounded value and weight from its cell (value, weight): the mean divided by the
/// weight (0 where nothing landed), the maximum or latest value as it is.
#[inline(always)]
fn voxel_value(compounding: Compounding, [value, weight]: [f32; 2]) -> (f32, f32) {
    let image = match compounding {
        Compounding::Mean if weight > 0.0 => value / weight,
        Compounding::Mean => 0.0,
        Compounding::Maximum | Compounding::Latest => value,
    };
    (image, weight)
}

/// A voxel volume that frames are inserted into, batch after batch.
#[derive(Debug, Clone)]
pub struct Accumulator {
    /// Voxel counts (z, y, x).
    shape: [usize; 3],
    world_to_index: Matrix4<f64>,
    interpolation: Interpolation,
    compounding: Compounding,
    /// Per voxel (value, weight) side by side, so that a splat touches one cache line, not two.
    cells: Vec<[f32; 2]>,
    frames_inserted: usize,
}

impl Accumulator {
    /// A zeroed accumulator over the grid `shape` (z, y, x) with `index_to_world` (row-major 4x4, mm).
    /// Fails before allocating if the grid needs more than `max_bytes`.
    pub fn new(
        shape: [usize; 3],
        index_to_world: &[f64],
        interpolation: Interpolation,
        compounding: Compounding,
        max_bytes: u128,
    ) -> Result<Self> {
        if shape.contains(&0) {
            return Err(KernelError::Shape {
                argument: "shape",
                expected: "three positive voxel counts (z, y, x)".into(),
                got: format!("{shape:?}"),
            });
        }
        // Checked: three usize factors can pass u128::MAX, and a wrapped count would pass the limit.
        let voxels = shape
            .iter()
            .try_fold(1u128, |count, &n| count.checked_mul(n as u128))
            .unwrap_or(u128::MAX);
        let needed_bytes = voxels.saturating_mul(BYTES_PER_VOXEL);
        if needed_bytes > max_bytes {
            return Err(KernelError::MemoryLimit {
                needed_bytes,
                limit_bytes: max_bytes,
            });
        }
        check_len("index_to_world", index_to_world, 16)?;
        check_finite("index_to_world", index_to_world)?;
        let world_to_index = Matrix4::from_row_slice(index_to_world)
            .try_inverse()
            .ok_or(KernelError::Value {
                argument: "index_to_world",
                message: "the matrix is singular".into(),
            })?;
        // Voxels within a plane are numbered by u32, voxel indices along an axis by i32.
        if shape[1] as u128 * shape[2] as u128 > u32::MAX as u128
            || shape.iter().any(|&n| n >= i32::MAX as usize)
        {
            return Err(KernelError::Shape {
                argument: "shape",
                expected: format!(
                    "at most {} voxels per z plane and {} along an axis",
                    u32::MAX,
                    i32::MAX - 1
                ),
                got: format!("{shape:?}"),
            });
        }
        let voxels = usize::try_from(voxels).map_err(|_| KernelError::Allocation {
            argument: "shape",
            bytes: u128::MAX,
        })?;
        Ok(Accumulator {
            shape,
            world_to_index,
            interpolation,
            compounding,
            cells: filled("shape", voxels, [0.0; 2])?,
            frames_inserted: 0,
        })
    }

    pub fn shape(&self) -> [usize; 3] {
        self.shape
    }

    pub fn frames_inserted(&self) -> usize {
        self.frames_inserted
    }

    /// Insert frames at their poses: `image_to_world` holds one row-major 4x4 per frame (mm).
    /// With `valid` (one flag per pixel, the frames' layout), pixels flagged false are left out of
    /// the image and of the coverage.
    pub fn insert<P: Pixel>(
        &mut self,
        frames: &FrameStack<P>,
        image_to_world: &[f64],
        valid: Option<&[bool]>,
    ) -> Result<()> {
        let affines = self.pixel_to_index(frames.n_frames, image_to_world)?;
        if let Some(valid) = valid {
            check_len("valid", valid, frames.pixels.len())?;
        }
        let frame_size = frames.rows * frames.cols;
        for (batch, batch_affines) in affines.chunks(FRAMES_PER_BATCH).enumerate() {
            let first = batch * FRAMES_PER_BATCH * frame_size;
            let batch_pixels = first..first + batch_affines.len() * frame_size;
            let batch = Batch {
                pixels: &frames.pixels[batch_pixels.clone()],
                valid: valid.map(|valid| &valid[batch_pixels]),
                rows: frames.rows,
                cols: frames.cols,
                affines: batch_affines,
            };
            self.insert_batch(&batch);
        }
        self.frames_inserted += frames.n_frames;
        Ok(())
    }

    /// Warp frames back to zero force (as [`crate::warp::warp_frames`]) and insert them, one batch
    /// at a time, without holding all corrected frames. Pixels sampled from outside the frame are
    /// left out when `exclude_invalid`, else inserted with the value `fill`.
    pub fn insert_corrected<P: Pixel>(
        &mut self,
        frames: &FrameStack<P>,
        image_to_world: &[f64],
        correction: &Correction,
        fill: P,
        exclude_invalid: bool,
    ) -> Result<()> {
        let affines = self.pixel_to_index(frames.n_frames, image_to_world)?;
        let (rows, cols) = (frames.rows, frames.cols);
        let fields = correction.frame_fields(frames.n_frames, rows, cols)?;
        // Scratch reused by every batch.
        let batch_size = FRAMES_PER_BATCH.min(frames.n_frames) * rows * cols;
        let mut corrected = filled("frames", batch_size, fill)?;
        let mut valid = filled("frames", batch_size, false)?;
        for (batch, batch_affines) in affines.chunks(FRAMES_PER_BATCH).enumerate() {
            let first_frame = batch * FRAMES_PER_BATCH;
            let pixels = &mut corrected[..batch_affines.len() * rows * cols];
            let batch_valid = &mut valid[..batch_affines.len() * rows * cols];
            pixels
                .par_chunks_mut(cols)
                .zip(batch_valid.par_chunks_mut(cols))
                .enumerate()
                .for_each_init(RowScratch::default, |scratch, (index, (pixels, valid))| {
                    let frame = first_frame + index / rows;
                    warp_row(
                        frames.frame(frame),
                        rows,
                        cols,
                        &fields[frame],
                        index % rows,
                        fill,
                        WarpedRow { pixels, valid },
                        scratch,
                    );
                });
            let batch = Batch {
                pixels,
                valid: exclude_invalid.then_some(&*batch_valid),
                rows,
                cols,
                affines: batch_affines,
            };
            self.insert_batch(&batch);
        }
        self.frames_inserted += frames.n_frames;
        Ok(())
    }

    /// The compounded image (mean divided by weight; 0 where nothing landed) and the weight volume,
    /// or an error when they cannot be allocated.
    pub fn volume(&self) -> Result<(Vec<f32>, Vec<f32>)> {
        let mut image = filled("shape", self.cells.len(), 0.0f32)?;
        let mut weight = filled("shape", self.cells.len(), 0.0f32)?;
        let compounding = self.compounding;
        image
            .par_iter_mut()
            .zip(weight.par_iter_mut())
            .zip(self.cells.par_iter())
            .for_each(|((image, weight), &cell)| {
                (*image, *weight) = voxel_value(compounding, cell);
            });
        Ok((image, weight))
    }

    /// The image and weight of [`Accumulator::volume`] in the voxel box from `lo` (first voxel, z,
    /// y, x) to `hi` (one past the last), each `(hi - lo)` voxels in (z, y, x) order; only the box
    /// is computed. Fails unless `0 <= lo < hi <= shape` on every axis.
    pub fn volume_region(&self, lo: [i64; 3], hi: [i64; 3]) -> Result<(Vec<f32>, Vec<f32>)> {
        let box_shape = self.check_region(lo, hi)?;
        let [_, ny, nx] = self.shape;
        let [lz, ly, lx] = lo.map(|bound| bound as usize);
        let [bz, by, bx] = box_shape;
        let voxels = bz * by * bx;
        let mut image = filled("hi", voxels, 0.0f32)?;
        let mut weight = filled("hi", voxels, 0.0f32)?;
        let compounding = self.compounding;
        // One box row (bx voxels along x) at a time, each read from one run of cells.
        image
            .par_chunks_mut(bx)
            .zip(weight.par_chunks_mut(bx))
            .enumerate()
            .with_min_len(64)
            .for_each(|(row, (image, weight))| {
                let (z, y) = (lz + row / by, ly + row % by);
                let first = (z * ny + y) * nx + lx;
                let cells = &self.cells[first..first + bx];
                for ((image, weight), &cell) in image.iter_mut().zip(weight).zip(cells) {
                    (*image, *weight) = voxel_value(compounding, cell);
                }
            });
        Ok((image, weight))
    }

    /// The voxel counts (z, y, x) of the box `lo..hi`, or an error naming the first bound outside
    /// `0 <= lo < hi <= shape`.
    fn check_region(&self, lo: [i64; 3], hi: [i64; 3]) -> Result<[usize; 3]> {
        let mut counts = [0usize; 3];
        for (axis, name) in ["z", "y", "x"].into_iter().enumerate() {
            let n = self.shape[axis] as i64;
            let (low, high) = (lo[axis], hi[axis]);
            if low < 0 || low >= n {
                return Err(KernelError::Value {
                    argument: "lo",
                    message: format!(
                        "the {name} bound {low} is outside the grid's voxels 0..{n} along {name}"
                    ),
                });
            }
            if high <= low || high > n {
                return Err(KernelError::Value {
                    argument: "hi",
                    message: format!(
                        "the {name} bound {high} must be above lo's {low} and at most the grid's \
                         {n} voxels along {name}"
                    ),
                });
            }
            counts[axis] = (high - low) as usize;
        }
        Ok(counts)
    }

    /// An error unless `image_to_world` holds `n_frames` finite affine 4x4 poses.
    pub fn check_poses(&self, n_frames: usize, image_to_world: &[f64]) -> Result<()> {
        self.pixel_to_index(n_frames, image_to_world).map(|_| ())
    }

    fn pixel_to_index(&self, n_frames: usize, image_to_world: &[f64]) -> Result<Vec<PixelToIndex>> {
        check_len("image_to_world", image_to_world, n_frames * 16)?;
        image_to_world
            .chunks(16)
            .enumerate()
            .map(|(frame, values)| {
                if values.iter().any(|v| !v.is_finite()) {
                    return Err(KernelError::Value {
                        argument: "image_to_world",
                        message: format!("frame {frame}: the transform holds non-finite values"),
                    });
                }
                if values[12..] != [0.0, 0.0, 0.0, 1.0] {
                    return Err(KernelError::Value {
                        argument: "image_to_world",
                        message: format!(
                            "frame {frame}: the last row must be [0, 0, 0, 1], got {:?}",
                            &values[12..]
                        ),
                    });
                }
                let combined = self.world_to_index * Matrix4::from_row_slice(values);
                Ok(std::array::from_fn(|r| {
                    std::array::from_fn(|c| combined[(r, c)])
                }))
            })
            .collect()
    }

    /// Insert one batch of frames, deterministically in parallel over slabs of voxel planes: each
    /// slab lands the rows that may reach it and takes their pixels in (frame, row, column) order.
    fn insert_batch<P: Pixel>(&mut self, batch: &Batch<P>) {
        if rayon::current_num_threads() == 1 {
            return self.insert_batch_serially(batch);
        }
        let Batch {
            pixels,
            valid,
            rows,
            cols,
            affines,
        } = *batch;
        let (shape, interpolation) = (self.shape, self.interpolation);
        let splat = self.splatter();
        let plane_size = splat.plane_size();
        // A few slabs per thread balance the load; the slabs never change a result.
        let nz = self.shape[0];
        let planes_per_slab = nz.div_ceil(2 * rayon::current_num_threads()).max(1);
        self.cells
            .par_chunks_mut(planes_per_slab * plane_size)
            .enumerate()
            .for_each_init(Vec::new, |row_landings, (slab, cells)| {
                let first_plane = slab * planes_per_slab;
                let slab_planes = first_plane..first_plane + cells.len() / plane_size;
                row_landings.resize(cols, MISSES);
                for (frame, affine) in affines.iter().enumerate() {
                    for row in 0..rows {
                        // The planes a row reaches, in closed form: k is affine along the row,
                        // so its extremes are at the ends (widened by a plane against rounding).
                        if !splat.row_may_reach(affine, row, cols, &slab_planes) {
                            continue;
                        }
                        let first = (frame * rows + row) * cols;
                        // Landed here, by each slab the row may reach (once, unless the row
                        // crosses a slab boundary): no batch-wide buffer, no separate pass.
                        let row_valid = valid.map(|valid| &valid[first..first + cols]);
                        land_row_on(
                            Simd::detected(),
                            shape,
                            interpolation,
                            affine,
                            row,
                            row_valid,
                            row_landings,
                        );
                        let row_landings = &*row_landings;
                        if splat.interpolation == Interpolation::Nearest {
                            // One plane per pixel, at or above 0: the cell straight from the landing.
                            for (&landing, pixel) in row_landings.iter().zip(&pixels[first..]) {
                                let plane = (landing >> 32).wrapping_sub(1) as usize;
                                if landing != MISSES && slab_planes.contains(&plane) {
                                    let offset = (plane - first_plane) * plane_size;
                                    let cell = &mut cells[offset + landing as u32 as usize];
                                    splat.combine(cell, pixel.to_f64() as f32, 1.0);
                                }
                            }
                            continue;
                        }
                        for (col, &landing) in row_landings.iter().enumerate() {
                            if landing == MISSES {
                                continue;
                            }
                            let reached = splat.planes_reached((landing >> 32) as i32 - 1);
                            let planes = reached.start.max(slab_planes.start)
                                ..reached.end.min(slab_planes.end);
                            if planes.is_empty() {
                                continue;
                            }
                            let sample = pixels[first + col].to_f64() as f32;
                            for plane in planes {
                                let offset = (plane - first_plane) * plane_size;
                                splat.onto_plane(
                                    &mut cells[offset..offset + plane_size],
                                    plane,
                                    sample,
                                    landing as u32,
                                    (affine, row, col),
                                );
                            }
                        }
                    }
                }
            });
    }

    /// [`Accumulator::insert_batch`] on one thread: pixels splatted as they are landed, frame
    /// after frame, row after row. Every voxel sees its updates in the same order as on the
    /// plane-parallel path, so the volume is the same.
    fn insert_batch_serially<P: Pixel>(&mut self, batch: &Batch<P>) {
        let Batch {
            pixels,
            valid,
            rows,
            cols,
            affines,
        } = *batch;
        let splat = self.splatter();
        let plane_size = splat.plane_size();
        let mut landings = vec![MISSES; cols];
        for (frame, affine) in affines.iter().enumerate() {
            for row in 0..rows {
                let first = (frame * rows + row) * cols;
                let row_valid = valid.map(|valid| &valid[first..first + cols]);
                land_row_on(
                    Simd::detected(),
                    self.shape,
                    self.interpolation,
                    affine,
                    row,
                    row_valid,
                    &mut landings,
                );
                let row_pixels = &pixels[first..first + cols];
                if splat.interpolation == Interpolation::Nearest {
                    // One plane per pixel, at or above 0: the cell straight from the landing.
                    for (&landing, &pixel) in landings.iter().zip(row_pixels) {
                        if landing != MISSES {
                            let plane = (landing >> 32) as usize - 1;
                            let cell =
                                &mut self.cells[plane * plane_size + landing as u32 as usize];
                            splat.combine(cell, pixel.to_f64() as f32, 1.0);
                        }
                    }
                    continue;
                }
                for (col, (&landing, &pixel)) in landings.iter().zip(row_pixels).enumerate() {
                    if landing == MISSES {
                        continue;
                    }
                    let sample = pixel.to_f64() as f32;
                    let (lowest, voxel) = ((landing >> 32) as i32 - 1, landing as u32);
                    for plane in splat.planes_reached(lowest) {
                        let cells = &mut self.cells[plane * plane_size..(plane + 1) * plane_size];
                        splat.onto_plane(cells, plane, sample, voxel, (affine, row, col));
                    }
                }
            }
        }
    }

    fn splatter(&self) -> Splatter {
        Splatter {
            shape: self.shape,
            interpolation: self.interpolation,
            compounding: self.compounding,
        }
    }
}

/// How one pixel is splatted into one voxel plane.
#[derive(Debug, Clone, Copy)]
struct Splatter {
    shape: [usize; 3],
    interpolation: Interpolation,
    compounding: Compounding,
}

impl Splatter {
    fn plane_size(&self) -> usize {
        self.shape[1] * self.shape[2]
    }

    /// The planes a splat whose lowest plane is `lowest` reaches inside the grid.
    #[inline]
    fn planes_reached(&self, lowest: i32) -> std::ops::Range<usize> {
        let reach = match self.interpolation {
            Interpolation::Nearest => 1,
            Interpolation::Linear => 2,
        };
        let nz = self.shape[0] as i32;
        (lowest.max(0) as usize)..((lowest + reach).min(nz) as usize)
    }

    /// Whether any pixel of row `row` (of `cols` pixels) may reach a plane of `planes`.
    #[inline]
    fn row_may_reach(
        &self,
        affine: &PixelToIndex,
        row: usize,
        cols: usize,
        planes: &std::ops::Range<usize>,
    ) -> bool {
        let ends = [0, cols - 1].map(|col| voxel_position(affine, col, row)[2]);
        let rounding = match self.interpolation {
            Interpolation::Nearest => 0.5,
            Interpolation::Linear => 0.0,
        };
        let lowest = floor_i32(ends[0].min(ends[1]) + rounding) - 1;
        let highest = floor_i32(ends[0].max(ends[1]) + rounding) + 1;
        let reached = self
            .planes_reached(lowest.clamp(-1, i32::MAX as i64 - 2) as i32)
            .start
            ..self
                .planes_reached(highest.clamp(-1, i32::MAX as i64 - 2) as i32)
                .end;
        reached.start < planes.end && planes.start < reached.end
    }

    /// Combine `sample` with weight `w` into the voxel `cell` (value, weight).
    #[inline(always)]
    fn combine(&self, cell: &mut [f32; 2], sample: f32, w: f32) {
        let [value, weight] = cell;
        match self.compounding {
            Compounding::Mean => *value += w * sample,
            Compounding::Maximum => {
                if *weight == 0.0 || sample > *value {
                    *value = sample
                }
            }
            Compounding::Latest => *value = sample,
        }
        *weight += w;
    }

    /// Splat `sample` of the pixel `(affine, row, col)` into the voxel plane `plane` (`cells`):
    /// at `voxel` (nearest), or with the trilinear weights of its 4 voxels in the plane.
    #[inline(always)]
    fn onto_plane(
        &self,
        cells: &mut [[f32; 2]],
        plane: usize,
        sample: f32,
        voxel: u32,
        (affine, row, col): (&PixelToIndex, usize, usize),
    ) {
        let mut splat = |voxel: usize, w: f32| self.combine(&mut cells[voxel], sample, w);
        match self.interpolation {
            Interpolation::Nearest => splat(voxel as usize, 1.0),
            Interpolation::Linear => {
                let [_, ny, nx] = self.shape;
                let [i, j, k] = voxel_position(affine, col, row);
                let (i0, j0, k0) = (floor_i64(i), floor_i64(j), floor_i64(k));
                let (fx, fy, fz) = (i - i0 as f64, j - j0 as f64, k - k0 as f64);
                let wz = if plane as i64 == k0 { 1.0 - fz } else { fz };
                let maximum = self.compounding == Compounding::Maximum;
                for (dj, wy) in [(0i64, 1.0 - fy), (1, fy)] {
                    for (di, wx) in [(0i64, 1.0 - fx), (1, fx)] {
                        let (vi, vj) = (i0 + di, j0 + dj);
                        let w = wz * wy * wx;
                        let kept = if maximum {
                            w >= MAXIMUM_MIN_WEIGHT
                        } else {
                            w as f32 > 0.0
                        };
                        if kept && vi >= 0 && vi < nx as i64 && vj >= 0 && vj < ny as i64 {
                            splat(vj as usize * nx + vi as usize, w as f32);
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IDENTITY: [f64; 16] = [
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
    ];

    fn pose_at_z(z: f64) -> [f64; 16] {
        let mut pose = IDENTITY;
        pose[11] = z;
        pose
    }

    #[test]
    fn floor_i64_matches_floor() {
        for x in [
            -2.5,
            -2.0,
            -1e-300,
            -0.0,
            0.0,
            0.3,
            1.0,
            1.999999,
            7.5,
            -7.5,
            1e15 + 0.5,
        ] {
            assert_eq!(floor_i64(x), x.floor() as i64, "{x}");
        }
    }

    #[test]
    fn memory_limit_is_checked_before_allocating() {
        let err = Accumulator::new(
            [4000, 4000, 4000],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            1 << 30,
        )
        .unwrap_err();
        assert!(matches!(err, KernelError::MemoryLimit { .. }));
        // A voxel count past u128::MAX saturates instead of wrapping to a small number.
        let err = Accumulator::new(
            [1 << 63, 1 << 63, 4],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX - 1,
        )
        .unwrap_err();
        assert!(matches!(err, KernelError::MemoryLimit { .. }));
    }

    #[test]
    fn nearest_mean_of_two_frames_on_one_plane() {
        let mut acc = Accumulator::new(
            [2, 2, 3],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap();
        let pixels: Vec<f32> = vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0];
        let frames = FrameStack::new(&pixels, 2, 2, 3).unwrap();
        let poses: Vec<f64> = [pose_at_z(1.0), pose_at_z(1.2)].concat();
        acc.insert(&frames, &poses, None).unwrap();
        let (image, weight) = acc.volume().unwrap();
        assert_eq!(&image[6..], &[2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        assert_eq!(&weight[6..], &[2.0; 6]);
        assert_eq!(&weight[..6], &[0.0; 6]);
    }

    #[test]
    fn trilinear_splat_conserves_weight_inside_the_grid() {
        let mut acc = Accumulator::new(
            [3, 3, 3],
            &IDENTITY,
            Interpolation::Linear,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap();
        let mut pose = pose_at_z(0.3);
        pose[3] = 0.25;
        pose[7] = 0.6;
        let pixels = vec![10u8; 1];
        acc.insert(&FrameStack::new(&pixels, 1, 1, 1).unwrap(), &pose, None)
            .unwrap();
        let (image, weight) = acc.volume().unwrap();
        assert!((weight.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert!(image.iter().zip(&weight).all(|(&v, &w)| if w > 0.0 {
            (v - 10.0).abs() < 1e-5
        } else {
            v == 0.0
        }));
    }

    #[test]
    fn trilinear_maximum_skips_corners_below_an_eighth() {
        // One pixel at (0.25, 0.6, 0.3): corner weights 0.21, 0.07, 0.315, 0.105 on plane 0 and
        // 0.09, 0.03, 0.135, 0.045 on plane 1. Maximum updates the three of at least 1/8, mean all eight.
        let mut pose = pose_at_z(0.3);
        pose[3] = 0.25;
        pose[7] = 0.6;
        let pixels = vec![10u8; 1];
        let mut volumes = [Compounding::Maximum, Compounding::Mean].map(|compounding| {
            let mut acc = Accumulator::new(
                [2, 2, 2],
                &IDENTITY,
                Interpolation::Linear,
                compounding,
                u128::MAX,
            )
            .unwrap();
            acc.insert(&FrameStack::new(&pixels, 1, 1, 1).unwrap(), &pose, None)
                .unwrap();
            acc.volume().unwrap()
        });
        let (mean_image, mean_weight) = volumes[1].clone();
        assert!(mean_weight.iter().all(|&w| w > 0.0));
        assert!(mean_image.iter().all(|&v| (v - 10.0).abs() < 1e-5));
        let (image, weight) = std::mem::take(&mut volumes[0]);
        let kept: Vec<usize> = (0..8).filter(|&v| weight[v] > 0.0).collect();
        assert_eq!(kept, vec![0, 2, 6]);
        for v in 0..8 {
            let expected = if kept.contains(&v) { 10.0 } else { 0.0 };
            assert_eq!(image[v], expected, "voxel {v}");
            assert_eq!(weight[v] > 0.0, mean_weight[v] >= 0.125, "voxel {v}");
        }
    }

    #[test]
    fn trilinear_splat_below_the_first_plane_reaches_only_plane_zero() {
        let mut acc = Accumulator::new(
            [3, 1, 1],
            &IDENTITY,
            Interpolation::Linear,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap();
        let pixels = vec![4.0f32];
        acc.insert(
            &FrameStack::new(&pixels, 1, 1, 1).unwrap(),
            &pose_at_z(-0.25),
            None,
        )
        .unwrap();
        let (image, weight) = acc.volume().unwrap();
        assert_eq!(weight, vec![0.75, 0.0, 0.0]);
        assert_eq!(image, vec![4.0, 0.0, 0.0]);
    }

    #[test]
    fn invalid_pixels_leave_no_value_and_no_coverage() {
        let pixels: Vec<f32> = vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let frames = FrameStack::new(&pixels, 1, 2, 3).unwrap();
        let valid = [true, false, true, false, true, true];
        let mut masked = Accumulator::new(
            [1, 2, 3],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap();
        let mut all = masked.clone();
        masked.insert(&frames, &IDENTITY, Some(&valid)).unwrap();
        all.insert(&frames, &IDENTITY, None).unwrap();
        let (image, weight) = masked.volume().unwrap();
        assert_eq!(weight, vec![1.0, 0.0, 1.0, 0.0, 1.0, 1.0]);
        assert_eq!(image, vec![1.0, 0.0, 3.0, 0.0, 5.0, 6.0]);
        assert_eq!(all.volume().unwrap().1, vec![1.0; 6]);
        let err = masked
            .insert(&frames, &IDENTITY, Some(&valid[..5]))
            .unwrap_err();
        assert!(err.to_string().starts_with("valid:"), "{err}");
    }

    #[test]
    fn grid_too_large_for_memory_is_an_error_not_an_abort() {
        let err = Accumulator::new(
            [1 << 20, 1 << 15, 1 << 15],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap_err();
        assert!(matches!(err, KernelError::Allocation { .. }), "{err}");
        let err = Accumulator::new(
            [1, 1 << 17, 1 << 16],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap_err();
        assert!(err.to_string().starts_with("shape:"), "{err}");
    }

    #[test]
    fn every_instruction_set_lands_identically() {
        let mut state = 11u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let shape = [17, 19, 23];
        for trial in 0..40 {
            // Positions from far outside the grid (beyond i32) to inside it.
            let scale = if trial % 10 == 0 { 1e12 } else { 2.0 };
            let affine: PixelToIndex =
                std::array::from_fn(|_| std::array::from_fn(|_| (uniform() - 0.4) * scale));
            let valid: Vec<bool> = (0..31).map(|_| uniform() < 0.8).collect();
            for interpolation in [Interpolation::Nearest, Interpolation::Linear] {
                let landed = |simd| {
                    let mut out = vec![0u64; 31];
                    land_row_on(
                        simd,
                        shape,
                        interpolation,
                        &affine,
                        trial,
                        Some(&valid),
                        &mut out,
                    );
                    out
                };
                let levels = Simd::available();
                let baseline = landed(levels[0]);
                for &simd in &levels[1..] {
                    assert_eq!(landed(simd), baseline, "{simd:?}");
                }
            }
        }
    }

    #[test]
    fn floor_i32_matches_floor_and_clamps() {
        for x in [-2.5, -1e-300, 0.0, 0.3, 7.5, -7.5, 3e9, -3e9, f64::NAN] {
            let expected = if x.is_nan() {
                -(i32::MAX as i64)
            } else {
                x.floor().clamp(-(i32::MAX as f64), i32::MAX as f64) as i64
            };
            assert_eq!(floor_i32(x), expected, "{x}");
        }
    }

    #[test]
    fn volume_region_is_the_box_of_the_whole_volume() {
        let shape = [5, 4, 6];
        let mut state = 7u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let pixels: Vec<f32> = (0..3 * 7 * 8).map(|_| (uniform() * 255.0) as f32).collect();
        let frames = FrameStack::new(&pixels, 3, 7, 8).unwrap();
        let mut poses = Vec::new();
        for frame in 0..3 {
            let mut pose = IDENTITY;
            pose[0] = 0.7;
            pose[5] = 0.6;
            pose[3] = uniform() - 0.5;
            pose[7] = uniform() - 0.5;
            pose[11] = 1.0 + frame as f64 * 1.3 + uniform() * 0.2;
            poses.extend(pose);
        }
        for interpolation in [Interpolation::Nearest, Interpolation::Linear] {
            for compounding in [Compounding::Mean, Compounding::Maximum, Compounding::Latest] {
                let mut acc =
                    Accumulator::new(shape, &IDENTITY, interpolation, compounding, u128::MAX)
                        .unwrap();
                acc.insert(&frames, &poses, None).unwrap();
                let (image, weight) = acc.volume().unwrap();
                assert!(weight[..4 * 6].iter().all(|&w| w == 0.0));
                assert!(weight[4 * 6..].iter().filter(|&&w| w > 0.0).count() > 20);
                for (lo, hi) in [
                    ([0, 0, 0], [5, 4, 6]),
                    ([1, 2, 3], [4, 3, 6]),
                    ([4, 3, 5], [5, 4, 6]),
                ] {
                    let (region, region_weight) = acc.volume_region(lo, hi).unwrap();
                    let mut expected = (Vec::new(), Vec::new());
                    for z in lo[0]..hi[0] {
                        for y in lo[1]..hi[1] {
                            for x in lo[2]..hi[2] {
                                let voxel = ((z * 4 + y) * 6 + x) as usize;
                                expected.0.push(image[voxel]);
                                expected.1.push(weight[voxel]);
                            }
                        }
                    }
                    assert_eq!(
                        region, expected.0,
                        "{interpolation:?} {compounding:?} {lo:?}"
                    );
                    assert_eq!(region_weight, expected.1);
                }
            }
        }
    }

    #[test]
    fn volume_region_names_the_bad_bound() {
        let acc = Accumulator::new(
            [5, 4, 6],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Mean,
            u128::MAX,
        )
        .unwrap();
        for (lo, hi, start) in [
            ([-1, 0, 0], [5, 4, 6], "lo: the z bound -1"),
            ([0, 4, 0], [5, 4, 6], "lo: the y bound 4"),
            ([0, 0, 0], [5, 4, 7], "hi: the x bound 7"),
            (
                [2, 0, 0],
                [2, 4, 6],
                "hi: the z bound 2 must be above lo's 2",
            ),
        ] {
            let err = acc.volume_region(lo, hi).unwrap_err().to_string();
            assert!(err.starts_with(start), "{err}");
        }
    }

    #[test]
    fn bad_pose_names_the_frame() {
        let mut acc = Accumulator::new(
            [2, 2, 2],
            &IDENTITY,
            Interpolation::Nearest,
            Compounding::Latest,
            u128::MAX,
        )
        .unwrap();
        let pixels = vec![0u8; 2];
        let mut poses = [IDENTITY, IDENTITY].concat();
        poses[16 + 5] = f64::NAN;
        let err = acc
            .insert(&FrameStack::new(&pixels, 2, 1, 1).unwrap(), &poses, None)
            .unwrap_err();
        assert!(err.to_string().contains("frame 1"), "{err}");
    }
}
