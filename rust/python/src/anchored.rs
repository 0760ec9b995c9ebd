//! `usdeform._core.VesselPart`: the vessel part of a vessel-anchored model, converted and checked
//! once; the warps and the compounder take it with each frame's lumen (`anchors`), which
//! `usdeform._core.sweep_lumens` finds.

use numpy::{PyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;

use usdeform_core::anchored::{self, Anchor};
use usdeform_core::frame_correction::{self, PlacedVessel};
use usdeform_core::lumen::{self, AnchoredModel, LumenSettings, LumenTrack};

use crate::conversion::{
    as_slice, field_array, profile_from, typed_array, with_frame_stack, FrameInputs, Frames,
};
use crate::errors::{input_error, run_kernel, CoreError};
use crate::model::Model;

/// The vessel part of a vessel-anchored model: coefficients (2, 3, n, n) (component, force term
/// 1/h/h^2, y and x inner function), the reference lumen's radius (pixels) and the window's
/// half-width in lumen radii.
#[pyclass(frozen, module = "usdeform._core")]
pub struct VesselPart {
    pub inner: anchored::VesselPart,
}

#[pymethods]
impl VesselPart {
    #[new]
    fn new(
        py: Python<'_>,
        coefficients: &Bound<'_, PyAny>,
        reference_radius_px: f64,
        window_radii: f64,
    ) -> PyResult<Self> {
        let array = typed_array::<f64>(
            py,
            "vessel_coefficients",
            coefficients,
            &[Some(2), Some(3), None, None],
            "(2, 3, n, n)",
        )?;
        let shape = array.shape();
        if shape[2] != shape[3] {
            return Err(input_error(format!(
                "vessel_coefficients: expected shape (2, 3, n, n), got {shape:?}"
            )));
        }
        let values = as_slice("vessel_coefficients", &array)?;
        let inner = anchored::VesselPart::new(values, shape[2], reference_radius_px, window_radii)
            .map_err(CoreError)?;
        Ok(VesselPart { inner })
    }

    /// The displacement D(x, y, F) (pixels) of `model`'s image part plus this vessel part on
    /// `anchor` ((x, y, radius), pixels; None: the image part alone), on the window of rows
    /// `rows` = (start, stop) and columns `cols` of the model's frame: (2, window rows, window
    /// columns).
    #[pyo3(signature = (model, force_n, profile, anchor, rows, cols))]
    #[allow(clippy::too_many_arguments)]
    fn displacement<'py>(
        &self,
        py: Python<'py>,
        model: &Bound<'py, Model>,
        force_n: f64,
        profile: (f64, f64, f64),
        anchor: Option<(f64, f64, f64)>,
        rows: (usize, usize),
        cols: (usize, usize),
    ) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let anchor = anchor
            .map(|(x, y, radius)| Anchor::from_triples("anchor", &[x, y, radius]))
            .transpose()
            .map_err(CoreError)?
            .map(|anchors| anchors[0]);
        let (model, profile) = (&model.get().inner, profile_from(profile));
        let field = run_kernel(py, None, || {
            frame_correction::anchored_field(
                model,
                &self.inner,
                force_n,
                &profile,
                anchor,
                rows.0..rows.1,
                cols.0..cols.1,
            )
        })?;
        field_array(
            py,
            field,
            rows.1.saturating_sub(rows.0),
            cols.1.saturating_sub(cols.0),
        )
    }
}

/// The lumens `anchors` ((n_frames, 3) of (x, y, radius), pixels) that `vessel` is placed on, both
/// given or neither.
pub fn anchors_from(
    py: Python<'_>,
    vessel: Option<&Bound<'_, VesselPart>>,
    anchors: Option<&Bound<'_, PyAny>>,
    n_frames: usize,
) -> PyResult<Option<Vec<Anchor>>> {
    match (vessel, anchors) {
        (None, None) => Ok(None),
        (Some(_), Some(anchors)) => {
            let array = typed_array::<f64>(
                py,
                "anchors",
                anchors,
                &[Some(n_frames), Some(3)],
                "(n_frames, 3) of (x, y, radius) per frame",
            )?;
            let values = as_slice("anchors", &array)?;
            Ok(Some(
                Anchor::from_triples("anchors", values).map_err(CoreError)?,
            ))
        }
        _ => Err(input_error(
            "vessel, anchors: a vessel part needs the lumen of each frame, and the lumens a vessel part",
        )),
    }
}

/// `vessel` placed on `anchors` (see [`anchors_from`]).
pub fn placed<'a>(
    vessel: Option<&'a Bound<'_, VesselPart>>,
    anchors: &'a Option<Vec<Anchor>>,
) -> Option<PlacedVessel<'a>> {
    vessel
        .zip(anchors.as_deref())
        .map(|(vessel, anchors)| PlacedVessel {
            part: &vessel.get().inner,
            anchors,
        })
}

/// The lumen search's settings with the lumen a model was fitted with (`reference`, (x, y,
/// radius), pixels), checked once: what `sweep_lumens` and `Accumulator.insert_anchored` take.
#[pyclass(frozen, module = "usdeform._core")]
pub struct LumenSearch {
    pub reference: Anchor,
    pub settings: LumenSettings,
}

#[pymethods]
impl LumenSearch {
    #[new]
    #[pyo3(signature = (
        reference, *, window_radii, tolerance_px, max_iterations, smoothing_sigma_px,
        threshold_fraction, min_contrast, min_area_px,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        reference: Lumen,
        window_radii: f64,
        tolerance_px: f64,
        max_iterations: usize,
        smoothing_sigma_px: f64,
        threshold_fraction: f64,
        min_contrast: f64,
        min_area_px: usize,
    ) -> PyResult<Self> {
        let settings = LumenSettings {
            window_radii,
            tolerance_px,
            max_iterations,
            smoothing_sigma_px,
            threshold_fraction,
            min_contrast,
            min_area_px,
        };
        settings.check().map_err(CoreError)?;
        Ok(LumenSearch {
            reference: anchor_of("reference", reference)?,
            settings,
        })
    }
}

/// A lumen (x, y, radius), pixels.
pub type Lumen = (f64, f64, f64);

pub fn anchor_of(argument: &'static str, (x, y, radius): Lumen) -> PyResult<Anchor> {
    Ok(Anchor::from_triples(argument, &[x, y, radius]).map_err(CoreError)?[0])
}

pub fn lumen_of(anchor: Anchor) -> Lumen {
    (anchor.centre_x, anchor.centre_y, anchor.radius)
}

/// Each frame's zero-force lumen ((x, y, radius), pixels; None where none is found) for `model`'s
/// image part and `vessel`, searched as `search` says, where the previous frame's lumen was; the
/// search goes on from `last_found` (None: none yet) and `frames_missed`. Returns the lumens and
/// where the search stands after the last frame: (lumens, last_found, frames_missed). Serial:
/// the frames depend on each other.
#[pyfunction]
#[pyo3(signature = (frames, forces, profiles, model, vessel, search, *, last_found, frames_missed))]
#[allow(clippy::too_many_arguments)]
fn sweep_lumens<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    forces: &Bound<'py, PyAny>,
    profiles: &Bound<'py, PyAny>,
    model: &Bound<'py, Model>,
    vessel: &Bound<'py, VesselPart>,
    search: &Bound<'py, LumenSearch>,
    last_found: Option<Lumen>,
    frames_missed: usize,
) -> PyResult<(Vec<Option<Lumen>>, Option<Lumen>, usize)> {
    let frames = Frames::extract(py, frames)?;
    let inputs = FrameInputs::extract(py, forces, profiles)?;
    let correction = inputs.correction(&model.get().inner, None)?;
    let search = search.get();
    let searched = AnchoredModel {
        model: correction.model,
        part: &vessel.get().inner,
        reference: search.reference,
    };
    let mut track = LumenTrack {
        last_found: last_found.map(|l| anchor_of("last_found", l)).transpose()?,
        frames_missed,
    };
    let found = with_frame_stack!(&frames, |stack| {
        run_kernel(py, None, || {
            lumen::sweep_lumens(
                &stack,
                correction.forces,
                correction.profiles,
                &searched,
                &search.settings,
                &mut track,
            )
        })
    })?;
    Ok((
        found.into_iter().map(|a| a.map(lumen_of)).collect(),
        track.last_found.map(lumen_of),
        track.frames_missed,
    ))
}

pub fn register(module: &Bound<'_, PyModule>) -> PyResult<()> {
    module.add_class::<VesselPart>()?;
    module.add_class::<LumenSearch>()?;
    module.add_function(wrap_pyfunction!(sweep_lumens, module)?)?;
    Ok(())
}
