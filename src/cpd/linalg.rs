//! Dense float64 linear algebra on the host, on `faer`: a row-major [`Matrix`] (the
//! layout the device buffers use), products, LU solves and symmetric eigenpairs.

use faer::linalg::solvers::Solve;
use faer::{Mat, MatRef, Side};

use crate::error::{Error, Result};

/// A row-major dense matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct Matrix {
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Entries row by row, `rows * cols` of them.
    pub data: Vec<f64>,
}

impl Matrix {
    /// A `rows` x `cols` matrix of zeros.
    pub fn zeros(rows: usize, cols: usize) -> Self {
        Self {
            rows,
            cols,
            data: vec![0.0; rows * cols],
        }
    }

    /// The entry at row `r`, column `c`.
    pub fn at(&self, r: usize, c: usize) -> f64 {
        self.data[r * self.cols + c]
    }

    /// Sets the entry at row `r`, column `c` to `v`.
    pub fn set(&mut self, r: usize, c: usize, v: f64) {
        self.data[r * self.cols + c] = v;
    }

    /// self * other.
    pub fn mul(&self, other: &Matrix) -> Matrix {
        assert_eq!(self.cols, other.rows, "matrix shapes");
        Matrix::from_faer((self.view() * other.view()).as_ref())
    }

    /// The transpose.
    pub fn transpose(&self) -> Matrix {
        Matrix::from_faer(self.view().transpose())
    }

    /// A faer view of the same data.
    pub fn view(&self) -> MatRef<'_, f64> {
        MatRef::from_row_major_slice(&self.data, self.rows, self.cols)
    }

    /// A row-major copy of a faer matrix.
    pub fn from_faer(m: MatRef<'_, f64>) -> Matrix {
        let (rows, cols) = (m.nrows(), m.ncols());
        Matrix {
            rows,
            cols,
            data: (0..rows)
                .flat_map(|i| (0..cols).map(move |j| m[(i, j)]))
                .collect(),
        }
    }
}

/// Solves A X = B (A square) by LU with partial pivoting; B has any number of columns.
/// A singular or non-finite system is an error.
pub fn solve(a: Matrix, b: Matrix) -> Result<Matrix> {
    assert!(a.cols == a.rows && b.rows == a.rows, "solve: shapes");
    if a.data.iter().chain(&b.data).any(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(
            "non-finite linear system on the host".into(),
        ));
    }
    let x: Mat<f64> = a.view().partial_piv_lu().solve(b.view());
    let x = Matrix::from_faer(x.as_ref());
    if x.data.iter().any(|v| !v.is_finite()) {
        return Err(Error::InvalidInput(
            "singular linear system on the host".into(),
        ));
    }
    Ok(x)
}

/// Eigen-decomposition of a symmetric matrix: (eigenvalues, eigenvectors as columns),
/// sorted by decreasing eigenvalue.
pub fn symmetric_eigen(a: &Matrix) -> (Vec<f64>, Matrix) {
    let n = a.rows;
    let Ok(eigen) = a.view().self_adjoint_eigen(Side::Lower) else {
        // faer fails only on non-finite input: report it as NaN eigenpairs.
        return (vec![f64::NAN; n], Matrix::zeros(n, n));
    };
    let (s, u) = (eigen.S(), eigen.U());
    let values = (0..n).rev().map(|i| s[i]).collect();
    let mut vectors = Matrix::zeros(n, n);
    for (new, old) in (0..n).rev().enumerate() {
        for k in 0..n {
            vectors.set(k, new, u[(k, old)]);
        }
    }
    (values, vectors)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_recovers_a_known_solution() {
        let a = Matrix {
            rows: 3,
            cols: 3,
            data: vec![0.0, 2.0, 1.0, 1.0, 1.0, 0.0, 3.0, 0.0, 4.0],
        };
        let x = Matrix {
            rows: 3,
            cols: 2,
            data: vec![1.0, -1.0, 2.0, 0.5, -3.0, 2.0],
        };
        let b = a.mul(&x);
        let got = solve(a, b).unwrap();
        for (g, w) in got.data.iter().zip(&x.data) {
            assert!((g - w).abs() < 1e-12, "{got:?}");
        }
    }

    #[test]
    fn symmetric_eigen_reconstructs_the_matrix() {
        let a = Matrix {
            rows: 3,
            cols: 3,
            data: vec![4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 1.0],
        };
        let (values, vectors) = symmetric_eigen(&a);
        assert!(values[0] >= values[1] && values[1] >= values[2]);
        let mut lambda = Matrix::zeros(3, 3);
        for i in 0..3 {
            lambda.set(i, i, values[i]);
        }
        let back = vectors.mul(&lambda).mul(&vectors.transpose());
        for (g, w) in back.data.iter().zip(&a.data) {
            assert!((g - w).abs() < 1e-10);
        }
    }
}
