//! `usdeform._core.Accumulator`: frames inserted into a voxel volume, batch after batch.

use std::sync::{Mutex, MutexGuard, TryLockError};

use numpy::PyReadonlyArrayDyn;
use pyo3::prelude::*;

use usdeform_core::compound::{self, Compounding, Interpolation};
use usdeform_core::warp::Pixel;

use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};

use usdeform_core::frame_correction::{Correction, PlacedVessel};
use usdeform_core::lumen::{self, AnchoredModel, LumenTrack};

use crate::anchored::{anchor_of, anchors_from, lumen_of, placed, Lumen, LumenSearch, VesselPart};
use crate::conversion::{
    as_slice, frames_array, poses_from, typed_array, with_frame_stack, FrameInputs, Frames,
};
use crate::errors::{
    checked_threads, chunks_of, frame_chunks, input_error, internal_error, run_kernel, CoreError,
    Pool, UsdeformError, FRAMES_PER_CHUNK,
};
use crate::model::Model;

/// The frames, poses, per-frame inputs and worker pool of an insertion with correction, converted
/// and checked (`fill` against the frames' type).
fn corrected_inputs<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    image_to_world: &Bound<'py, PyAny>,
    forces: &Bound<'py, PyAny>,
    profiles: &Bound<'py, PyAny>,
    fill: f64,
    threads: Option<usize>,
) -> PyResult<(
    Frames<'py>,
    PyReadonlyArrayDyn<'py, f64>,
    FrameInputs<'py>,
    Pool,
)> {
    let frames = Frames::extract(py, frames)?;
    let poses = poses_from(py, image_to_world, frames.shape()[0])?;
    let inputs = FrameInputs::extract(py, forces, profiles)?;
    frames.check_fill(fill)?;
    Ok((frames, poses, inputs, Pool::new(threads)?))
}

fn parse_interpolation(name: &str) -> PyResult<Interpolation> {
    match name {
        "nearest" => Ok(Interpolation::Nearest),
        "linear" => Ok(Interpolation::Linear),
        other => Err(input_error(format!(
            "interpolation: expected 'nearest' or 'linear', got {other:?}"
        ))),
    }
}

fn parse_compounding(name: &str) -> PyResult<Compounding> {
    match name {
        "mean" => Ok(Compounding::Mean),
        "max" => Ok(Compounding::Maximum),
        "latest" => Ok(Compounding::Latest),
        other => Err(input_error(format!(
            "compounding: expected 'mean', 'max' or 'latest', got {other:?}"
        ))),
    }
}

/// A voxel accumulator that frames are inserted into, batch after batch (PLUS-style compounding).
///
/// Safe to share between threads: a call while another thread's call is running on the same
/// accumulator fails with a UsdeformError instead of waiting (a wait could deadlock on the GIL).
#[pyclass(frozen, module = "usdeform._core")]
struct Accumulator {
    inner: Mutex<compound::Accumulator>,
}

impl Accumulator {
    fn lock(&self) -> PyResult<MutexGuard<'_, compound::Accumulator>> {
        match self.inner.try_lock() {
            Ok(guard) => Ok(guard),
            // A poisoned lock only follows a panic, which the kernels catch before it unwinds here.
            Err(TryLockError::Poisoned(poisoned)) => Ok(poisoned.into_inner()),
            Err(TryLockError::WouldBlock) => Err(UsdeformError::new_err(
                "Compounder: another thread is using this compounder; give each thread its own \
                 compounder or serialise the calls with a lock",
            )),
        }
    }
}

/// The frames' validity mask, bool of the frames' shape, or None.
fn valid_from<'py>(
    py: Python<'py>,
    valid: Option<&Bound<'py, PyAny>>,
    shape: [usize; 3],
) -> PyResult<Option<PyReadonlyArrayDyn<'py, bool>>> {
    valid
        .map(|valid| {
            typed_array::<bool>(
                py,
                "valid",
                valid,
                &shape.map(Some),
                "of the frames' shape (n_frames, rows, cols), bool",
            )
        })
        .transpose()
}

#[pymethods]
impl Accumulator {
    /// `shape` (z, y, x) voxels, `index_to_world` (4, 4) mm; fails before allocating beyond `max_bytes`.
    #[new]
    #[pyo3(signature = (shape, index_to_world, interpolation, compounding, max_bytes))]
    fn new(
        py: Python<'_>,
        shape: (usize, usize, usize),
        index_to_world: &Bound<'_, PyAny>,
        interpolation: &str,
        compounding: &str,
        max_bytes: u128,
    ) -> PyResult<Self> {
        let index_to_world = typed_array::<f64>(
            py,
            "index_to_world",
            index_to_world,
            &[Some(4), Some(4)],
            "(4, 4)",
        )?;
        let index_to_world = as_slice("index_to_world", &index_to_world)?;
        let (interpolation, compounding) = (
            parse_interpolation(interpolation)?,
            parse_compounding(compounding)?,
        );
        let inner = run_kernel(py, None, || {
            compound::Accumulator::new(
                [shape.0, shape.1, shape.2],
                index_to_world,
                interpolation,
                compounding,
                max_bytes,
            )
        })?;
        Ok(Accumulator {
            inner: Mutex::new(inner),
        })
    }

    /// Insert frames (n_frames, rows, cols) at their `image_to_world` poses (n_frames, 4, 4), mm;
    /// pixels whose `valid` flag (bool, the frames' shape) is False are left out.
    #[pyo3(signature = (frames, image_to_world, *, valid=None, threads=None))]
    fn insert(
        &self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        valid: Option<&Bound<'_, PyAny>>,
        threads: Option<usize>,
    ) -> PyResult<()> {
        let frames = Frames::extract(py, frames)?;
        let shape = frames.shape();
        let poses = poses_from(py, image_to_world, shape[0])?;
        let poses = as_slice("image_to_world", &poses)?;
        let valid = valid_from(py, valid, shape)?;
        let valid = valid.as_ref().map(|v| as_slice("valid", v)).transpose()?;
        let pool = Pool::new(threads)?;
        let mut inner = self.lock()?;
        let inner = &mut *inner;
        inner.check_poses(shape[0], poses).map_err(CoreError)?;
        let frame_size = shape[1] * shape[2];
        with_frame_stack!(&frames, |stack| {
            for chunk in frame_chunks(shape[0]) {
                py.check_signals()?;
                let chunk_valid =
                    valid.map(|v| &v[chunk.start * frame_size..chunk.end * frame_size]);
                let chunk_poses = &poses[chunk.start * 16..chunk.end * 16];
                let chunk_stack = stack.frames(chunk);
                pool.run(py, || inner.insert(&chunk_stack, chunk_poses, chunk_valid))?;
            }
            Ok(())
        })
    }

    /// Warp frames back to zero force (as `warp_frames`) and insert them, without keeping the
    /// corrected frames. Pixels sampled from outside their frame are left out when
    /// `exclude_invalid`, else inserted with the value `fill`. With `vessel` and `anchors`, the
    /// vessel part on each frame's lumen is added to the model's field (as `warp_frames`).
    #[pyo3(signature = (frames, image_to_world, forces, profiles, model, *, fill=0.0, exclude_invalid=true, threads=None, vessel=None, anchors=None))]
    #[allow(clippy::too_many_arguments)]
    fn insert_corrected(
        &self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        forces: &Bound<'_, PyAny>,
        profiles: &Bound<'_, PyAny>,
        model: &Bound<'_, Model>,
        fill: f64,
        exclude_invalid: bool,
        threads: Option<usize>,
        vessel: Option<&Bound<'_, VesselPart>>,
        anchors: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        let (frames, poses, inputs, pool) =
            corrected_inputs(py, frames, image_to_world, forces, profiles, fill, threads)?;
        let [n_frames, rows, cols] = frames.shape();
        let poses = as_slice("image_to_world", &poses)?;
        let anchors = anchors_from(py, vessel, anchors, n_frames)?;
        let correction = inputs.correction(&model.get().inner, placed(vessel, &anchors))?;
        let mut inner = self.lock()?;
        let inner = &mut *inner;
        // Checked for all frames first: errors name the frame in the whole stack, and a failed
        // call inserts nothing.
        inner.check_poses(n_frames, poses).map_err(CoreError)?;
        pool.run(py, || {
            correction.frame_fields(n_frames, rows, cols).map(|_| ())
        })?;
        with_frame_stack!(&frames, |stack| {
            let fill = Pixel::from_f64(fill);
            for chunk in frame_chunks(n_frames) {
                py.check_signals()?;
                let chunk_poses = &poses[chunk.start * 16..chunk.end * 16];
                let (chunk_stack, chunk_correction) =
                    (stack.frames(chunk.clone()), correction.frames(chunk));
                pool.run(py, || {
                    inner.insert_corrected(
                        &chunk_stack,
                        chunk_poses,
                        &chunk_correction,
                        fill,
                        exclude_invalid,
                    )
                })?;
            }
            Ok(())
        })
    }

    /// Correct frames with a vessel-anchored model (`model`'s image part, `vessel`) and insert them,
    /// as `sweep_lumens` then `insert_corrected` with each frame's vessel part on its lumen (or the
    /// last lumen found before it; the reference lumen before any), giving the same volume: the
    /// lumen search runs frame after frame on one of the `threads` (None: all cores), while the
    /// frames whose lumens are found are warped and inserted on the others (with one thread, the
    /// search and the insertion take turns, chunk by chunk). Every argument is checked, and every
    /// frame's force, profile and pose, before anything is inserted; after that only a failed
    /// allocation can stop the search part-way. The search goes on from `last_found` (None: none
    /// yet; the first placement is then the reference lumen) and `frames_missed`, as for
    /// `sweep_lumens`; returns where it stands after the last frame: (last_found, frames_missed).
    #[pyo3(signature = (frames, image_to_world, forces, profiles, model, vessel, search, *, last_found, frames_missed, fill=0.0, exclude_invalid=true, threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn insert_anchored(
        &self,
        py: Python<'_>,
        frames: &Bound<'_, PyAny>,
        image_to_world: &Bound<'_, PyAny>,
        forces: &Bound<'_, PyAny>,
        profiles: &Bound<'_, PyAny>,
        model: &Bound<'_, Model>,
        vessel: &Bound<'_, VesselPart>,
        search: &Bound<'_, LumenSearch>,
        last_found: Option<Lumen>,
        frames_missed: usize,
        fill: f64,
        exclude_invalid: bool,
        threads: Option<usize>,
    ) -> PyResult<(Option<Lumen>, usize)> {
        let start = LumenTrack {
            last_found: last_found.map(|l| anchor_of("last_found", l)).transpose()?,
            frames_missed,
        };
        // The search takes one of the threads, the insertion the others (at least one).
        let threads = checked_threads(threads)?;
        let inserting = threads
            .unwrap_or_else(rayon::current_num_threads)
            .saturating_sub(1)
            .max(1);
        let (frames, poses, inputs, pool) = corrected_inputs(
            py,
            frames,
            image_to_world,
            forces,
            profiles,
            fill,
            Some(inserting),
        )?;
        let [n_frames, rows, cols] = frames.shape();
        let poses = as_slice("image_to_world", &poses)?;
        let image_part = inputs.correction(&model.get().inner, None)?;
        let (part, search) = (&vessel.get().inner, search.get());
        let searched = AnchoredModel {
            model: image_part.model,
            part,
            reference: search.reference,
        };
        let mut inner = self.lock()?;
        let inner = &mut *inner;
        inner.check_poses(n_frames, poses).map_err(CoreError)?;
        pool.run(py, || {
            image_part.frame_fields(n_frames, rows, cols).map(|_| ())
        })?;
        with_frame_stack!(&frames, |stack| {
            let fill = Pixel::from_f64(fill);
            let chunks: Vec<_> = chunks_of(n_frames, compound::FRAMES_PER_BATCH).collect();
            // One chunk's lumens, the search going on from `track`; a panic caught.
            let search_chunk = |chunk: Range<usize>, track: &mut LumenTrack| {
                catch_unwind(AssertUnwindSafe(|| {
                    lumen::sweep_lumens(
                        &stack.frames(chunk.clone()),
                        &image_part.forces[chunk.clone()],
                        &image_part.profiles[chunk],
                        &searched,
                        &search.settings,
                        track,
                    )
                }))
            };
            std::thread::scope(|scope| {
                // With more than one thread the search runs ahead on a thread of its own.
                // It returns where the search stands after its last chunk.
                let (mut receiver, searcher) = match threads {
                    Some(1) => (None, None),
                    _ => {
                        let (sender, receiver) = std::sync::mpsc::sync_channel(2);
                        let search_chunks = chunks.clone();
                        let searcher = scope.spawn(move || {
                            let mut track = start;
                            for chunk in search_chunks {
                                let found = search_chunk(chunk, &mut track);
                                let stop = !matches!(found, Ok(Ok(_)));
                                if sender.send(found).is_err() || stop {
                                    break; // the inserting side stopped, or the search failed
                                }
                            }
                            track
                        });
                        (Some(receiver), Some(searcher))
                    }
                };
                let mut track = start;
                let mut last = start.last_found.unwrap_or(search.reference);
                for chunk in chunks {
                    py.check_signals()?;
                    let message = match receiver.take() {
                        // The receiver moves to the thread that waits without the GIL, and back.
                        Some(waiting) => {
                            let (returned, message) = py.detach(move || {
                                let message = waiting.recv();
                                (waiting, message)
                            });
                            receiver = Some(returned);
                            message.unwrap_or_else(|_| Err(Box::new("the lumen search stopped")))
                        }
                        None => py.detach(|| search_chunk(chunk.clone(), &mut track)),
                    };
                    let found = match message {
                        Ok(found) => found.map_err(CoreError)?,
                        Err(panic) => return Err(internal_error(panic)),
                    };
                    let placed = lumen::placements(&found, &mut last);
                    let correction = Correction {
                        forces: &image_part.forces[chunk.clone()],
                        profiles: &image_part.profiles[chunk.clone()],
                        vessel: Some(PlacedVessel {
                            part,
                            anchors: &placed,
                        }),
                        ..image_part
                    };
                    let chunk_poses = &poses[chunk.start * 16..chunk.end * 16];
                    let chunk_stack = stack.frames(chunk);
                    pool.run(py, || {
                        inner.insert_corrected(
                            &chunk_stack,
                            chunk_poses,
                            &correction,
                            fill,
                            exclude_invalid,
                        )
                    })?;
                }
                if let Some(searcher) = searcher {
                    track = searcher.join().map_err(internal_error)?;
                }
                Ok((track.last_found.map(lumen_of), track.frames_missed))
            })
        })
    }

    /// The compounded image and the coverage weight, both float32 (z, y, x).
    fn volume<'py>(&self, py: Python<'py>) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let inner = self.lock()?;
        let shape = inner.shape();
        let inner = &*inner;
        let (image, weight) = run_kernel(py, None, || inner.volume())?;
        Ok((
            frames_array(py, image, shape)?,
            frames_array(py, weight, shape)?,
        ))
    }

    /// The image and coverage weight of `volume()` in the voxel box from `lo` (first voxel, z, y,
    /// x) to `hi` (one past the last), both float32 of shape `hi - lo`; only the box is computed.
    /// InputError (a ValueError) naming the bound unless `0 <= lo < hi <= shape` on every axis.
    fn volume_region<'py>(
        &self,
        py: Python<'py>,
        lo: (i64, i64, i64),
        hi: (i64, i64, i64),
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let (lo, hi) = ([lo.0, lo.1, lo.2], [hi.0, hi.1, hi.2]);
        let inner = self.lock()?;
        let inner = &*inner;
        let (image, weight) = run_kernel(py, None, || inner.volume_region(lo, hi))?;
        let shape: [usize; 3] = std::array::from_fn(|axis| (hi[axis] - lo[axis]) as usize);
        Ok((
            frames_array(py, image, shape)?,
            frames_array(py, weight, shape)?,
        ))
    }

    #[getter]
    fn frames_inserted(&self) -> PyResult<usize> {
        Ok(self.lock()?.frames_inserted())
    }

    #[getter]
    fn shape(&self) -> PyResult<(usize, usize, usize)> {
        let [z, y, x] = self.lock()?.shape();
        Ok((z, y, x))
    }
}

// Chunking the frames must never change the compounded volume.
const _: () = assert!(FRAMES_PER_CHUNK % compound::FRAMES_PER_BATCH == 0);

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<Accumulator>()?;
    module.add("BYTES_PER_VOXEL", compound::BYTES_PER_VOXEL)?;
    Ok(())
}
