//! Small dense linear algebra in float64 for CPD's M-step (no LAPACK here): LU solves with
//! partial pivoting and a Jacobi eigensolver for small symmetric matrices.

use crate::error::{Error, Result};

/// A row-major dense matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct Matrix {
    pub rows: usize,
    pub cols: usize,
    pub data: Vec<f64>,
}

impl Matrix {
    pub fn zeros(rows: usize, cols: usize) -> Self {
        Self {
            rows,
            cols,
            data: vec![0.0; rows * cols],
        }
    }

    pub fn at(&self, r: usize, c: usize) -> f64 {
        self.data[r * self.cols + c]
    }

    pub fn set(&mut self, r: usize, c: usize, v: f64) {
        self.data[r * self.cols + c] = v;
    }

    /// self * other.
    pub fn mul(&self, other: &Matrix) -> Matrix {
        assert_eq!(self.cols, other.rows, "matrix shapes");
        let mut out = Matrix::zeros(self.rows, other.cols);
        for i in 0..self.rows {
            for k in 0..self.cols {
                let a = self.at(i, k);
                if a == 0.0 {
                    continue;
                }
                let row = &other.data[k * other.cols..(k + 1) * other.cols];
                let dst = &mut out.data[i * other.cols..(i + 1) * other.cols];
                for (d, b) in dst.iter_mut().zip(row) {
                    *d += a * b;
                }
            }
        }
        out
    }

    pub fn transpose(&self) -> Matrix {
        let mut out = Matrix::zeros(self.cols, self.rows);
        for i in 0..self.rows {
            for j in 0..self.cols {
                out.set(j, i, self.at(i, j));
            }
        }
        out
    }
}

/// Solves A X = B (A square) by LU with partial pivoting; B has any number of columns.
pub fn solve(mut a: Matrix, mut b: Matrix) -> Result<Matrix> {
    let n = a.rows;
    assert!(a.cols == n && b.rows == n, "solve: shapes");
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&i, &j| a.at(i, col).abs().total_cmp(&a.at(j, col).abs()))
            .unwrap_or(col);
        let p = a.at(pivot, col);
        if !(p.abs() > 0.0) || !p.is_finite() {
            return Err(Error::InvalidInput(format!(
                "singular system in CPD's M-step (pivot {p})"
            )));
        }
        if pivot != col {
            for c in 0..n {
                a.data.swap(pivot * n + c, col * n + c);
            }
            for c in 0..b.cols {
                b.data.swap(pivot * b.cols + c, col * b.cols + c);
            }
        }
        for r in col + 1..n {
            let f = a.at(r, col) / p;
            if f == 0.0 {
                continue;
            }
            for c in col..n {
                let v = a.at(r, c) - f * a.at(col, c);
                a.set(r, c, v);
            }
            for c in 0..b.cols {
                let v = b.at(r, c) - f * b.at(col, c);
                b.set(r, c, v);
            }
        }
    }
    for col in (0..n).rev() {
        for c in 0..b.cols {
            let mut v = b.at(col, c);
            for k in col + 1..n {
                v -= a.at(col, k) * b.at(k, c);
            }
            b.set(col, c, v / a.at(col, col));
        }
    }
    Ok(b)
}

/// Eigen-decomposition of a small symmetric matrix by cyclic Jacobi rotations: returns
/// (eigenvalues, eigenvectors as columns), sorted by decreasing eigenvalue.
pub fn symmetric_eigen(a: &Matrix) -> (Vec<f64>, Matrix) {
    let n = a.rows;
    let mut a = a.clone();
    let mut v = Matrix::zeros(n, n);
    for i in 0..n {
        v.set(i, i, 1.0);
    }
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a.at(i, j).powi(2))
            .sum();
        let scale: f64 = (0..n)
            .map(|i| a.at(i, i).powi(2))
            .sum::<f64>()
            .max(f64::MIN_POSITIVE);
        if off <= 1e-30 * scale {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a.at(p, q);
                if apq == 0.0 {
                    continue;
                }
                let theta = (a.at(q, q) - a.at(p, p)) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a.at(k, p), a.at(k, q));
                    a.set(k, p, c * akp - s * akq);
                    a.set(k, q, s * akp + c * akq);
                }
                for k in 0..n {
                    let (apk, aqk) = (a.at(p, k), a.at(q, k));
                    a.set(p, k, c * apk - s * aqk);
                    a.set(q, k, s * apk + c * aqk);
                }
                for k in 0..n {
                    let (vkp, vkq) = (v.at(k, p), v.at(k, q));
                    v.set(k, p, c * vkp - s * vkq);
                    v.set(k, q, s * vkp + c * vkq);
                }
            }
        }
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&i, &j| a.at(j, j).total_cmp(&a.at(i, i)));
    let values = order.iter().map(|&i| a.at(i, i)).collect();
    let mut vectors = Matrix::zeros(n, n);
    for (new, &old) in order.iter().enumerate() {
        for k in 0..n {
            vectors.set(k, new, v.at(k, old));
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
    fn jacobi_eigen_reconstructs_the_matrix() {
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
