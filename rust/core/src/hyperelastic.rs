//! The element loop of the finite-element mechanics (`usdeform.sim.mechanics`): internal nodal
//! forces and the tangent matrix of a compressible Yeoh material in plane strain, on quadratic (P2)
//! triangles, at the current displacement.
//!
//! Written here rather than left to NumPy because the loop is most of a section's Newton step
//! besides the sparse solve: NumPy's version builds a dozen arrays of (2, 2, 2, 2, elements,
//! points) per call; this one keeps each point's stress and tangent in registers. Everything
//! runs on the calling thread (the library's sections are solved in parallel processes), and the
//! sums run in a fixed order, so results do not depend on a thread count.
//!
//! Conventions (those of the Python caller): an element's 12 vector DOFs are `(i, c)` at `2 i + c`,
//! `i` the 6 scalar shape functions, `c` the component (x, z); the displacement gradient is
//! `G[c][k] = du_c / dx_k`; `F = I + G`; stresses in N/mm^2, forces in N per mm out of plane.

use crate::error::{check_finite, check_len, KernelError, Result};

const SHAPES: usize = 6;
const ELEMENT_DOFS: usize = 2 * SHAPES;
const ELEMENT_ENTRIES: usize = ELEMENT_DOFS * ELEMENT_DOFS;

/// A 2 x 2 matrix `[row][column]`.
type Matrix2 = [[f64; 2]; 2];
/// A fourth-order 2D tensor `[c][k][d][l]`.
type Tensor2 = [[Matrix2; 2]; 2];

/// Per-element material of the compressible Yeoh law (moduli and pressure in N/mm^2).
pub struct Materials {
    pub shear_modulus: Vec<f64>,
    pub yeoh_c2: Vec<f64>,
    pub yeoh_c3: Vec<f64>,
    pub bulk_modulus: Vec<f64>,
    pub lumen_pressure: Vec<f64>,
}

/// A discretised section: connectivity, shape-function gradients, quadrature weights, materials
/// and where each element-matrix entry goes in the free-free block of the tangent matrix.
pub struct HyperelasticSection {
    n_dofs: usize,
    n_points: usize,
    element_dofs: Vec<usize>,
    gradients: Vec<f64>,
    weights: Vec<f64>,
    materials: Materials,
    entry_slots: Vec<i64>,
    n_entries: usize,
}

/// Internal forces (`n_dofs`), the tangent's free-free entries (`n_entries`, empty when not asked
/// for) and the smallest Jacobian determinant met (not positive: an inverted element).
pub struct Assembly {
    pub force: Vec<f64>,
    pub tangent: Vec<f64>,
    pub min_jacobian: f64,
}

/// First Piola-Kirchhoff stress `P[c][k]` and tangent `A[c][k][d][l] = dP_ck / dF_dl` at one point,
/// and `J = det F`; `None` for `J <= 0`.
fn stress_and_tangent(
    gradient: &Matrix2,
    shear: f64,
    c2: f64,
    c3: f64,
    bulk: f64,
    pressure: f64,
) -> Option<(Matrix2, Tensor2, f64)> {
    let f = [
        [1.0 + gradient[0][0], gradient[0][1]],
        [gradient[1][0], 1.0 + gradient[1][1]],
    ];
    let j = f[0][0] * f[1][1] - f[0][1] * f[1][0];
    if j <= 0.0 {
        return None;
    }
    let finv_t = [[f[1][1] / j, -f[1][0] / j], [-f[0][1] / j, f[0][0] / j]];
    let i1 = f[0][0] * f[0][0] + f[0][1] * f[0][1] + f[1][0] * f[1][0] + f[1][1] * f[1][1] + 1.0;
    let j23 = j.powf(-2.0 / 3.0);
    let mut d_i1bar = [[0.0; 2]; 2];
    for c in 0..2 {
        for k in 0..2 {
            d_i1bar[c][k] = j23 * (2.0 * f[c][k] - (2.0 / 3.0) * i1 * finv_t[c][k]);
        }
    }
    let x = j23 * i1 - 3.0;
    let psi1 = 0.5 * shear * (1.0 + 2.0 * c2 * x + 3.0 * c3 * x * x);
    let dpsi1 = 0.5 * shear * (2.0 * c2 + 6.0 * c3 * x);
    let volumetric = 0.5 * bulk * (j * j - 1.0);
    let mut stress = [[0.0; 2]; 2];
    for c in 0..2 {
        for k in 0..2 {
            stress[c][k] =
                psi1 * d_i1bar[c][k] + volumetric * finv_t[c][k] - pressure * j * finv_t[c][k];
        }
    }
    let mut tangent = [[[[0.0; 2]; 2]; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            for c in 0..2 {
                for d in 0..2 {
                    let product = finv_t[a][b] * finv_t[c][d]; // FinvT_ab FinvT_cd
                    let cross = finv_t[a][d] * finv_t[c][b]; // d(FinvT_ab)/dF_cd = -FinvT_ad FinvT_cb
                    let delta = if a == c && b == d { 1.0 } else { 0.0 };
                    let d_d_i1bar = -(2.0 / 3.0) * d_i1bar[a][b] * finv_t[c][d]
                        + j23
                            * (2.0 * delta - (4.0 / 3.0) * finv_t[a][b] * f[c][d]
                                + (2.0 / 3.0) * i1 * cross);
                    tangent[a][b][c][d] = dpsi1 * d_i1bar[a][b] * d_i1bar[c][d]
                        + psi1 * d_d_i1bar
                        + bulk * j * j * product
                        - volumetric * cross
                        - pressure * j * (product - cross);
                }
            }
        }
    }
    Some((stress, tangent, j))
}

impl HyperelasticSection {
    /// Checks and stores a section. `element_dofs` (n_elements x 12, each below `n_dofs`),
    /// `gradients` (n_elements x n_points x 6 x 2: d(shape i)/d(x_k), 1/mm), `weights`
    /// (n_elements x n_points, mm^2), `materials` (n_elements each, finite), `entry_slots`
    /// (n_elements x 144: the index in the tangent's entries of element-matrix entry (a, b), or -1
    /// where it is outside the free-free block; each below `n_entries`).
    pub fn new(
        n_dofs: usize,
        element_dofs: Vec<usize>,
        gradients: Vec<f64>,
        weights: Vec<f64>,
        materials: Materials,
        entry_slots: Vec<i64>,
        n_entries: usize,
    ) -> Result<Self> {
        if element_dofs.is_empty() {
            return Err(KernelError::Empty {
                argument: "element_dofs",
            });
        }
        if element_dofs.len() % ELEMENT_DOFS != 0 {
            return Err(KernelError::Shape {
                argument: "element_dofs",
                expected: format!("a multiple of {ELEMENT_DOFS} values (12 per element)"),
                got: format!("{} values", element_dofs.len()),
            });
        }
        let n_elements = element_dofs.len() / ELEMENT_DOFS;
        if weights.is_empty() || weights.len() % n_elements != 0 {
            return Err(KernelError::Shape {
                argument: "weights",
                expected: format!("n_points values for each of {n_elements} elements"),
                got: format!("{} values", weights.len()),
            });
        }
        let n_points = weights.len() / n_elements;
        check_len("gradients", &gradients, n_elements * n_points * SHAPES * 2)?;
        check_finite("gradients", &gradients)?;
        check_finite("weights", &weights)?;
        for (name, values) in [
            ("shear_modulus", &materials.shear_modulus),
            ("yeoh_c2", &materials.yeoh_c2),
            ("yeoh_c3", &materials.yeoh_c3),
            ("bulk_modulus", &materials.bulk_modulus),
            ("lumen_pressure", &materials.lumen_pressure),
        ] {
            check_len(name, values, n_elements)?;
            check_finite(name, values)?;
        }
        if let Some(index) = element_dofs.iter().position(|&dof| dof >= n_dofs) {
            return Err(KernelError::Value {
                argument: "element_dofs",
                message: format!(
                    "index {index}: DOF {} is outside the {n_dofs} DOFs",
                    element_dofs[index]
                ),
            });
        }
        check_len("entry_slots", &entry_slots, n_elements * ELEMENT_ENTRIES)?;
        if let Some(index) = entry_slots
            .iter()
            .position(|&slot| slot < -1 || slot >= n_entries as i64)
        {
            return Err(KernelError::Value {
                argument: "entry_slots",
                message: format!(
                    "index {index}: slot {} is neither -1 nor below the {n_entries} entries",
                    entry_slots[index]
                ),
            });
        }
        Ok(HyperelasticSection {
            n_dofs,
            n_points,
            element_dofs,
            gradients,
            weights,
            materials,
            entry_slots,
            n_entries,
        })
    }

    /// Number of displacement DOFs.
    pub fn dofs(&self) -> usize {
        self.n_dofs
    }

    /// Internal nodal forces at displacement `u` (mm) with `pressure_fraction` of the lumen
    /// pressure applied, and with `with_tangent` the tangent's free-free entries (element by
    /// element, in entry order). Stops at the first inverted element and reports its Jacobian as
    /// `min_jacobian` (the outputs are then incomplete).
    pub fn assemble(
        &self,
        u: &[f64],
        pressure_fraction: f64,
        with_tangent: bool,
    ) -> Result<Assembly> {
        check_len("u", u, self.n_dofs)?;
        check_finite("u", u)?;
        if !pressure_fraction.is_finite() {
            return Err(KernelError::Value {
                argument: "pressure_fraction",
                message: format!("expected a finite number, got {pressure_fraction}"),
            });
        }
        let mut force = vec![0.0; self.n_dofs];
        let mut tangent = if with_tangent {
            vec![0.0; self.n_entries]
        } else {
            Vec::new()
        };
        let mut min_jacobian = f64::INFINITY;
        let n_elements = self.element_dofs.len() / ELEMENT_DOFS;
        let m = &self.materials;
        for element in 0..n_elements {
            let dofs = &self.element_dofs[element * ELEMENT_DOFS..(element + 1) * ELEMENT_DOFS];
            let mut element_u = [0.0; ELEMENT_DOFS];
            for (value, &dof) in element_u.iter_mut().zip(dofs) {
                *value = u[dof];
            }
            let mut element_force = [0.0; ELEMENT_DOFS];
            let mut element_tangent = [[0.0; ELEMENT_DOFS]; ELEMENT_DOFS];
            let pressure = pressure_fraction * m.lumen_pressure[element];
            for point in 0..self.n_points {
                let at = element * self.n_points + point;
                let g = &self.gradients[at * SHAPES * 2..(at + 1) * SHAPES * 2];
                let mut gradient = [[0.0; 2]; 2];
                for i in 0..SHAPES {
                    for c in 0..2 {
                        for k in 0..2 {
                            gradient[c][k] += element_u[2 * i + c] * g[2 * i + k];
                        }
                    }
                }
                let Some((stress, material_tangent, j)) = stress_and_tangent(
                    &gradient,
                    m.shear_modulus[element],
                    m.yeoh_c2[element],
                    m.yeoh_c3[element],
                    m.bulk_modulus[element],
                    pressure,
                ) else {
                    let j = (1.0 + gradient[0][0]) * (1.0 + gradient[1][1])
                        - gradient[0][1] * gradient[1][0];
                    return Ok(Assembly {
                        force,
                        tangent,
                        min_jacobian: j,
                    });
                };
                min_jacobian = min_jacobian.min(j);
                let w = self.weights[at];
                for i in 0..SHAPES {
                    for c in 0..2 {
                        element_force[2 * i + c] +=
                            w * (g[2 * i] * stress[c][0] + g[2 * i + 1] * stress[c][1]);
                    }
                }
                if !with_tangent {
                    continue;
                }
                // K[(i, c), (j, d)] += w sum_{k, l} g_ik A[c][k][d][l] g_jl, through
                // T[i][c][d][l] = sum_k g_ik A[c][k][d][l]
                let mut partial = [[[[0.0; 2]; 2]; 2]; SHAPES];
                for (i, row) in partial.iter_mut().enumerate() {
                    for c in 0..2 {
                        for d in 0..2 {
                            for l in 0..2 {
                                row[c][d][l] = g[2 * i] * material_tangent[c][0][d][l]
                                    + g[2 * i + 1] * material_tangent[c][1][d][l];
                            }
                        }
                    }
                }
                for i in 0..SHAPES {
                    for c in 0..2 {
                        let row = &mut element_tangent[2 * i + c];
                        for jj in 0..SHAPES {
                            for d in 0..2 {
                                row[2 * jj + d] += w
                                    * (partial[i][c][d][0] * g[2 * jj]
                                        + partial[i][c][d][1] * g[2 * jj + 1]);
                            }
                        }
                    }
                }
            }
            for (value, &dof) in element_force.iter().zip(dofs) {
                force[dof] += value;
            }
            if with_tangent {
                let slots =
                    &self.entry_slots[element * ELEMENT_ENTRIES..(element + 1) * ELEMENT_ENTRIES];
                for (entry, &slot) in slots.iter().enumerate() {
                    if slot >= 0 {
                        tangent[slot as usize] +=
                            element_tangent[entry / ELEMENT_DOFS][entry % ELEMENT_DOFS];
                    }
                }
            }
        }
        Ok(Assembly {
            force,
            tangent,
            min_jacobian,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One straight P2 triangle (0,0), (1,0), (0,1) with its 3 vertex and 3 edge nodes, gradients
    /// at one point (the centroid), weight 1/2, and every entry free in its own slot.
    fn triangle(shear: f64) -> HyperelasticSection {
        let (x, y) = (1.0 / 3.0, 1.0 / 3.0);
        let l = [1.0 - x - y, x, y];
        let dl = [[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]];
        let mut gradients = Vec::new();
        for (la, dla) in l.iter().zip(dl) {
            gradients.extend(dla.map(|d| (4.0 * la - 1.0) * d));
        }
        for (a, b) in [(0, 1), (1, 2), (0, 2)] {
            gradients.extend([0, 1].map(|k| 4.0 * (l[a] * dl[b][k] + l[b] * dl[a][k])));
        }
        let materials = Materials {
            shear_modulus: vec![shear],
            yeoh_c2: vec![0.1],
            yeoh_c3: vec![0.01],
            bulk_modulus: vec![50.0 * shear],
            lumen_pressure: vec![0.0],
        };
        HyperelasticSection::new(
            12,
            (0..12).collect(),
            gradients,
            vec![0.5],
            materials,
            (0..144).collect(),
            144,
        )
        .unwrap()
    }

    #[test]
    fn undeformed_state_has_no_force_and_a_symmetric_tangent() {
        let section = triangle(1.0);
        let assembly = section.assemble(&[0.0; 12], 1.0, true).unwrap();
        assert!(assembly.force.iter().all(|value| value.abs() < 1e-12));
        for a in 0..12 {
            for b in 0..12 {
                let (ab, ba) = (assembly.tangent[a * 12 + b], assembly.tangent[b * 12 + a]);
                assert!((ab - ba).abs() < 1e-9 * (1.0 + ab.abs()));
            }
        }
        assert!((assembly.min_jacobian - 1.0).abs() < 1e-15);
    }

    #[test]
    fn tangent_is_the_derivative_of_the_force() {
        let section = triangle(2.0);
        let u: Vec<f64> = (0..12).map(|i| 0.01 * ((i * 7 % 5) as f64 - 2.0)).collect();
        let base = section.assemble(&u, 1.0, true).unwrap();
        let step = 1e-6;
        for b in 0..12 {
            let mut moved = u.clone();
            moved[b] += step;
            let after = section.assemble(&moved, 1.0, false).unwrap();
            for a in 0..12 {
                let numeric = (after.force[a] - base.force[a]) / step;
                let analytic = base.tangent[a * 12 + b];
                assert!((numeric - analytic).abs() < 1e-4 * (1.0 + analytic.abs()));
            }
        }
    }

    #[test]
    fn an_inverted_element_is_reported() {
        let section = triangle(1.0);
        // every node mirrored in x (u_x = -2 x): F_xx = -1, J = -1
        let node_x = [0.0, 1.0, 0.0, 0.5, 0.5, 0.0];
        let mut u = [0.0; 12];
        for (i, x) in node_x.iter().enumerate() {
            u[2 * i] = -2.0 * x;
        }
        let assembly = section.assemble(&u, 1.0, true).unwrap();
        assert!((assembly.min_jacobian + 1.0).abs() < 1e-12);
    }

    #[test]
    fn bad_inputs_name_the_argument() {
        let section = triangle(1.0);
        let error = section.assemble(&[0.0; 11], 1.0, true).err().unwrap();
        assert!(error.to_string().starts_with("u:"));
        let mut u = [0.0; 12];
        u[4] = f64::NAN;
        assert!(section
            .assemble(&u, 1.0, true)
            .err()
            .unwrap()
            .to_string()
            .starts_with("u:"));
    }
}
