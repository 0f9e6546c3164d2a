//! Float64 reference backend of CPD: the same algorithm as the device's, with the E-step
//! and kernel products computed directly in float64 (dense, O(M N)).

use glam::DVec3;

use super::linalg::Matrix;
use super::{Backend, CpdParams, CpdResult, Expectation};
use crate::error::Result;

/// The float64 reference [`Backend`]: dense E-step and kernel products on
/// the host.
pub struct ReferenceBackend {
    source: Vec<DVec3>,
    target: Vec<DVec3>,
    beta: f64,
    /// The dense kernel matrix, formed at the first product.
    kernel: Option<Matrix>,
}

impl ReferenceBackend {
    /// The backend for source `source` (kernel width `beta`) and target `target`.
    pub fn new(source: &[DVec3], target: &[DVec3], beta: f64) -> Self {
        Self {
            source: source.to_vec(),
            target: target.to_vec(),
            beta,
            kernel: None,
        }
    }
}

impl Backend for ReferenceBackend {
    fn expectation(&mut self, moving: &[DVec3], sigma2: f64, log_c: f64) -> Result<Expectation> {
        let (m, n) = (moving.len(), self.target.len());
        let mut p1 = vec![0.0; m];
        let mut pull = vec![DVec3::ZERO; m];
        let mut spread = vec![0.0; m];
        let mut pt1 = vec![0.0; n];
        let mut exponents = vec![0.0; m];
        let mut log_denominators = 0.0;
        for (j, x) in self.target.iter().enumerate() {
            for (i, t) in moving.iter().enumerate() {
                exponents[i] = -(*x - *t).length_squared() / (2.0 * sigma2);
            }
            let top = exponents.iter().copied().fold(log_c, f64::max);
            let den = log_sum_exp(top, &exponents, log_c);
            log_denominators += den;
            for i in 0..m {
                let p = (exponents[i] - den).exp();
                p1[i] += p;
                pull[i] += p * (*x - moving[i]);
                spread[i] += p * (*x - moving[i]).length_squared();
                pt1[j] += p;
            }
        }
        Ok(Expectation {
            p1,
            pt1,
            pull,
            spread,
            log_denominators,
        })
    }

    fn kernel_product(&mut self, v: &Matrix) -> Result<Matrix> {
        let (source, beta) = (&self.source, self.beta);
        let g = self
            .kernel
            .get_or_insert_with(|| super::kernel_matrix(source, beta));
        Ok(g.mul(v))
    }
}

/// log(sum exp(exponents) + exp(log_c)), given `top`, the largest of them.
fn log_sum_exp(top: f64, exponents: &[f64], log_c: f64) -> f64 {
    let sum: f64 = exponents.iter().map(|e| (e - top).exp()).sum::<f64>() + (log_c - top).exp();
    top + sum.ln()
}

/// Registers with the float64 reference backend.
pub fn register(source: &[DVec3], target: &[DVec3], params: &CpdParams) -> Result<CpdResult> {
    let make = |y: &[DVec3], x: &[DVec3]| Ok(ReferenceBackend::new(y, x, params.beta));
    super::run_normalized(make, source, target, params, &mut |_, _| {})
}
