//! Hole filling of a compounded volume, after PLUS's vtkPlusFillHolesInVolume (FillHoles="ON").
//!
//! A voxel is a hole when its coverage weight is below `min_known_weight` (no pixel, or too little
//! of one, landed in it). Each hole is given to the configured elements in order; the first element
//! that succeeds sets its value, and a hole no element fills stays 0. Elements read only the known
//! voxels of the input, never values filled in the same pass, so every voxel is computed
//! independently: planes are filled in parallel and the output is bit-identical for any thread count.
//!
//! The elements (PLUS's HoleFillingElement types). The four cube rules are a reconstruction from
//! PLUS's documented behaviour (assumptions are marked as such); the stick rule follows PLUS's
//! source and is checked against PLUS's reference volumes (STICK, the type its configurations use):
//! - `Gaussian`: the Gaussian-weighted mean (standard deviation `stdev`, voxels) of the known voxels
//!   in the `size`^3 cube around the hole;
//! - `GaussianAccumulation`: the same with each voxel's weight multiplied by its coverage weight;
//! - `DistanceWeightInverse`: the mean weighted by 1 / (distance in voxels);
//! - `NearestNeighbor`: the mean of the known voxels nearest (Euclidean) to the hole in the cube;
//! - these four succeed when at least `min_known_ratio` of the cube's `size`^3 voxels are known
//!   (assumption: the cube counts its voxels outside the volume as unknown);
//! - `Stick`: along each of the 13 lines through the hole (axes, face and body diagonals), the
//!   nearest known voxel is searched forward (along the direction) and backward; a line whose two
//!   ends lie `f` and `b` steps from the hole with `f + b <= length_limit - 1` gives a stick. As in
//!   PLUS (vtkIGSIOFillHolesInVolume), the stick's value is `(f * backward + (b + 1) * forward) /
//!   (f + b + 1)` cast to the voxel type, and its score is `1 / ((f + b + 1) * |direction|)`. The
//!   sticks of the highest score, all of a tie together, are taken until `sticks_to_use` are used;
//!   the hole gets their score-weighted mean.

use rayon::prelude::*;

use crate::error::{reserve, KernelError, Result};
use crate::warp::Pixel;

/// One step of PLUS's hole filling.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum HoleFillingElement {
    Gaussian {
        size: usize,
        stdev: f64,
        min_known_ratio: f64,
    },
    GaussianAccumulation {
        size: usize,
        stdev: f64,
        min_known_ratio: f64,
    },
    DistanceWeightInverse {
        size: usize,
        min_known_ratio: f64,
    },
    NearestNeighbor {
        size: usize,
        min_known_ratio: f64,
    },
    Stick {
        length_limit: usize,
        sticks_to_use: usize,
    },
}

/// The 13 stick directions (dx, dy, dz), one per pair of opposite neighbours, in PLUS's order and
/// sign (the sign decides which end is forward): axes, face diagonals, body diagonals.
pub const STICK_DIRECTIONS: [[i64; 3]; 13] = [
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [1, 1, 0],
    [1, 0, 1],
    [0, 1, 1],
    [1, -1, 0],
    [1, 0, -1],
    [0, 1, -1],
    [1, 1, 1],
    [-1, 1, 1],
    [1, -1, 1],
    [-1, -1, 1],
];

/// Largest cube `size` accepted: the cube of a hole is visited for every hole, so a larger one
/// would make the filling quadratic in the volume in practice.
pub const MAX_SIZE: usize = 31;

/// A voxel type the filling reads and writes: uint8 (as PLUS writes) or float32.
pub trait VoxelValue: Pixel + Default {
    /// A filled value in this type. uint8 truncates toward zero and saturates, as PLUS's cast of its
    /// float result to unsigned char; float32 rounds to nearest.
    fn from_fill(value: f64) -> Self;
}

impl VoxelValue for u8 {
    #[inline]
    fn from_fill(value: f64) -> Self {
        value as u8
    }
}

impl VoxelValue for f32 {
    #[inline]
    fn from_fill(value: f64) -> Self {
        value as f32
    }
}

/// The cube neighbourhood of an element, prepared once: offsets (dz, dy, dx) in z, y, x order
/// (centre left out: it is the hole) with their weights.
#[derive(Debug, Clone)]
struct Cube {
    offsets: Vec<([i64; 3], f64)>,
    /// Known voxels needed, as a ratio of the cube's size^3 voxels.
    min_known_ratio: f64,
    volume: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CubeRule {
    /// Weighted mean with the cube's weights.
    Weighted,
    /// Weighted mean with the cube's weights times the coverage weight.
    WeightedByCoverage,
    /// Mean of the known voxels with the smallest weight (the squared distance).
    Nearest,
}

#[derive(Debug, Clone)]
enum Prepared {
    Cube(Cube, CubeRule),
    Stick {
        length_limit: usize,
        sticks_to_use: usize,
    },
}

fn value_error(argument: &'static str, message: String) -> KernelError {
    KernelError::Value { argument, message }
}

fn check_cube(index: usize, size: usize, min_known_ratio: f64) -> Result<()> {
    if size % 2 == 0 || size > MAX_SIZE {
        return Err(value_error(
            "elements",
            format!("element {index}: size must be odd and in 1..={MAX_SIZE} voxels, got {size}"),
        ));
    }
    if !(0.0..=1.0).contains(&min_known_ratio) {
        return Err(value_error(
            "elements",
            format!("element {index}: min_known_ratio must be in [0, 1], got {min_known_ratio}"),
        ));
    }
    Ok(())
}

fn check_stdev(index: usize, stdev: f64) -> Result<()> {
    if stdev.is_finite() && stdev > 0.0 {
        Ok(())
    } else {
        Err(value_error(
            "elements",
            format!("element {index}: stdev must be positive and finite, got {stdev}"),
        ))
    }
}

/// The cube of `size` with weights `weight(squared distance)`, centre left out.
fn cube(size: usize, min_known_ratio: f64, weight: impl Fn(f64) -> f64) -> Result<Cube> {
    let half = (size / 2) as i64;
    let mut offsets = reserve("elements", size * size * size)?;
    for dz in -half..=half {
        for dy in -half..=half {
            for dx in -half..=half {
                if (dz, dy, dx) != (0, 0, 0) {
                    offsets.push(([dz, dy, dx], weight((dz * dz + dy * dy + dx * dx) as f64)));
                }
            }
        }
    }
    Ok(Cube {
        offsets,
        min_known_ratio,
        volume: (size * size * size) as f64,
    })
}

fn prepare(index: usize, element: &HoleFillingElement) -> Result<Prepared> {
    Ok(match *element {
        HoleFillingElement::Gaussian {
            size,
            stdev,
            min_known_ratio,
        }
        | HoleFillingElement::GaussianAccumulation {
            size,
            stdev,
            min_known_ratio,
        } => {
            check_cube(index, size, min_known_ratio)?;
            check_stdev(index, stdev)?;
            let rule = if matches!(element, HoleFillingElement::Gaussian { .. }) {
                CubeRule::Weighted
            } else {
                CubeRule::WeightedByCoverage
            };
            let kernel = cube(size, min_known_ratio, |d2| {
                (-d2 / (2.0 * stdev * stdev)).exp()
            })?;
            Prepared::Cube(kernel, rule)
        }
        HoleFillingElement::DistanceWeightInverse {
            size,
            min_known_ratio,
        } => {
            check_cube(index, size, min_known_ratio)?;
            Prepared::Cube(
                cube(size, min_known_ratio, |d2| 1.0 / d2.sqrt())?,
                CubeRule::Weighted,
            )
        }
        HoleFillingElement::NearestNeighbor {
            size,
            min_known_ratio,
        } => {
            check_cube(index, size, min_known_ratio)?;
            Prepared::Cube(cube(size, min_known_ratio, |d2| d2)?, CubeRule::Nearest)
        }
        HoleFillingElement::Stick {
            length_limit,
            sticks_to_use,
        } => {
            if length_limit == 0 {
                return Err(value_error(
                    "elements",
                    format!("element {index}: stick length limit must be at least 1 voxel"),
                ));
            }
            if !(1..=STICK_DIRECTIONS.len()).contains(&sticks_to_use) {
                return Err(value_error(
                    "elements",
                    format!(
                        "element {index}: number of sticks to use must be in 1..=13, got {sticks_to_use}"
                    ),
                ));
            }
            Prepared::Stick {
                length_limit,
                sticks_to_use,
            }
        }
    })
}

/// The input volume, read-only, with its known-voxel test.
struct Input<'a, T> {
    image: &'a [T],
    weight: &'a [f32],
    shape: [i64; 3],
    min_known_weight: f32,
}

impl<T: VoxelValue> Input<'_, T> {
    /// Flat index of voxel (z, y, x) if inside the volume.
    #[inline]
    fn index(&self, z: i64, y: i64, x: i64) -> Option<usize> {
        let [nz, ny, nx] = self.shape;
        if (0..nz).contains(&z) && (0..ny).contains(&y) && (0..nx).contains(&x) {
            Some(((z * ny + y) * nx + x) as usize)
        } else {
            None
        }
    }

    #[inline]
    fn is_known(&self, index: usize) -> bool {
        let weight = self.weight[index];
        weight > 0.0 && weight >= self.min_known_weight
    }

    /// The known voxel at (z, y, x), if any: its flat index.
    #[inline]
    fn known(&self, z: i64, y: i64, x: i64) -> Option<usize> {
        self.index(z, y, x).filter(|&i| self.is_known(i))
    }

    fn fill_from_cube(&self, cube: &Cube, rule: CubeRule, at: [i64; 3]) -> Option<f64> {
        let (mut value_sum, mut weight_sum, mut known) = (0.0f64, 0.0f64, 0usize);
        let mut nearest = f64::INFINITY;
        for &([dz, dy, dx], kernel) in &cube.offsets {
            let Some(i) = self.known(at[0] + dz, at[1] + dy, at[2] + dx) else {
                continue;
            };
            known += 1;
            let value = self.image[i].to_f64();
            match rule {
                CubeRule::Weighted => {
                    value_sum += kernel * value;
                    weight_sum += kernel;
                }
                CubeRule::WeightedByCoverage => {
                    let weight = kernel * self.weight[i] as f64;
                    value_sum += weight * value;
                    weight_sum += weight;
                }
                CubeRule::Nearest => {
                    if kernel < nearest {
                        (nearest, value_sum, weight_sum) = (kernel, value, 1.0);
                    } else if kernel == nearest {
                        value_sum += value;
                        weight_sum += 1.0;
                    }
                }
            }
        }
        let enough = known as f64 >= cube.min_known_ratio * cube.volume;
        (known > 0 && enough && weight_sum > 0.0).then(|| value_sum / weight_sum)
    }

    /// Steps (1..=limit) to the nearest known voxel from `at` along `direction`, and its value.
    fn stick_end(&self, at: [i64; 3], direction: [i64; 3], limit: usize) -> Option<(usize, f64)> {
        let [dx, dy, dz] = direction;
        for step in 1..=limit {
            let reach = step as i64;
            let index = self.index(at[0] + reach * dz, at[1] + reach * dy, at[2] + reach * dx)?;
            if self.is_known(index) {
                return Some((step, self.image[index].to_f64()));
            }
        }
        None
    }

    fn fill_from_sticks(
        &self,
        length_limit: usize,
        sticks_to_use: usize,
        at: [i64; 3],
    ) -> Option<f64> {
        // (score, value) per direction; a score of 0 is no stick.
        let mut sticks = [(0.0f64, 0.0f64); 13];
        for (stick, &direction) in sticks.iter_mut().zip(STICK_DIRECTIONS.iter()) {
            let backward = [-direction[0], -direction[1], -direction[2]];
            let Some((forward_steps, forward_value)) =
                self.stick_end(at, direction, length_limit - 1)
            else {
                continue;
            };
            let Some((backward_steps, backward_value)) =
                self.stick_end(at, backward, length_limit - 1 - forward_steps)
            else {
                continue;
            };
            let span = (forward_steps + backward_steps + 1) as f64;
            let forward_weight = (backward_steps + 1) as f64 / span;
            let value = (1.0 - forward_weight) * backward_value + forward_weight * forward_value;
            let unit = ((direction[0] * direction[0]
                + direction[1] * direction[1]
                + direction[2] * direction[2]) as f64)
                .sqrt();
            *stick = (1.0 / (span * unit), T::from_fill(value).to_f64());
        }
        let (mut value_sum, mut score_sum, mut used) = (0.0f64, 0.0f64, 0usize);
        while used < sticks_to_use {
            let best = sticks.iter().fold(0.0f64, |best, stick| best.max(stick.0));
            if best == 0.0 {
                break;
            }
            for stick in sticks.iter_mut().filter(|stick| stick.0 == best) {
                value_sum += stick.1 * stick.0;
                score_sum += stick.0;
                used += 1;
                stick.0 = 0.0;
            }
        }
        (score_sum > 0.0).then(|| value_sum / score_sum)
    }

    fn fill(&self, elements: &[Prepared], at: [i64; 3]) -> Option<f64> {
        elements.iter().find_map(|element| match element {
            Prepared::Cube(cube, rule) => self.fill_from_cube(cube, *rule, at),
            Prepared::Stick {
                length_limit,
                sticks_to_use,
            } => self.fill_from_sticks(*length_limit, *sticks_to_use, at),
        })
    }
}

/// The volume `image` (z, y, x, C order, `shape`) with its holes filled by `elements` in order.
///
/// `weight` is the coverage weight per voxel; voxels with `weight > 0` and `weight >=
/// min_known_weight` are known and copied unchanged, the others are holes (0 where no element fills
/// them). Fails before allocating if the output needs more than `max_bytes`.
pub fn fill_holes<T: VoxelValue>(
    image: &[T],
    weight: &[f32],
    shape: [usize; 3],
    elements: &[HoleFillingElement],
    min_known_weight: f32,
    max_bytes: u128,
) -> Result<Vec<T>> {
    let voxels = shape
        .iter()
        .try_fold(1usize, |n, &s| n.checked_mul(s))
        .filter(|&n| i64::try_from(n).is_ok())
        .ok_or(KernelError::Allocation {
            argument: "image",
            bytes: u128::MAX,
        })?;
    if voxels == 0 {
        return Err(KernelError::Shape {
            argument: "image",
            expected: "three positive voxel counts (z, y, x)".into(),
            got: format!("{shape:?}"),
        });
    }
    for (argument, len) in [("image", image.len()), ("weight", weight.len())] {
        if len != voxels {
            return Err(KernelError::Shape {
                argument,
                expected: format!("{voxels} voxels ({shape:?})"),
                got: format!("{len} voxels"),
            });
        }
    }
    if !min_known_weight.is_finite() || min_known_weight < 0.0 {
        return Err(value_error(
            "min_known_weight",
            format!("must be finite and non-negative, got {min_known_weight}"),
        ));
    }
    if let Some(index) = weight.iter().position(|w| !w.is_finite()) {
        return Err(KernelError::NonFinite {
            argument: "weight",
            index,
        });
    }
    let needed_bytes = voxels as u128 * std::mem::size_of::<T>() as u128;
    if needed_bytes > max_bytes {
        return Err(KernelError::MemoryLimit {
            needed_bytes,
            limit_bytes: max_bytes,
        });
    }
    let prepared = elements
        .iter()
        .enumerate()
        .map(|(index, element)| prepare(index, element))
        .collect::<Result<Vec<_>>>()?;
    let input = Input {
        image,
        weight,
        shape: shape.map(|n| n as i64),
        min_known_weight,
    };
    let mut out = reserve::<T>("image", voxels)?;
    out.resize(voxels, T::default());
    let plane = shape[1] * shape[2];
    out.par_chunks_mut(plane)
        .enumerate()
        .for_each(|(z, out_plane)| {
            for (offset, voxel) in out_plane.iter_mut().enumerate() {
                let index = z * plane + offset;
                *voxel = if input.is_known(index) {
                    image[index]
                } else {
                    let at = [
                        z as i64,
                        (offset / shape[2]) as i64,
                        (offset % shape[2]) as i64,
                    ];
                    input
                        .fill(&prepared, at)
                        .map_or_else(T::default, T::from_fill)
                };
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    const STICK: HoleFillingElement = HoleFillingElement::Stick {
        length_limit: 4,
        sticks_to_use: 1,
    };

    fn known_everywhere_but(shape: [usize; 3], holes: &[usize]) -> Vec<f32> {
        let mut weight = vec![1.0f32; shape.iter().product()];
        for &h in holes {
            weight[h] = 0.0;
        }
        weight
    }

    #[test]
    fn stick_weights_its_ends_as_plus() {
        // Planes z = 0 and z = 3 known (10 and 40), z = 1, 2 holes: the z stick is the only one.
        // z = 1: f = 2, b = 1, weights 2/4 and 2/4; z = 2: f = 1, b = 2, backward 1/4, forward 3/4.
        let shape = [4, 1, 1];
        let image = [10.0f32, 0.0, 0.0, 40.0];
        let weight = [1.0f32, 0.0, 0.0, 1.0];
        let out = fill_holes(&image, &weight, shape, &[STICK], 0.0, u128::MAX).unwrap();
        assert_eq!(out, vec![10.0, 25.0, 32.5, 40.0]);
        let as_u8: Vec<u8> = vec![10, 0, 0, 41];
        let out = fill_holes(&as_u8, &weight, shape, &[STICK], 0.0, u128::MAX).unwrap();
        assert_eq!(out, vec![10, 25, 33, 41]); // 25.5 and 33.25 truncate as PLUS's cast
    }

    #[test]
    fn highest_score_wins_and_limit_applies() {
        // A hole with known voxels 1 step away along x and 2 along z: the x stick scores higher.
        let shape = [5, 1, 3];
        let mut image = vec![0.0f32; 15];
        let mut weight = vec![0.0f32; 15];
        for (z, x, value) in [(2, 0, 6.0), (2, 2, 8.0), (0, 1, 100.0), (4, 1, 200.0)] {
            image[z * 3 + x] = value;
            weight[z * 3 + x] = 1.0;
        }
        let x_stick = (6.0 + 2.0 * 8.0) / 3.0; // f = b = 1: forward weight 2/3
        let out = fill_holes(&image, &weight, shape, &[STICK], 0.0, u128::MAX).unwrap();
        assert!((f64::from(out[2 * 3 + 1]) - x_stick).abs() < 1e-5);
        let short = HoleFillingElement::Stick {
            length_limit: 3,
            sticks_to_use: 2,
        };
        let out = fill_holes(&image, &weight, shape, &[short], 0.0, u128::MAX).unwrap();
        assert!((f64::from(out[2 * 3 + 1]) - x_stick).abs() < 1e-5); // z ends 4 steps apart
        assert_eq!(out[0], 0.0); // (0, 0, 0): no stick reaches known voxels on both sides
        let long = HoleFillingElement::Stick {
            length_limit: 5,
            sticks_to_use: 2,
        };
        let out = fill_holes(&image, &weight, shape, &[long], 0.0, u128::MAX).unwrap();
        let z_stick = 0.4 * 100.0 + 0.6 * 200.0; // f = b = 2: forward weight 3/5
        let expected = (x_stick / 3.0 + z_stick / 5.0) / (1.0 / 3.0 + 1.0 / 5.0);
        assert!((f64::from(out[2 * 3 + 1]) - expected).abs() < 1e-4);
    }

    #[test]
    fn sticks_at_a_tie_are_all_used() {
        // The centre of a 3 x 3 plane with its four edge neighbours known: the x and y sticks tie.
        let shape = [1, 3, 3];
        let mut image = vec![0.0f32; 9];
        let mut weight = vec![0.0f32; 9];
        for (index, value) in [(3, 10.0), (5, 20.0), (1, 30.0), (7, 50.0)] {
            image[index] = value;
            weight[index] = 1.0;
        }
        let one = HoleFillingElement::Stick {
            length_limit: 9,
            sticks_to_use: 1,
        };
        let out = fill_holes(&image, &weight, shape, &[one], 0.0, u128::MAX).unwrap();
        let x_stick = (10.0 + 2.0 * 20.0) / 3.0;
        let y_stick = (30.0 + 2.0 * 50.0) / 3.0;
        assert!((f64::from(out[4]) - (x_stick + y_stick) / 2.0).abs() < 1e-5);
    }

    #[test]
    fn cube_elements_follow_their_ratio_and_order() {
        let shape = [3, 3, 3];
        let image: Vec<f32> = (0..27).map(|v| v as f32).collect();
        let centre = 13;
        let weight = known_everywhere_but(shape, &[centre]);
        let gaussian = HoleFillingElement::Gaussian {
            size: 3,
            stdev: 1.0,
            min_known_ratio: 0.9,
        };
        // Symmetric cube of values v around 13: every symmetric weighting gives 13.
        for element in [
            gaussian,
            HoleFillingElement::DistanceWeightInverse {
                size: 3,
                min_known_ratio: 0.5,
            },
            HoleFillingElement::NearestNeighbor {
                size: 3,
                min_known_ratio: 0.5,
            },
            HoleFillingElement::GaussianAccumulation {
                size: 3,
                stdev: 0.5,
                min_known_ratio: 0.5,
            },
        ] {
            let out = fill_holes(&image, &weight, shape, &[element], 0.0, u128::MAX).unwrap();
            assert!(
                (out[centre] - 13.0).abs() < 1e-5,
                "{element:?}: {}",
                out[centre]
            );
        }
        // 26 of 27 known: ratio 0.963 passes 0.95, fails 0.97; the failing element passes to the next.
        let strict = HoleFillingElement::Gaussian {
            size: 3,
            stdev: 1.0,
            min_known_ratio: 0.97,
        };
        let out = fill_holes(&image, &weight, shape, &[strict], 0.0, u128::MAX).unwrap();
        assert_eq!(out[centre], 0.0);
        let out = fill_holes(&image, &weight, shape, &[strict, STICK], 0.0, u128::MAX).unwrap();
        // The three axis sticks tie: (12 + 2 * 14) / 3, (10 + 2 * 16) / 3 and (4 + 2 * 22) / 3.
        assert!((f64::from(out[centre]) - 130.0 / 9.0).abs() < 1e-5);
    }

    #[test]
    fn low_weight_voxels_are_holes() {
        let shape = [3, 1, 1];
        let image = [10.0f32, 99.0, 30.0];
        let weight = [1.0f32, 0.001, 1.0];
        let out = fill_holes(&image, &weight, shape, &[STICK], 1.0 / 256.0, u128::MAX).unwrap();
        assert_eq!(out, vec![10.0, 70.0 / 3.0, 30.0]); // forward weight 2/3
        let out = fill_holes(&image, &weight, shape, &[STICK], 0.0, u128::MAX).unwrap();
        assert_eq!(out, vec![10.0, 99.0, 30.0]);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let shape = [2, 2, 2];
        let image = vec![0.0f32; 8];
        let weight = vec![0.0f32; 8];
        let even = HoleFillingElement::NearestNeighbor {
            size: 4,
            min_known_ratio: 0.5,
        };
        let error = fill_holes(&image, &weight, shape, &[STICK, even], 0.0, u128::MAX).unwrap_err();
        assert!(
            error.to_string().contains("element 1: size must be odd"),
            "{error}"
        );
        let error = fill_holes(&image, &weight[..7], shape, &[STICK], 0.0, u128::MAX).unwrap_err();
        assert!(
            error.to_string().starts_with("weight: expected 8 voxels"),
            "{error}"
        );
        let error = fill_holes(&image, &weight, shape, &[STICK], 0.0, 16).unwrap_err();
        assert!(matches!(
            error,
            KernelError::MemoryLimit {
                needed_bytes: 32,
                ..
            }
        ));
        let error = fill_holes(
            &image,
            &weight,
            [usize::MAX, 2, 2],
            &[STICK],
            0.0,
            u128::MAX,
        )
        .unwrap_err();
        assert!(matches!(error, KernelError::Allocation { .. }));
        let mut nan = weight.clone();
        nan[3] = f32::NAN;
        let error = fill_holes(&image, &nan, shape, &[STICK], 0.0, u128::MAX).unwrap_err();
        assert_eq!(
            error,
            KernelError::NonFinite {
                argument: "weight",
                index: 3
            }
        );
    }

    #[test]
    fn same_result_for_any_thread_count() {
        let shape = [17, 13, 11];
        let n: usize = shape.iter().product();
        // A deterministic pseudo-random volume with about 40 % holes.
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as f32 / (1u64 << 31) as f32
        };
        let image: Vec<f32> = (0..n).map(|_| next() * 255.0).collect();
        let weight: Vec<f32> = (0..n)
            .map(|_| if next() < 0.4 { 0.0 } else { next() * 3.0 })
            .collect();
        let elements = [
            HoleFillingElement::Gaussian {
                size: 3,
                stdev: 0.7,
                min_known_ratio: 0.8,
            },
            HoleFillingElement::Stick {
                length_limit: 3,
                sticks_to_use: 3,
            },
            HoleFillingElement::NearestNeighbor {
                size: 5,
                min_known_ratio: 0.1,
            },
        ];
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| fill_holes(&image, &weight, shape, &elements, 0.0, u128::MAX).unwrap())
        };
        let one = run(1);
        for threads in [2, 3, 8] {
            let other = run(threads);
            assert!(one
                .iter()
                .zip(&other)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }
}
