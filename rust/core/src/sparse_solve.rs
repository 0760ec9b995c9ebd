//! Sparse symmetric linear solves: the Newton step `K du = -r` of the finite-element mechanics
//! (`usdeform.sim.mechanics`).
//!
//! Written here rather than left to SciPy's `spsolve` (SuperLU, a general LU with a column
//! ordering recomputed at every call) because the tangent matrix of a section is symmetric and
//! keeps one sparsity pattern for the whole solve: a supernodal LDL^T (faer) whose fill-reducing
//! ordering and symbolic factorisation are computed once per pattern is about ten times faster
//! per Newton step, and the Newton steps were most of a section's solve time. LDL^T without
//! pivoting (not Cholesky) so that an indefinite tangent (a section past a limit point) is still
//! solved; only an exactly zero pivot fails. Everything runs on the calling thread, so results do
//! not depend on a thread count.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, LdltRef, SymbolicCholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par, Side};

use crate::error::{check_finite, KernelError, Result};

/// The sparsity pattern of a symmetric `n x n` matrix in compressed sparse column form (both
/// triangles stored; only the lower one is read) and its symbolic LDL^T factorisation.
pub struct SymmetricPattern {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    symbolic: SymbolicCholesky<usize>,
}

fn pattern_error(message: String) -> KernelError {
    KernelError::Value {
        argument: "indices",
        message,
    }
}

fn check_values(argument: &'static str, values: &[f64], expected: usize) -> Result<()> {
    if values.len() != expected {
        return Err(KernelError::Shape {
            argument,
            expected: format!("{expected} values"),
            got: format!("{}", values.len()),
        });
    }
    check_finite(argument, values)
}

impl SymmetricPattern {
    /// Checks the pattern (`col_ptr`: n + 1 offsets from 0, non-decreasing, ending at the number
    /// of entries; `row_idx`: rows below n, strictly increasing within each column, with every
    /// diagonal entry present) and factorises it symbolically (approximate minimum degree order).
    pub fn new(col_ptr: Vec<usize>, row_idx: Vec<usize>) -> Result<Arc<Self>> {
        if col_ptr.is_empty() {
            return Err(KernelError::Empty { argument: "indptr" });
        }
        let n = col_ptr.len() - 1;
        if n == 0 {
            return Err(KernelError::Empty { argument: "indptr" });
        }
        if col_ptr[0] != 0 || col_ptr[n] != row_idx.len() {
            return Err(KernelError::Value {
                argument: "indptr",
                message: format!(
                    "expected offsets from 0 to the number of entries {}, got {} to {}",
                    row_idx.len(),
                    col_ptr[0],
                    col_ptr[n]
                ),
            });
        }
        for column in 0..n {
            let (start, end) = (col_ptr[column], col_ptr[column + 1]);
            if start > end || end > row_idx.len() {
                return Err(KernelError::Value {
                    argument: "indptr",
                    message: format!(
                        "offsets must not decrease nor pass the number of entries (column {column})"
                    ),
                });
            }
            let rows = &row_idx[start..end];
            if let Some(&row) = rows.iter().find(|&&row| row >= n) {
                return Err(pattern_error(format!(
                    "column {column}: row {row} is outside the {n} x {n} matrix"
                )));
            }
            if rows.windows(2).any(|pair| pair[0] >= pair[1]) {
                return Err(pattern_error(format!(
                    "column {column}: rows must increase strictly (sorted, no duplicates)"
                )));
            }
            if rows.binary_search(&column).is_err() {
                return Err(pattern_error(format!(
                    "column {column}: the diagonal entry is missing"
                )));
            }
        }
        let symbolic = factorize_symbolic_cholesky(
            SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx),
            Side::Lower,
            Default::default(),
            Default::default(),
        )
        .map_err(|error| match error {
            faer::sparse::FaerError::OutOfMemory => KernelError::Allocation {
                argument: "symbolic factorisation",
                bytes: u128::MAX,
            },
            other => pattern_error(format!("the factorisation cannot be indexed: {other:?}")),
        })?;
        Ok(Arc::new(SymmetricPattern {
            col_ptr,
            row_idx,
            symbolic,
        }))
    }

    /// Number of rows (and columns).
    pub fn size(&self) -> usize {
        self.col_ptr.len() - 1
    }

    /// Number of stored entries, i.e. the length `solve` expects of `values`.
    pub fn entries(&self) -> usize {
        self.row_idx.len()
    }

    /// Solves `A x = rhs` for the matrix `A` of this pattern with entries `values` (in pattern
    /// order): [`SymmetricPattern::factorize`] then [`SymmetricFactor::solve`].
    pub fn solve(self: &Arc<Self>, values: &[f64], rhs: &[f64]) -> Result<Vec<f64>> {
        self.factorize(values)?.solve(rhs)
    }

    /// The numeric LDL^T factorisation of the matrix of this pattern with entries `values` (in
    /// pattern order). Fails for non-finite values and for a singular matrix (a zero pivot).
    pub fn factorize(self: &Arc<Self>, values: &[f64]) -> Result<SymmetricFactor> {
        let n = self.size();
        check_values("values", values, self.entries())?;
        let matrix = SparseColMatRef::new(
            SymbolicSparseColMatRef::new_checked(n, n, &self.col_ptr, None, &self.row_idx),
            values,
        );
        let mut buffer = workspace(
            self.symbolic
                .factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default()),
        )?;
        let mut factor_values = vec![0.0; self.symbolic.len_val()];
        self.symbolic
            .factorize_numeric_ldlt(
                &mut factor_values,
                matrix,
                Side::Lower,
                LdltRegularization::default(),
                Par::Seq,
                MemStack::new(&mut buffer),
                Default::default(),
            )
            .map_err(|_| KernelError::Value {
                argument: "values",
                message: "the matrix is singular (a zero pivot in its LDL^T factorisation)".into(),
            })?;
        Ok(SymmetricFactor {
            pattern: Arc::clone(self),
            values: factor_values,
        })
    }
}

fn workspace(requirement: StackReq) -> Result<MemBuffer> {
    MemBuffer::try_new(requirement).map_err(|_| KernelError::Allocation {
        argument: "factorisation workspace",
        bytes: u128::MAX,
    })
}

/// The numeric LDL^T factor of one matrix of a [`SymmetricPattern`]: solves for any number of
/// right-hand sides without factorising again.
pub struct SymmetricFactor {
    pattern: Arc<SymmetricPattern>,
    values: Vec<f64>,
}

impl SymmetricFactor {
    /// Solves `A x = rhs` for the factorised matrix `A`. Fails for non-finite input and for a
    /// numerically singular matrix (a solution that is not finite).
    pub fn solve(&self, rhs: &[f64]) -> Result<Vec<f64>> {
        let symbolic = &self.pattern.symbolic;
        let n = self.pattern.size();
        check_values("rhs", rhs, n)?;
        let mut buffer = workspace(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq))?;
        let mut solution = rhs.to_vec();
        LdltRef::new(symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(&mut solution, n, 1),
            Par::Seq,
            MemStack::new(&mut buffer),
        );
        match solution.iter().position(|v| !v.is_finite()) {
            Some(_) => Err(KernelError::Value {
                argument: "values",
                message: "the matrix is numerically singular (the solution is not finite)".into(),
            }),
            None => Ok(solution),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 1-D Laplacian (2 on the diagonal, -1 beside it) in CSC form.
    fn laplacian(n: usize) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
        let (mut col_ptr, mut row_idx, mut values) = (vec![0], vec![], vec![]);
        for column in 0..n {
            for row in column.saturating_sub(1)..(column + 2).min(n) {
                row_idx.push(row);
                values.push(if row == column { 2.0 } else { -1.0 });
            }
            col_ptr.push(row_idx.len());
        }
        (col_ptr, row_idx, values)
    }

    #[test]
    fn solves_the_laplacian() {
        let n = 50;
        let (col_ptr, row_idx, values) = laplacian(n);
        let pattern = SymmetricPattern::new(col_ptr, row_idx).unwrap();
        // A x = rhs for x = 1..n: rhs is 0 except in the last row, 2 n - (n - 1) = n + 1.
        let exact: Vec<f64> = (1..=n).map(|i| i as f64).collect();
        let mut rhs = vec![0.0; n];
        rhs[n - 1] = (n + 1) as f64;
        let solution = pattern.solve(&values, &rhs).unwrap();
        for (got, want) in solution.iter().zip(&exact) {
            assert!((got - want).abs() < 1e-9, "{got} != {want}");
        }
    }

    #[test]
    fn a_factor_solves_many_right_hand_sides_as_solve_does() {
        let n = 30;
        let (col_ptr, row_idx, values) = laplacian(n);
        let pattern = SymmetricPattern::new(col_ptr, row_idx).unwrap();
        let factor = pattern.factorize(&values).unwrap();
        for k in 0..3 {
            let rhs: Vec<f64> = (0..n)
                .map(|i| ((i * 7 + k * 3) % 11) as f64 - 5.0)
                .collect();
            assert_eq!(
                factor.solve(&rhs).unwrap(),
                pattern.solve(&values, &rhs).unwrap()
            );
        }
        assert!(factor.solve(&[1.0]).is_err());
    }

    #[test]
    fn solves_an_indefinite_matrix() {
        // diag(2, -3) with an off-diagonal 1: LDL^T with a negative pivot.
        let pattern = SymmetricPattern::new(vec![0, 2, 4], vec![0, 1, 0, 1]).unwrap();
        let solution = pattern.solve(&[2.0, 1.0, 1.0, -3.0], &[3.0, -2.0]).unwrap();
        assert!((solution[0] - 1.0).abs() < 1e-12 && (solution[1] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_patterns_and_values() {
        assert!(SymmetricPattern::new(vec![0, 1, 2], vec![0, 0]).is_err()); // no diagonal in column 1
        assert!(SymmetricPattern::new(vec![0, 2, 3], vec![1, 0, 1]).is_err()); // unsorted rows
        assert!(SymmetricPattern::new(vec![0, 1, 2], vec![0, 5]).is_err()); // row outside
        assert!(SymmetricPattern::new(vec![0, 1, 3], vec![0, 1]).is_err()); // offsets past the end
        assert!(SymmetricPattern::new(vec![], vec![]).is_err());
        let pattern = SymmetricPattern::new(vec![0, 1, 2], vec![0, 1]).unwrap();
        assert!(pattern.solve(&[1.0, f64::NAN], &[1.0, 1.0]).is_err());
        assert!(pattern.solve(&[1.0, 1.0], &[1.0]).is_err());
        assert!(pattern.solve(&[1.0, 0.0], &[1.0, 1.0]).is_err()); // singular
    }
}
