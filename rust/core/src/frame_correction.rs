//! One frame's displacement for a correction: the model's field plus, for a vessel-anchored model,
//! the vessel part placed on the frame's lumen ([`crate::anchored`]).

use std::ops::Range;

use crate::anchored::{Anchor, FrameVessel, VesselPart};
use crate::error::{check_finite, check_len, KernelError, Result};
use crate::field::FrameField;
use crate::model::DeformationModel;
use crate::simd::{compiled_for, dispatch, Simd};
use crate::stiffness::StiffnessProfile;
use crate::terms::{zeroed, RowField};

/// Per-frame correction settings: the model, each frame's force (N) and stiffness profile, and for
/// a vessel-anchored model its vessel part with each frame's lumen.
#[derive(Debug, Clone, Copy)]
pub struct Correction<'a> {
    pub model: &'a DeformationModel,
    pub forces: &'a [f64],
    pub profiles: &'a [StiffnessProfile],
    pub vessel: Option<PlacedVessel<'a>>,
}

/// A vessel part and the lumen each frame places it on.
#[derive(Debug, Clone, Copy)]
pub struct PlacedVessel<'a> {
    pub part: &'a VesselPart,
    pub anchors: &'a [Anchor],
}

impl<'a> Correction<'a> {
    /// The settings of the frames `range` only.
    pub fn frames(&self, range: std::ops::Range<usize>) -> Correction<'a> {
        Correction {
            model: self.model,
            forces: &self.forces[range.clone()],
            profiles: &self.profiles[range.clone()],
            vessel: self.vessel.map(|vessel| PlacedVessel {
                part: vessel.part,
                anchors: &vessel.anchors[range],
            }),
        }
    }

    /// The displacement field of every frame of `n_frames` on a `rows x cols` grid (validated; the
    /// grid must be the model's frame shape).
    pub fn frame_fields(
        &self,
        n_frames: usize,
        rows: usize,
        cols: usize,
    ) -> Result<Vec<FrameCorrection>> {
        self.model.check_frame_shape(rows, cols)?;
        check_len("forces", self.forces, n_frames)?;
        check_len("profiles", self.profiles, n_frames)?;
        check_finite("forces", self.forces)?;
        if let Some(vessel) = &self.vessel {
            check_len("anchors", vessel.anchors, n_frames)?;
        }
        let terms = (0..n_frames)
            .map(|frame| {
                self.model
                    .frame_terms(self.forces[frame], &self.profiles[frame], frame)
            })
            .collect::<Result<Vec<_>>>()?;
        let normalization = self.model.spatial.normalization();
        Ok(self
            .model
            .spatial
            .frame_fields(&terms, rows, cols)
            .into_iter()
            .enumerate()
            .map(|(frame, field)| FrameCorrection {
                field,
                vessel: self.vessel.map(|vessel| {
                    vessel
                        .part
                        .frame(terms[frame], vessel.anchors[frame], normalization, cols)
                }),
            })
            .collect())
    }
}

/// One frame's displacement: the model's field, plus the vessel part on the frame's lumen.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameCorrection {
    pub field: FrameField,
    pub vessel: Option<FrameVessel>,
}

impl FrameCorrection {
    /// The displacement along `row` at the columns `cols` into `out` (cleared first);
    /// `coefficients` is scratch for a B-spline row.
    pub fn tabulate_row(
        &self,
        row: usize,
        cols: Range<usize>,
        coefficients: &mut Vec<[f64; 2]>,
        out: &mut Vec<[f64; 2]>,
    ) {
        dispatch!(
            Simd::detected(),
            [tabulate, tabulate_avx2, tabulate_avx512](self, row, cols, coefficients, out)
        )
    }
}

/// [`FrameCorrection::tabulate_row`] of `correction`.
#[inline(always)]
fn tabulate(
    correction: &FrameCorrection,
    row: usize,
    cols: Range<usize>,
    coefficients: &mut Vec<[f64; 2]>,
    out: &mut Vec<[f64; 2]>,
) {
    // Filled in a loop of this function (not `extend`'s), so that the copies compile it.
    out.clear();
    out.resize(cols.len(), [0.0; 2]);
    match &correction.field {
        FrameField::Quadratic(polynomial) => {
            let row_field = polynomial.row(row);
            for (value, col) in out.iter_mut().zip(cols.clone()) {
                *value = row_field.at(col);
            }
        }
        FrameField::BSpline(spline) => {
            spline.row_into(row, coefficients);
            spline.row_over(coefficients).fill(cols.clone(), out);
        }
    }
    if let Some(vessel) = &correction.vessel {
        vessel.add_row(row, cols, out);
    }
}

compiled_for!(
    fn tabulate(
        correction: &FrameCorrection,
        row: usize,
        cols: Range<usize>,
        coefficients: &mut Vec<[f64; 2]>,
        out: &mut Vec<[f64; 2]>,
    );
    tabulate_avx2: "avx2",
    tabulate_avx512: "avx512f,avx512bw,avx512vl,avx512dq",
);

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
    use crate::anchored::Anchor;
    use crate::bspline::BSplineModel;
    use crate::field::SpatialModel;
    use crate::model::Coupling;
    use crate::simd::Level;
    use crate::terms::{Integral, Normalization};

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

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_vector_paths_tabulate_as_the_baseline() {
        let (rows, cols) = (40, 48);
        let (model, part) = (model(rows, cols), part(3));
        let terms = model.frame_terms(2.0, &StiffnessProfile::UNIT, 0).unwrap();
        let anchor = Anchor {
            centre_x: 20.3,
            centre_y: 17.6,
            radius: 5.0,
        };
        let correction = FrameCorrection {
            field: model.spatial.frame_fields(&[terms], rows, cols).remove(0),
            vessel: Some(part.frame(terms, anchor, model.spatial.normalization(), cols)),
        };
        let run = |level: Level, row: usize| {
            let (mut coefficients, mut out) = (Vec::new(), Vec::new());
            // SAFETY: only the levels this CPU has are run.
            unsafe {
                match level {
                    Level::Baseline => {
                        tabulate(&correction, row, 3..45, &mut coefficients, &mut out)
                    }
                    Level::Avx2 => {
                        tabulate_avx2(&correction, row, 3..45, &mut coefficients, &mut out)
                    }
                    Level::Avx512 => {
                        tabulate_avx512(&correction, row, 3..45, &mut coefficients, &mut out)
                    }
                }
            }
            out
        };
        for row in [0, 9, 17, 30] {
            let baseline = run(Level::Baseline, row);
            for simd in Simd::available() {
                assert_eq!(run(simd.level(), row), baseline, "{simd:?}, row {row}");
            }
        }
    }

    #[test]
    fn bad_windows_are_rejected() {
        let (model, part) = (model(10, 10), part(2));
        let profile = StiffnessProfile::UNIT;
        let err = anchored_field(&model, &part, 1.0, &profile, None, 0..11, 0..5).unwrap_err();
        assert!(err.to_string().starts_with("window:"), "{err}");
    }
}
