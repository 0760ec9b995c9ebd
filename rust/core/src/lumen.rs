//! The lumen search of the vessel-anchored correction: each frame's zero-force lumen, searched
//! where the previous frame's was.
//!
//! A search warps a window of the frame back to zero force with the model's field (bilinear, the
//! frame's edge pixels replicated outside it, uint8 rounded to nearest), and segments the
//! anechoic region there: Gaussian smoothing, levels `dark` (the minimum) and `tissue` (the
//! median), a hysteresis threshold (dark below `dark + threshold_fraction (tissue - dark)`, with a
//! core below the halfway level), a 3 x 3 opening, 8-connected regions, and the region at or
//! nearest to the seed filled (its holes closed). The lumen is that region's centroid and
//! equivalent radius. The zero-force lumen of a frame is the fixed point of searching the frame
//! corrected with the vessel part on the lumen found. Serial and deterministic: a sweep's frames
//! depend on each other. `usdeform.reference.sweep_lumens` (NumPy and OpenCV) is the twin.

use std::ops::Range;

use crate::anchored::{Anchor, VesselPart};
use crate::error::{check_finite, KernelError, Result};
use crate::frame_correction::FrameCorrection;
use crate::model::DeformationModel;
use crate::simd::{compiled_for, dispatch, Simd};
use crate::stiffness::StiffnessProfile;
use crate::terms::ForceTerms;
use crate::warp::{FrameStack, Pixel};

/// The search's settings (see the module's description).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LumenSettings {
    /// Half-width of a search window, in the expected lumen's radii (at most 100).
    pub window_radii: f64,
    /// Largest change of centre and radius (pixels) at which a frame's fixed point stops.
    pub tolerance_px: f64,
    /// Most corrections tried per frame (at most 1000).
    pub max_iterations: usize,
    /// Gaussian smoothing, pixels (at most 100).
    pub smoothing_sigma_px: f64,
    /// Dark below `dark + threshold_fraction (tissue - dark)`, in [0.5, 1).
    pub threshold_fraction: f64,
    /// The darkest level must lie at or below `(1 - min_contrast) tissue`, in (0, 1].
    pub min_contrast: f64,
    /// Smallest region, pixels (at least 5).
    pub min_area_px: usize,
}

impl LumenSettings {
    /// An error naming the setting out of range.
    pub fn check(&self) -> Result<()> {
        let valid = self.window_radii > 0.0
            && self.window_radii <= 100.0
            && self.tolerance_px.is_finite()
            && self.tolerance_px >= 0.0
            && (1..=1000).contains(&self.max_iterations)
            && self.smoothing_sigma_px > 0.0
            && self.smoothing_sigma_px <= 100.0
            && (0.5..1.0).contains(&self.threshold_fraction)
            && self.min_contrast > 0.0
            && self.min_contrast <= 1.0
            && self.min_area_px >= 5;
        if valid {
            Ok(())
        } else {
            Err(KernelError::Value {
                argument: "settings",
                message: format!("out of range: {self:?}"),
            })
        }
    }
}

/// Where a sweep's search stands: the last lumen found (None: none yet) and the frames searched
/// since without one.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LumenTrack {
    pub last_found: Option<Anchor>,
    pub frames_missed: usize,
}

/// Frames must have fewer rows and columns than this: pixel positions are float32, exact below it.
const MAX_SIDE: usize = 1 << 24;

/// Where each frame's vessel part goes: its lumen, or where none was found, the last lumen found
/// before it (`last`, updated; at first the sweep's earlier lumen or the model's reference).
pub fn placements(found: &[Option<Anchor>], last: &mut Anchor) -> Vec<Anchor> {
    found
        .iter()
        .map(|anchor| {
            *last = anchor.unwrap_or(*last);
            *last
        })
        .collect()
}

/// A model's field, what the search warps each frame with.
#[derive(Debug, Clone, Copy)]
pub struct AnchoredModel<'a> {
    pub model: &'a DeformationModel,
    pub part: &'a VesselPart,
    /// The lumen the model was fitted with: where the first search starts.
    pub reference: Anchor,
}

/// Each frame's zero-force lumen (None where none is found), searched where the previous frame's
/// lumen was; after frames without one, the region the next may lie in grows by the last lumen's
/// radius per frame missed. `track` says where an earlier part of the same sweep left the search
/// and is updated, so that a sweep searched in parts finds what it finds in one call.
pub fn sweep_lumens<P: Pixel>(
    frames: &FrameStack<'_, P>,
    forces: &[f64],
    profiles: &[StiffnessProfile],
    model: &AnchoredModel<'_>,
    settings: &LumenSettings,
    track: &mut LumenTrack,
) -> Result<Vec<Option<Anchor>>> {
    settings.check()?;
    check_finite("forces", forces)?;
    for (argument, len) in [("forces", forces.len()), ("profiles", profiles.len())] {
        if len != frames.n_frames {
            return Err(KernelError::Shape {
                argument,
                expected: format!("one per frame ({})", frames.n_frames),
                got: len.to_string(),
            });
        }
    }
    if frames.rows >= MAX_SIDE || frames.cols >= MAX_SIDE {
        return Err(KernelError::Shape {
            argument: "frames",
            expected: format!("fewer than {MAX_SIDE} rows and columns"),
            got: format!("{} x {}", frames.rows, frames.cols),
        });
    }
    // Every frame's force and profile checked before any is searched (errors name the frame).
    let terms = forces
        .iter()
        .zip(profiles)
        .enumerate()
        .map(|(index, (&force, profile))| model.model.frame_terms(force, profile, index))
        .collect::<Result<Vec<_>>>()?;
    if [frames.rows, frames.cols] != model.model.frame_shape {
        return Err(KernelError::Shape {
            argument: "frames",
            expected: format!("frames of the model's shape {:?}", model.model.frame_shape),
            got: format!("{} x {}", frames.rows, frames.cols),
        });
    }
    let image_parts = model
        .model
        .spatial
        .frame_fields(&terms, frames.rows, frames.cols);
    let mut found = Vec::with_capacity(frames.n_frames);
    let mut search = Search::new(frames.rows, frames.cols, settings);
    for (index, (terms, image_part)) in terms.into_iter().zip(image_parts).enumerate() {
        let near = track.last_found.map(|last| Anchor {
            radius: last.radius * (track.frames_missed as f64 + 1.0),
            ..last
        });
        let frame = FrameSearch {
            pixels: frames.frame(index),
            model,
            terms,
            image_part: FrameCorrection {
                field: image_part,
                vessel: None,
            },
        };
        let anchor = search.zero_force_lumen(&frame, near);
        match anchor {
            Some(lumen) => (track.last_found, track.frames_missed) = (Some(lumen), 0),
            None => track.frames_missed += 1,
        }
        found.push(anchor);
    }
    Ok(found)
}

/// One frame to search, with the model's field at its force: its force terms and image part.
struct FrameSearch<'a, P> {
    pixels: &'a [P],
    model: &'a AnchoredModel<'a>,
    terms: ForceTerms,
    image_part: FrameCorrection,
}

/// A window of a frame: rows and columns.
type Window = (Range<usize>, Range<usize>);

/// The search's scratch buffers, reused across frames.
struct Search<'s> {
    rows: usize,
    cols: usize,
    settings: &'s LumenSettings,
    kernel: Vec<f32>,
    image_part: TabulatedImagePart,
    displacements: Vec<[f64; 2]>,
    warped: Vec<f32>,
    pass: Vec<f32>,
    smoothed: Vec<f32>,
    sorted: Vec<f32>,
    below: Vec<u8>,
    opened: Vec<u8>,
    labels: Vec<u32>,
    runs: Vec<Run>,
    run_labels: Vec<u32>,
}

/// A run of a row's dark pixels: its row and columns, and the run it is joined to (itself: the
/// first run of its region, the root).
#[derive(Debug, Clone)]
struct Run {
    row: usize,
    columns: Range<usize>,
    parent: usize,
}

/// The root of run `index`'s region (the paths walked are halved).
fn root_run(runs: &mut [Run], mut index: usize) -> usize {
    while runs[index].parent != index {
        let grandparent = runs[runs[index].parent].parent;
        runs[index].parent = grandparent;
        index = grandparent;
    }
    index
}

/// Join the regions of runs `a` and `b`: the root is the earlier of their roots, so that a region's
/// root stays its first run.
fn join_runs(runs: &mut [Run], a: usize, b: usize) {
    let (a, b) = (root_run(runs, a), root_run(runs, b));
    runs[a.max(b)].parent = a.min(b);
}

/// A connected dark region of a window.
#[derive(Debug, Clone, Copy)]
struct Region {
    area: usize,
    sum_x: f64,
    sum_y: f64,
    has_core: bool,
    top: usize,
    left: usize,
    bottom: usize,
    right: usize,
}

impl<'s> Search<'s> {
    fn new(rows: usize, cols: usize, settings: &'s LumenSettings) -> Self {
        Search {
            rows,
            cols,
            settings,
            kernel: gaussian_kernel(settings.smoothing_sigma_px),
            image_part: TabulatedImagePart::new(rows, cols),
            displacements: Vec::new(),
            warped: Vec::new(),
            pass: Vec::new(),
            smoothed: Vec::new(),
            sorted: Vec::new(),
            below: Vec::new(),
            opened: Vec::new(),
            labels: Vec::new(),
            runs: Vec::new(),
            run_labels: Vec::new(),
        }
    }

    /// The frame's zero-force lumen: found in the frame corrected by the image part alone (at or
    /// nearest to `near`'s centre, else to the reference lumen's), then again in the frame
    /// corrected with the vessel part on the lumen found, until centre and radius change by less
    /// than the tolerance; a region that does not overlap `near` or the previous step's lumen is
    /// not the lumen.
    fn zero_force_lumen<P: Pixel>(
        &mut self,
        frame: &FrameSearch<'_, P>,
        near: Option<Anchor>,
    ) -> Option<Anchor> {
        self.image_part.clear();
        let mut anchor = match near {
            None => self.find_lumen(frame, None, frame.model.reference, None),
            Some(near) => {
                let window = self.search_window(&near);
                same_lumen(self.find_lumen(frame, None, near, Some(window)), &near)
            }
        };
        for _ in 0..self.settings.max_iterations {
            let placed = anchor?;
            let window = self.search_window(&placed);
            let Some(found) = same_lumen(
                self.find_lumen(frame, Some(placed), placed, Some(window)),
                &placed,
            ) else {
                return Some(placed);
            };
            let change = (found.centre_x - placed.centre_x)
                .abs()
                .max((found.centre_y - placed.centre_y).abs())
                .max((found.radius - placed.radius).abs());
            anchor = Some(found);
            if change < self.settings.tolerance_px {
                break;
            }
        }
        anchor
    }

    /// The square of `window_radii` radii around `expected`, cut at the frame's edges (the whole
    /// frame where it lies outside).
    fn search_window(&self, expected: &Anchor) -> Window {
        let half = self.settings.window_radii * expected.radius;
        let span = |centre: f64, len: usize| {
            let start = (centre - half).floor().max(0.0);
            let stop = ((centre + half).ceil() + 1.0).min(len as f64);
            (start < stop).then_some(start as usize..stop as usize)
        };
        match (
            span(expected.centre_y, self.rows),
            span(expected.centre_x, self.cols),
        ) {
            (Some(rows), Some(cols)) => (rows, cols),
            _ => (0..self.rows, 0..self.cols),
        }
    }

    /// The lumen of the frame warped back with the vessel part on `lumen` (None: the image part
    /// alone): the dark region at or nearest to `seed`'s centre, in `window` (None: the whole
    /// frame); searched again in the whole frame where the window holds none or only part of it.
    fn find_lumen<P: Pixel>(
        &mut self,
        frame: &FrameSearch<'_, P>,
        lumen: Option<Anchor>,
        seed: Anchor,
        window: Option<Window>,
    ) -> Option<Anchor> {
        let (rows, cols) = window.clone().unwrap_or((0..self.rows, 0..self.cols));
        let (height, width) = (rows.len(), cols.len());
        self.warped.clear();
        self.warped.resize(height * width, 0.0);
        let pixels = Frame {
            pixels: frame.pixels,
            rows: self.rows,
            cols: self.cols,
        };
        let vessel = lumen.map(|lumen| {
            frame.model.part.frame(
                frame.terms,
                lumen,
                frame.model.model.spatial.normalization(),
                self.cols,
            )
        });
        let mut scratch = RowScratch::new(&cols);
        for (row, out) in rows.clone().zip(self.warped.chunks_exact_mut(width)) {
            // The field along the row: the image part, then the vessel part added (as
            // `FrameCorrection::tabulate_row` sums them).
            self.displacements.clear();
            self.displacements.extend_from_slice(self.image_part.row(
                &frame.image_part,
                row,
                cols.clone(),
            ));
            if let Some(vessel) = &vessel {
                vessel.add_row(row, cols.clone(), &mut self.displacements);
            }
            dispatch!(
                Simd::detected(),
                [warp_row, warp_row_avx2, warp_row_avx512](
                    &pixels,
                    row,
                    &self.displacements,
                    &mut scratch,
                    out
                )
            );
        }
        let seed_x = (seed.centre_x - cols.start as f64).clamp(0.0, width as f64 - 1.0);
        let seed_y = (seed.centre_y - rows.start as f64).clamp(0.0, height as f64 - 1.0);
        let chosen = self.segment(height, width, seed_x, seed_y);
        if window.is_some() {
            // A region on an edge of the window that is not the frame's is only a part of one.
            let partial = chosen.as_ref().is_none_or(|(_, found)| {
                (rows.start > 0 && found.top == 0)
                    || (cols.start > 0 && found.left == 0)
                    || (rows.end < self.rows && found.bottom == height - 1)
                    || (cols.end < self.cols && found.right == width - 1)
            });
            if partial {
                return self.find_lumen(frame, lumen, seed, None);
            }
        }
        chosen.map(|(label, found)| self.filled_lumen(label, &found, width, rows.start, cols.start))
    }

    /// The dark region of `warped` (height x width) at or nearest to the seed, if any, with its label.
    fn segment(
        &mut self,
        height: usize,
        width: usize,
        seed_x: f64,
        seed_y: f64,
    ) -> Option<(u32, Region)> {
        dispatch!(
            Simd::detected(),
            [segment, segment_avx2, segment_avx512](self, height, width, seed_x, seed_y)
        )
    }

    /// 8-connected regions of `opened`, labelled from 1 in raster order of their first pixel
    /// (`labels`, 0: background); `has_core` where a pixel is below `core_level`. Found as runs
    /// along the rows, each joined to the runs of the row above that it touches.
    #[inline(always)]
    fn label_regions(&mut self, height: usize, width: usize, core_level: f32) -> Vec<Region> {
        self.runs.clear();
        let mut above = 0..0; // the runs of the row above
        for (y, row) in self.opened.chunks_exact(width).enumerate() {
            let here = self.runs.len();
            let mut x = 0;
            while let Some(offset) = first_set(&row[x..]) {
                let start = x + offset;
                let end = row[start..]
                    .iter()
                    .position(|&v| v == 0)
                    .map_or(width, |length| start + length);
                let index = self.runs.len();
                self.runs.push(Run {
                    row: y,
                    columns: start..end,
                    parent: index,
                });
                // Runs of the row above ending before `start - 1` touch neither this run nor
                // those after it; the others touch it up to the first starting after `end`.
                while above.start < above.end && self.runs[above.start].columns.end < start {
                    above.start += 1;
                }
                for other in above.clone() {
                    if self.runs[other].columns.start > end {
                        break;
                    }
                    join_runs(&mut self.runs, other, index);
                }
                x = end;
            }
            above = here..self.runs.len();
        }
        // A region's root is its first run (`join_runs`): labels in order of the roots.
        self.labels.clear();
        self.labels.resize(height * width, 0);
        self.run_labels.clear();
        let mut regions: Vec<Region> = Vec::new();
        for index in 0..self.runs.len() {
            let root = root_run(&mut self.runs, index);
            let label = if root == index {
                regions.push(Region {
                    area: 0,
                    sum_x: 0.0,
                    sum_y: 0.0,
                    has_core: false,
                    top: usize::MAX,
                    left: usize::MAX,
                    bottom: 0,
                    right: 0,
                });
                regions.len() as u32
            } else {
                self.run_labels[root]
            };
            self.run_labels.push(label);
            let Run { row, columns, .. } = self.runs[index].clone();
            let pixels = row * width + columns.start..row * width + columns.end;
            let region = &mut regions[label as usize - 1];
            // Sums of whole pixel coordinates: exact in f64 (below 2^53), in any order.
            let length = columns.len();
            region.area += length;
            region.sum_x += ((columns.start + columns.end - 1) * length / 2) as f64;
            region.sum_y += (row * length) as f64;
            region.has_core |= self.smoothed[pixels.clone()]
                .iter()
                .any(|&v| v < core_level);
            region.top = region.top.min(row);
            region.bottom = region.bottom.max(row);
            region.left = region.left.min(columns.start);
            region.right = region.right.max(columns.end - 1);
            self.labels[pixels].fill(label);
        }
        regions
    }

    /// The lumen of region `found` (labelled `label`) with its holes filled: centroid and
    /// equivalent radius, in frame pixels (the window starts at `top`, `left`).
    fn filled_lumen(
        &self,
        label: u32,
        found: &Region,
        width: usize,
        top: usize,
        left: usize,
    ) -> Anchor {
        // The region's bounding box with a margin of one pixel; outside the region and reachable
        // from the margin (4-connected) is outside the lumen, the rest is the lumen.
        let (box_height, box_width) = (found.bottom - found.top + 3, found.right - found.left + 3);
        let in_region = |by: usize, bx: usize| {
            (1..box_height - 1).contains(&by)
                && (1..box_width - 1).contains(&bx)
                && self.labels[(found.top + by - 1) * width + found.left + bx - 1] == label
        };
        let mut outside = vec![false; box_height * box_width];
        let mut stack = vec![0usize];
        outside[0] = true;
        while let Some(index) = stack.pop() {
            let (by, bx) = (index / box_width, index % box_width);
            let neighbours = [
                (by.wrapping_sub(1), bx),
                (by + 1, bx),
                (by, bx.wrapping_sub(1)),
                (by, bx + 1),
            ];
            for (ny, nx) in neighbours {
                if ny < box_height && nx < box_width {
                    let neighbour = ny * box_width + nx;
                    if !outside[neighbour] && !in_region(ny, nx) {
                        outside[neighbour] = true;
                        stack.push(neighbour);
                    }
                }
            }
        }
        let (mut count, mut sum_x, mut sum_y) = (0usize, 0.0, 0.0);
        for by in 1..box_height - 1 {
            for bx in 1..box_width - 1 {
                if !outside[by * box_width + bx] {
                    count += 1;
                    sum_x += (found.left + bx - 1) as f64;
                    sum_y += (found.top + by - 1) as f64;
                }
            }
        }
        let count_f = count as f64;
        Anchor {
            centre_x: sum_x / count_f + left as f64,
            centre_y: sum_y / count_f + top as f64,
            radius: (count_f / std::f64::consts::PI).sqrt(),
        }
    }
}

/// [`Search::segment`] of `search`.
#[inline(always)]
fn segment(
    search: &mut Search<'_>,
    height: usize,
    width: usize,
    seed_x: f64,
    seed_y: f64,
) -> Option<(u32, Region)> {
    if height < 3 || width < 3 {
        return None; // too small to hold a lumen (as `segment_vessel` refuses it)
    }

    let size = height * width;
    gaussian_blur(
        (&search.warped, height, width, &search.kernel),
        &mut search.pass,
        &mut search.smoothed,
    );
    let dark = search
        .smoothed
        .iter()
        .copied()
        .fold(f32::INFINITY, f32::min);
    let tissue = median(&search.smoothed, &mut search.sorted);
    let (dark, tissue) = (dark as f64, tissue as f64);
    let anechoic = dark <= (1.0 - search.settings.min_contrast) * tissue && tissue > 0.0;
    if !anechoic {
        return None;
    }
    let threshold = (dark + search.settings.threshold_fraction * (tissue - dark)) as f32;
    let core_level = (dark + 0.5 * (tissue - dark)) as f32;
    search.below.clear();
    search
        .below
        .extend(search.smoothed.iter().map(|&v| u8::from(v < threshold)));
    open_3x3(&search.below, height, width, &mut search.opened);
    let regions = search.label_regions(height, width, core_level);
    let candidate = |label: usize| {
        let region: &Region = &regions[label - 1];
        region.area >= search.settings.min_area_px && region.has_core
    };
    let (column, row) = (
        seed_x.round_ties_even() as usize,
        seed_y.round_ties_even() as usize,
    );
    let at_seed = search.labels[row * width + column] as usize;
    let chosen = if at_seed > 0 && candidate(at_seed) {
        Some(at_seed)
    } else {
        (1..=regions.len())
            .filter(|&label| candidate(label))
            .map(|label| {
                let region = &regions[label - 1];
                let distance = (region.sum_x / region.area as f64 - seed_x)
                    .hypot(region.sum_y / region.area as f64 - seed_y);
                (distance, label)
            })
            .fold(None, |best: Option<(f64, usize)>, item| match best {
                Some(best) if best.0 <= item.0 => Some(best),
                _ => Some(item),
            })
            .map(|(_, label)| label)
    };
    debug_assert_eq!(search.labels.len(), size);
    chosen.map(|label| (label as u32, regions[label - 1]))
}

compiled_for!(
    fn segment(
        search: &mut Search<'_>,
        height: usize,
        width: usize,
        seed_x: f64,
        seed_y: f64,
    ) -> Option<(u32, Region)>;
    segment_avx2: "avx2",
    segment_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);

/// The index of the first non-zero byte of `bytes`: 16 at a time up to the block holding it.
#[inline(always)]
fn first_set(bytes: &[u8]) -> Option<usize> {
    let blocks = bytes
        .chunks_exact(16)
        .take_while(|block| u128::from_ne_bytes((*block).try_into().unwrap_or([1; 16])) == 0)
        .count();
    let offset = 16 * blocks;
    bytes[offset..]
        .iter()
        .position(|&v| v != 0)
        .map(|index| offset + index)
}

/// `found` if it overlaps `expected` (centres closer than the sum of the radii), else None.
fn same_lumen(found: Option<Anchor>, expected: &Anchor) -> Option<Anchor> {
    found.filter(|lumen| {
        (lumen.centre_x - expected.centre_x).hypot(lumen.centre_y - expected.centre_y)
            < lumen.radius + expected.radius
    })
}

/// OpenCV's Gaussian kernel for a float image: `round(8 sigma + 1) | 1` taps, normalised.
fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let taps = ((sigma * 8.0 + 1.0).round_ties_even() as usize) | 1;
    let scale = -0.5 / (sigma * sigma);
    let half = (taps - 1) as f64 * 0.5;
    let values: Vec<f32> = (0..taps)
        .map(|i| ((i as f64 - half).powi(2) * scale).exp() as f32)
        .collect();
    let sum: f64 = values.iter().map(|&v| v as f64).sum();
    values.iter().map(|&v| (v as f64 / sum) as f32).collect()
}

/// The index `position` maps to in `0..len` with the edge mirrored without repeating it
/// (OpenCV's BORDER_REFLECT_101).
fn reflect_101(mut position: i64, len: usize) -> usize {
    let len = len as i64;
    if len == 1 {
        return 0;
    }
    while position < 0 || position >= len {
        position = if position < 0 {
            -position
        } else {
            2 * len - position - 2
        };
    }
    position as usize
}

/// The image part of one frame's field (pixels), tabulated where the frame's searches have asked
/// for it: each pixel once per frame, however many windows cover it.
struct TabulatedImagePart {
    cols: usize,
    /// (lateral, axial) per frame pixel, rows x cols; set on each row's `tabulated` columns.
    values: Vec<[f64; 2]>,
    tabulated: Vec<Range<usize>>,
    coefficients: Vec<[f64; 2]>,
    row: Vec<[f64; 2]>,
}

impl TabulatedImagePart {
    fn new(rows: usize, cols: usize) -> Self {
        TabulatedImagePart {
            cols,
            values: vec![[0.0; 2]; rows * cols],
            tabulated: vec![0..0; rows],
            coefficients: Vec::new(),
            row: Vec::new(),
        }
    }

    /// Forget the values: the next frame's are tabulated anew.
    fn clear(&mut self) {
        self.tabulated.fill(0..0);
    }

    /// The image part `field` (the same frame's since the last [`Self::clear`]) along `row` at
    /// `cols`, those not tabulated yet tabulated first (with those between them and the
    /// tabulated ones: each row's tabulated columns stay one range).
    fn row(&mut self, field: &FrameCorrection, row: usize, cols: Range<usize>) -> &[[f64; 2]] {
        let done = match &self.tabulated[row] {
            done if done.is_empty() => cols.start..cols.start,
            done => done.clone(),
        };
        let wanted = cols.start.min(done.start)..cols.end.max(done.end);
        let start = row * self.cols;
        for missing in [wanted.start..done.start, done.end..wanted.end] {
            if !missing.is_empty() {
                let span = start + missing.start..start + missing.end;
                field.tabulate_row(row, missing, &mut self.coefficients, &mut self.row);
                self.values[span].copy_from_slice(&self.row);
            }
        }
        self.tabulated[row] = wanted;
        &self.values[start + cols.start..start + cols.end]
    }
}

/// A frame's pixels, rows x cols.
struct Frame<'a, P> {
    pixels: &'a [P],
    rows: usize,
    cols: usize,
}

/// Per-row buffers of [`warp_row`] for a window's columns.
struct RowScratch<P> {
    /// The window's columns, as float32.
    columns: Vec<f32>,
    /// Per column: the sample's fractional offsets `(x, y)` from its cell.
    fractions: Vec<[f32; 2]>,
    /// Per column: the sample's cell (top-left pixel `(x, y)`, within [-1, frame size)).
    cells: Vec<[i32; 2]>,
    /// Per column: the four pixels around the sample (top left, top right, bottom left, bottom right).
    corners: Vec<[P; 4]>,
}

impl<P: Pixel> RowScratch<P> {
    fn new(cols: &Range<usize>) -> Self {
        let width = cols.len();
        RowScratch {
            columns: cols.clone().map(|col| col as f32).collect(),
            fractions: vec![[0.0; 2]; width],
            cells: vec![[0; 2]; width],
            corners: vec![[P::from_f64(0.0); 4]; width],
        }
    }
}

/// `out` (a window's columns of frame row `row`, those `scratch` was made for) = the frame sampled
/// bilinearly at each pixel plus its displacement `field` ((lateral, axial) per column), indices
/// clamped to the frame (its edge replicated outside it), rounded as the frame's pixel type. Sums
/// as OpenCV's float remap.
#[inline(always)]
fn warp_row<P: Pixel>(
    frame: &Frame<'_, P>,
    row: usize,
    field: &[[f64; 2]],
    scratch: &mut RowScratch<P>,
    out: &mut [f32],
) {
    let (last_x, last_y) = (frame.cols as i32 - 1, frame.rows as i32 - 1);
    let (inner_x, inner_y) = (last_x as f32, last_y as f32);
    let (pixels, stride) = (frame.pixels, frame.cols);
    let at =
        |y: i32, x: i32| pixels[y.clamp(0, last_y) as usize * stride + x.clamp(0, last_x) as usize];
    // Where each sample lies and its weights, the four pixels around it, the blend; the first and
    // the last vectorised.
    let row = row as f32;
    for ((&[dx, dy], &col), (fraction, cell)) in field
        .iter()
        .zip(&scratch.columns)
        .zip(scratch.fractions.iter_mut().zip(scratch.cells.iter_mut()))
    {
        let source_x = dx as f32 + col;
        let source_y = dy as f32 + row;
        let (x0, y0) = (source_x.floor(), source_y.floor());
        *fraction = [source_x - x0, source_y - y0];
        // Cells beyond the frame's edge by more than one clamp to the edge as those one beyond
        // do (`max` and `min` take the number over a NaN).
        let (x0, y0) = (x0.max(-1.0).min(inner_x), y0.max(-1.0).min(inner_y));
        // SAFETY: whole numbers within [-1, frame size) and frames have fewer than 2^24 rows
        // and columns (`sweep_lumens`), so they are exact and fit an i32.
        *cell = unsafe { [x0.to_int_unchecked(), y0.to_int_unchecked()] };
    }
    for (&[x0, y0], corner) in scratch.cells.iter().zip(scratch.corners.iter_mut()) {
        *corner = if x0 >= 0 && y0 >= 0 && x0 < last_x && y0 < last_y {
            let index = y0 as usize * stride + x0 as usize;
            let (top, bottom) = (
                &pixels[index..index + 2],
                &pixels[index + stride..index + stride + 2],
            );
            [top[0], top[1], bottom[0], bottom[1]]
        } else {
            [
                at(y0, x0),
                at(y0, x0 + 1),
                at(y0 + 1, x0),
                at(y0 + 1, x0 + 1),
            ]
        };
    }
    for ((value, &[fx, fy]), corner) in out.iter_mut().zip(&scratch.fractions).zip(&scratch.corners)
    {
        let [top_left, top_right, bottom_left, bottom_right] = corner.map(P::to_f32);
        let sample = (1.0 - fy) * ((1.0 - fx) * top_left + fx * top_right)
            + fy * ((1.0 - fx) * bottom_left + fx * bottom_right);
        *value = P::rounded(sample);
    }
}

compiled_for!(
    fn warp_row<P: Pixel>(
        frame: &Frame<'_, P>,
        row: usize,
        field: &[[f64; 2]],
        scratch: &mut RowScratch<P>,
        out: &mut [f32],
    );
    warp_row_avx2: "avx2",
    warp_row_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);
compiled_for!(
    fn blur_rows(image: &[f32], width: usize, kernel: &[f32], out: &mut [f32]);
    blur_rows_avx2: "avx2",
    blur_rows_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);
compiled_for!(
    fn blur_columns(image: Blurred<'_>, out: &mut [f32]);
    blur_columns_avx2: "avx2",
    blur_columns_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);

/// An image (height x width) and the kernel it is smoothed with.
type Blurred<'a> = (&'a [f32], usize, usize, &'a [f32]);

/// `out` = `image` (height x width) smoothed by the separable `kernel`, rows first, edges mirrored;
/// each output sums its taps in order (as OpenCV's float filter).
fn gaussian_blur(
    (image, height, width, kernel): Blurred<'_>,
    pass: &mut Vec<f32>,
    out: &mut Vec<f32>,
) {
    pass.clear();
    pass.resize(height * width, 0.0);
    out.clear();
    out.resize(height * width, 0.0);
    let simd = Simd::detected();
    dispatch!(
        simd,
        [blur_rows, blur_rows_avx2, blur_rows_avx512](image, width, kernel, pass)
    );
    dispatch!(
        simd,
        [blur_columns, blur_columns_avx2, blur_columns_avx512]((pass, height, width, kernel), out)
    );
}

/// The row pass of [`gaussian_blur`] over whole rows of `image` into `out`.
#[inline(always)]
fn blur_rows(image: &[f32], width: usize, kernel: &[f32], out: &mut [f32]) {
    let half = kernel.len() / 2;
    let mut padded = vec![0.0f32; width + 2 * half];
    for (row, out_row) in image.chunks_exact(width).zip(out.chunks_exact_mut(width)) {
        // The row with its mirrored margins, then the taps one after the other over the row.
        padded[half..half + width].copy_from_slice(row);
        for i in (0..half).chain(half + width..width + 2 * half) {
            padded[i] = row[reflect_101(i as i64 - half as i64, width)];
        }
        weighted_sums(kernel, |k| &padded[k..k + width], out_row);
    }
}

/// The column pass of [`gaussian_blur`] into `out`.
#[inline(always)]
fn blur_columns((image, height, width, kernel): Blurred<'_>, out: &mut [f32]) {
    let half = kernel.len() / 2;
    for (y, out_row) in out.chunks_exact_mut(width).enumerate() {
        let source = |k: usize| reflect_101(y as i64 + k as i64 - half as i64, height) * width;
        weighted_sums(kernel, |k| &image[source(k)..source(k) + width], out_row);
    }
}

/// Columns [`weighted_sums`] sums at once (their sums held in registers).
const BLOCK: usize = 32;

/// `out[i]` = the sum of `kernel[k] * taps(k)[i]` over the taps in order, from 0.0 (`taps(k)` as
/// long as `out`); in blocks of [`BLOCK`] columns, the last ending at the last column (it may
/// overlap the one before: each column's sum is the same whatever block sums it).
#[inline(always)]
fn weighted_sums<'a>(kernel: &[f32], taps: impl Fn(usize) -> &'a [f32], out: &mut [f32]) {
    let len = out.len();
    if len < BLOCK {
        return block_sums(kernel, &taps, 0..len, out);
    }
    for start in (0..len - BLOCK).step_by(BLOCK).chain([len - BLOCK]) {
        block_sums(
            kernel,
            &taps,
            start..start + BLOCK,
            &mut out[start..start + BLOCK],
        );
    }
}

/// [`weighted_sums`] on the columns `columns` (at most [`BLOCK`]) into `out`.
#[inline(always)]
fn block_sums<'a>(
    kernel: &[f32],
    taps: &impl Fn(usize) -> &'a [f32],
    columns: Range<usize>,
    out: &mut [f32],
) {
    let mut sums = [0.0f32; BLOCK];
    let sums = &mut sums[..columns.len()];
    for (k, &weight) in kernel.iter().enumerate() {
        for (sum, &value) in sums.iter_mut().zip(&taps(k)[columns.clone()]) {
            *sum += weight * value;
        }
    }
    out.copy_from_slice(sums);
}

/// The median of `values` (not empty), the mean of the two middle values for an even count, as
/// NumPy's float32 median; `scratch` holds a copy to select in.
#[inline(always)]
fn median(values: &[f32], scratch: &mut Vec<f32>) -> f32 {
    scratch.clear();
    scratch.extend_from_slice(values);
    let middle = values.len() / 2;
    let (lower, upper, _) = scratch.select_nth_unstable_by(middle, f32::total_cmp);
    let upper = *upper;
    if values.len() % 2 == 1 {
        return upper;
    }
    let below = lower.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (below + upper) / 2.0
}

/// `out` = the 3 x 3 morphological opening of the 0/1 `mask` (height x width): erosion, then
/// dilation, pixels outside the image counting as neither (as OpenCV's default border).
#[inline(always)]
fn open_3x3(mask: &[u8], height: usize, width: usize, out: &mut Vec<u8>) {
    let mut eroded = vec![0u8; height * width];
    filter_3x3(mask, height, width, &mut eroded, u8::min);
    out.clear();
    out.resize(height * width, 0);
    filter_3x3(&eroded, height, width, out, u8::max);
}

/// `out` = `combine` (min or max) of each pixel's 3 x 3 neighbourhood within the image.
#[inline(always)]
fn filter_3x3(
    image: &[u8],
    height: usize,
    width: usize,
    out: &mut [u8],
    combine: fn(u8, u8) -> u8,
) {
    let mut across = vec![0u8; height * width];
    for (row, out_row) in image
        .chunks_exact(width)
        .zip(across.chunks_exact_mut(width))
    {
        out_row[0] = row[0];
        if width > 1 {
            out_row[0] = combine(row[0], row[1]);
            out_row[width - 1] = combine(row[width - 2], row[width - 1]);
        }
        // The pixels between the first and the last (none in a row narrower than three).
        let inner = out_row.len().saturating_sub(1).max(1);
        for (((value, &left), &centre), &right) in out_row[1..inner]
            .iter_mut()
            .zip(row)
            .zip(row.iter().skip(1))
            .zip(row.iter().skip(2))
        {
            *value = combine(combine(left, centre), right);
        }
    }
    for y in 0..height {
        let out_row = &mut out[y * width..(y + 1) * width];
        out_row.copy_from_slice(&across[y * width..(y + 1) * width]);
        for neighbour in [y.wrapping_sub(1), y + 1] {
            if neighbour < height {
                let other = &across[neighbour * width..(neighbour + 1) * width];
                for (value, &o) in out_row.iter_mut().zip(other) {
                    *value = combine(*value, o);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::Level;

    #[test]
    fn reflect_101_mirrors_without_repeating_the_edge() {
        let mapped: Vec<usize> = (-3..8).map(|p| reflect_101(p, 5)).collect();
        assert_eq!(mapped, vec![3, 2, 1, 0, 1, 2, 3, 4, 3, 2, 1]);
        assert_eq!(reflect_101(-4, 1), 0);
    }

    fn sorted_without_first(values: &[f32]) -> Vec<f32> {
        let mut sorted = values[1..].to_vec();
        sorted.sort_by(f32::total_cmp);
        sorted
    }

    #[test]
    fn median_of_even_and_odd_counts() {
        let mut scratch = Vec::new();
        assert_eq!(median(&[3.0, 1.0, 2.0], &mut scratch), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0], &mut scratch), 2.5);
        // the two middle values far apart, and many values close together
        assert_eq!(median(&[1.0, 1000.0, 0.5, 2000.0], &mut scratch), 500.5);
        let many: Vec<f32> = (0..1001)
            .map(|i| 100.0 + (i * 7919 % 1001) as f32 * 1e-3)
            .collect();
        let mut sorted = many.clone();
        sorted.sort_by(f32::total_cmp);
        assert_eq!(median(&many, &mut scratch), sorted[500]);
        assert_eq!(
            median(&many[1..], &mut scratch),
            (sorted_without_first(&many)[499] + sorted_without_first(&many)[500]) / 2.0
        );
    }

    #[test]
    fn median_selects_what_a_sort_gives() {
        // repeated values, negative numbers and both zeros; odd and even counts
        let mut scratch = Vec::new();
        let mut state = 12345u64;
        for len in [1usize, 2, 3, 4, 5, 10, 101, 1000, 4097] {
            for levels in [3u64, 50, 1 << 20] {
                let values: Vec<f32> = (0..len)
                    .map(|_| {
                        state = state
                            .wrapping_mul(6364136223846793005)
                            .wrapping_add(1442695040888963407);
                        ((state >> 33) % levels) as f32 * 0.37 - 5.0
                    })
                    .collect();
                let mut sorted = values.clone();
                sorted.sort_by(f32::total_cmp);
                let expected = match len % 2 {
                    1 => sorted[len / 2],
                    _ => (sorted[len / 2 - 1] + sorted[len / 2]) / 2.0,
                };
                let got = median(&values, &mut scratch);
                assert_eq!(
                    got.to_bits(),
                    expected.to_bits(),
                    "{len} values of {levels}"
                );
            }
        }
        assert_eq!(median(&[0.0, -0.0, 7.0, -0.0], &mut scratch).to_bits(), 0);
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_vector_paths_warp_and_blur_as_the_baseline() {
        let (rows, cols) = (23, 37);
        let pixels: Vec<u8> = (0..rows * cols).map(|i| (i * 7919 % 251) as u8).collect();
        let frame = Frame {
            pixels: &pixels,
            rows,
            cols,
        };
        // samples inside the frame, beyond its edges and a row away from them
        let columns = 3..31;
        let field: Vec<[f64; 2]> = columns
            .clone()
            .map(|c| [(c as f64 * 0.77).sin() * 9.3, (c as f64 * 1.3).cos() * 30.0])
            .collect();
        let image: Vec<f32> = (0..rows * cols)
            .map(|i| (i * 31 % 97) as f32 * 1.7)
            .collect();
        let kernel = gaussian_kernel(2.0);
        let run = |level: Level| {
            let mut scratch = RowScratch::new(&columns);
            let mut warped = vec![0.0; columns.len()];
            let (mut pass, mut blurred) = (vec![0.0; rows * cols], vec![0.0; rows * cols]);
            // SAFETY: only the levels this CPU has are run.
            unsafe {
                match level {
                    Level::Baseline => {
                        warp_row(&frame, 5, &field, &mut scratch, &mut warped);
                        blur_rows(&image, cols, &kernel, &mut pass);
                        blur_columns((&pass, rows, cols, &kernel), &mut blurred);
                    }
                    Level::Avx2 => {
                        warp_row_avx2(&frame, 5, &field, &mut scratch, &mut warped);
                        blur_rows_avx2(&image, cols, &kernel, &mut pass);
                        blur_columns_avx2((&pass, rows, cols, &kernel), &mut blurred);
                    }
                    Level::Avx512 => {
                        warp_row_avx512(&frame, 5, &field, &mut scratch, &mut warped);
                        blur_rows_avx512(&image, cols, &kernel, &mut pass);
                        blur_columns_avx512((&pass, rows, cols, &kernel), &mut blurred);
                    }
                }
            }
            (warped, blurred)
        };
        let baseline = run(Level::Baseline);
        for simd in Simd::available() {
            assert_eq!(run(simd.level()), baseline, "{simd:?}");
        }
    }

    #[test]
    fn gaussian_kernel_has_opencv_taps_and_sums_to_one() {
        let kernel = gaussian_kernel(2.0);
        assert_eq!(kernel.len(), 17);
        let sum: f32 = kernel.iter().sum();
        assert!((sum - 1.0).abs() < 1e-6);
        assert!(kernel[8] > kernel[7] && (kernel[7] - kernel[9]).abs() < 1e-9);
    }

    #[test]
    fn blur_keeps_a_constant_image() {
        // the kernel sums to one and the edges are mirrored, also where the image is narrower
        // than the kernel
        let kernel = gaussian_kernel(2.0);
        let (mut pass, mut out) = (Vec::new(), Vec::new());
        gaussian_blur((&[3.0; 12], 3, 4, &kernel), &mut pass, &mut out);
        assert!(out.iter().all(|v| (v - 3.0).abs() < 1e-5), "{out:?}");
    }

    #[test]
    fn tiny_images_hold_no_lumen_and_do_not_panic() {
        let settings = LumenSettings {
            window_radii: 2.5,
            tolerance_px: 0.25,
            max_iterations: 8,
            smoothing_sigma_px: 2.0,
            threshold_fraction: 0.8,
            min_contrast: 0.5,
            min_area_px: 20,
        };
        for (height, width) in [(1, 1), (1, 7), (7, 1), (2, 9), (9, 2)] {
            let mut search = Search::new(height, width, &settings);
            search.warped = (0..height * width)
                .map(|i| (i % 3) as f32 * 100.0)
                .collect();
            assert!(search.segment(height, width, 0.0, 0.0).is_none());
            let mut out = Vec::new();
            open_3x3(&vec![1; height * width], height, width, &mut out);
            assert!(out.iter().all(|&v| v == 1), "{height} x {width}");
        }
    }

    /// Settings for the small test windows: a 1-pixel blur, regions of 20 pixels or more.
    fn small_window_settings() -> LumenSettings {
        LumenSettings {
            window_radii: 2.5,
            tolerance_px: 0.25,
            max_iterations: 8,
            smoothing_sigma_px: 1.0,
            threshold_fraction: 0.8,
            min_contrast: 0.5,
            min_area_px: 20,
        }
    }

    #[test]
    fn regions_are_8_connected_and_labelled_in_raster_order() {
        let settings = small_window_settings();
        // a U whose arms meet two rows down (after the diagonal has begun), a diagonal
        let mask = [
            "1.1..1.", //
            "1.1...1", //
            "111..1.", //
            "......1", //
        ];
        let (height, width) = (mask.len(), mask[0].len());
        let mut search = Search::new(height, width, &settings);
        search.opened = mask.concat().bytes().map(|b| u8::from(b == b'1')).collect();
        search.smoothed = vec![1.0; height * width];
        search.smoothed[width + 6] = 0.0;
        let regions = search.label_regions(height, width, 0.5);
        let expected = [
            "1.1..2.", //
            "1.1...2", //
            "111..2.", //
            "......2", //
        ];
        let labels: String = search
            .labels
            .iter()
            .map(|&l| {
                if l == 0 {
                    '.'
                } else {
                    char::from(b'0' + l as u8)
                }
            })
            .collect();
        assert_eq!(labels, expected.concat());
        let summary: Vec<_> = regions
            .iter()
            .map(|r| {
                (
                    r.area, r.sum_x, r.sum_y, r.has_core, r.top, r.left, r.bottom, r.right,
                )
            })
            .collect();
        assert_eq!(
            summary,
            [
                (7, 7.0, 8.0, false, 0, 0, 2, 2),
                (4, 22.0, 6.0, true, 0, 5, 3, 6)
            ]
        );
    }

    #[test]
    fn opening_removes_specks_and_keeps_blocks() {
        let (height, width) = (6, 6);
        let mut mask = vec![0u8; 36];
        mask[0] = 1; // a speck in the corner
        for y in 2..5 {
            for x in 2..5 {
                mask[y * width + x] = 1;
            }
        }
        let mut out = Vec::new();
        open_3x3(&mask, height, width, &mut out);
        let mut expected = mask.clone();
        expected[0] = 0;
        assert_eq!(out, expected);
    }

    #[test]
    fn a_ring_is_filled_and_a_blob_is_found_nearest_the_seed() {
        let settings = small_window_settings();
        let (height, width) = (40, 40);
        let mut search = Search::new(height, width, &settings);
        // bright tissue with a dark ring (radii 4 to 8) around (20, 15): its hole is filled
        search.warped = (0..height * width)
            .map(|i| {
                let (y, x) = ((i / width) as f64, (i % width) as f64);
                let distance = (x - 20.0).hypot(y - 15.0);
                if (4.0..8.0).contains(&distance) {
                    5.0
                } else {
                    200.0
                }
            })
            .collect();
        let (label, region) = search.segment(height, width, 2.0, 2.0).expect("a region");
        let lumen = search.filled_lumen(label, &region, width, 10, 100);
        assert!((lumen.centre_x - 120.0).abs() < 0.5 && (lumen.centre_y - 25.0).abs() < 0.5);
        // the threshold at 0.8 of the way to the tissue widens the ring by about a pixel either way
        assert!((lumen.radius - 8.8).abs() < 0.3, "{}", lumen.radius);
        let hole = std::f64::consts::PI * lumen.radius.powi(2) - region.area as f64;
        assert!(hole > 15.0, "hole of {hole} pixels"); // the hole: radius 4 less about a pixel
    }
}
