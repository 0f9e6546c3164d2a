//! CPD's E-step and Gaussian-kernel products on the device: [`GpuBackend`], the points
//! sorted into a grid so that each workgroup's rows meet nearby columns first.

use bytemuck::{Pod, Zeroable};
use glam::DVec3;

use crate::error::{Error, Result};
use crate::gpu::{spans, Binding, Buffer, BufferKind, ComputePipeline, Context, Groups, Recorder};
use crate::mesh::centroid;
use crate::shaders;

use super::linalg::Matrix;
use super::{neighbours, Backend, Expectation, ROWS, SPAN};

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct EstepConstants {
    m: u32,
    n: u32,
    first: u32,
    end: u32,
    inv_two_sigma2: f32,
    log_c: f32,
    piece: u32,
    pieces: u32,
}
const _: () = assert!(shaders::CPD_DENOMINATOR_COMP.takes::<EstepConstants>());
const _: () = assert!(shaders::CPD_ACCUMULATE_COMP.takes::<EstepConstants>());
const _: () = assert!(shaders::GAUSS_PRODUCT_COMP.takes::<EstepConstants>());

/// CPD's compute pipelines.
pub struct CpdPipelines {
    denominator: ComputePipeline,
    accumulate: ComputePipeline,
    gauss: ComputePipeline,
}

impl CpdPipelines {
    /// Builds the E-step and kernel-product pipelines.
    pub fn new(ctx: &Context) -> Result<Self> {
        Ok(Self {
            denominator: ComputePipeline::new(ctx, &shaders::CPD_DENOMINATOR_COMP)?,
            accumulate: ComputePipeline::new(ctx, &shaders::CPD_ACCUMULATE_COMP)?,
            gauss: ComputePipeline::new(ctx, &shaders::GAUSS_PRODUCT_COMP)?,
        })
    }
}

/// Values read in a sorted order (`order[k]` is the caller's index of value k), back in
/// the caller's order.
fn unsorted<T: Copy>(sorted: Vec<T>, order: &[u32]) -> Vec<T> {
    let mut values = sorted.clone();
    for (&value, &i) in sorted.iter().zip(order) {
        values[i as usize] = value;
    }
    values
}

fn vec4s(points: &[DVec3], offset: DVec3) -> Vec<[f32; 4]> {
    points
        .iter()
        .map(|p| {
            let q = *p - offset;
            [q.x as f32, q.y as f32, q.z as f32, 0.0]
        })
        .collect()
}

/// The device backend: points live on the device as float32, relative to the target's
/// centroid (so coordinates far from the origin keep their precision).
pub struct GpuBackend<'a> {
    ctx: &'a Context,
    pipelines: &'a CpdPipelines,
    source: Vec<DVec3>,
    offset: DVec3,
    beta: f64,
    /// The target points (uploaded in each E-step's sorted order into `target`).
    target_points: Vec<DVec3>,
    target: Buffer,
    n: usize,
    moving: Buffer,
    log_den: Buffer,
    running: Buffer,
    sums: Buffer,
    source_points: Buffer,
    columns: Buffer,
    product: Buffer,
}

impl<'a> GpuBackend<'a> {
    /// Uploads `source` and `target` for a kernel of width `beta` (in the points'
    /// units).
    pub fn new(
        ctx: &'a Context,
        pipelines: &'a CpdPipelines,
        source: &[DVec3],
        target: &[DVec3],
        beta: f64,
    ) -> Result<Self> {
        let offset = centroid(target);
        let (m, n) = (source.len() as u64, target.len() as u64);
        let device = |name, bytes| Buffer::new(ctx, name, bytes, BufferKind::Device);
        Ok(Self {
            ctx,
            pipelines,
            source: source.to_vec(),
            offset,
            beta,
            target_points: target.to_vec(),
            target: Buffer::from_slice(ctx, "cpd target", &vec4s(target, offset))?,
            n: target.len(),
            moving: device("cpd moving", m * 16)?,
            log_den: device("cpd log denominators", n * 4)?,
            running: device("cpd running sums", n * 8)?,
            sums: device("cpd sums", m * 32)?,
            source_points: Buffer::from_slice(ctx, "cpd source", &vec4s(source, offset))?,
            columns: device("kernel columns", m * 16)?,
            product: device("kernel product", m * 16)?,
        })
    }
}

impl Backend for GpuBackend<'_> {
    fn expectation(&mut self, moving: &[DVec3], sigma2: f64, log_c: f64) -> Result<Expectation> {
        let (m, n) = (moving.len() as u32, self.n as u32);
        let constants = EstepConstants {
            m,
            n,
            first: 0,
            end: 0,
            inv_two_sigma2: (0.5 / sigma2) as f32,
            log_c: log_c as f32,
            piece: 0,
            pieces: 1,
        };
        if !constants.inv_two_sigma2.is_finite() || !constants.log_c.is_finite() {
            return Err(Error::InvalidInput(format!(
                "sigma^2 = {sigma2:e} is out of float32 range"
            )));
        }
        // Both sets sorted into cells where only near pairs matter (neighbours.rs).
        let width = neighbours::cutoff(sigma2, log_c, self.n.max(moving.len()));
        let grid = neighbours::Grid::new(moving.iter().chain(&self.target_points), width);
        let ((moving_order, moving_cells), (target_order, target_cells)) = match &grid {
            Some(grid) => (grid.sort(moving), grid.sort(&self.target_points)),
            None => {
                let identity = |k: u32| ((0..k).collect::<Vec<u32>>(), Vec::new());
                (identity(m), identity(n))
            }
        };
        let sorted = |points: &[DVec3], order: &[u32]| -> Vec<DVec3> {
            order.iter().map(|&i| points[i as usize]).collect()
        };
        self.moving
            .write(0, &vec4s(&sorted(moving, &moving_order), self.offset))?;
        self.target.write(
            0,
            &vec4s(&sorted(&self.target_points, &target_order), self.offset),
        )?;
        let groups = |own: u32| own.div_ceil(64 * ROWS);
        let (denominator_ranges, denominator_pieces) = neighbours::plan(
            grid.as_ref(),
            &target_cells,
            &moving_cells,
            groups(n) as usize,
            m,
            SPAN,
        );
        let (accumulate_ranges, accumulate_pieces) = neighbours::plan(
            grid.as_ref(),
            &moving_cells,
            &target_cells,
            groups(m) as usize,
            n,
            SPAN,
        );
        let denominator_ranges =
            Buffer::from_slice(self.ctx, "cpd denominator ranges", &denominator_ranges)?;
        let accumulate_ranges =
            Buffer::from_slice(self.ctx, "cpd accumulate ranges", &accumulate_ranges)?;
        let p = self.pipelines;
        let mut rec = Recorder::new(self.ctx)?;
        let (moving_buffer, target, log_den) = (&self.moving, &self.target, &self.log_den);
        let passes = [
            (
                &p.denominator,
                &self.running,
                &denominator_ranges,
                denominator_pieces,
                n,
            ),
            (
                &p.accumulate,
                &self.sums,
                &accumulate_ranges,
                accumulate_pieces,
                m,
            ),
        ];
        for (pipeline, out, ranges, pieces, own) in passes {
            let bindings = [
                Binding::buffer(moving_buffer),
                Binding::buffer(target),
                Binding::buffer(log_den),
                Binding::buffer(out),
                Binding::buffer(ranges),
            ];
            for piece in 0..pieces {
                rec.run_compute(
                    pipeline,
                    &bindings,
                    &EstepConstants {
                        piece,
                        pieces,
                        ..constants
                    },
                    Groups::Count(groups(own), 1, 1),
                );
                rec.memory_barrier();
            }
        }
        self.ctx.submit_and_wait(rec)?;
        // Back to the callers' order.
        let sums = unsorted(
            self.sums.read_range::<[[f32; 4]; 2]>(0, m as usize)?,
            &moving_order,
        );
        let log_den = unsorted(
            self.log_den.read_range::<f32>(0, n as usize)?,
            &target_order,
        );
        Ok(Expectation {
            p1: sums.iter().map(|s| s[0][3] as f64).collect(),
            // Pt1_n = sum_m P_mn = 1 - c / denominator_n.
            pt1: log_den
                .iter()
                .map(|&l| (1.0 - (log_c - l as f64).exp()).clamp(0.0, 1.0))
                .collect(),
            pull: sums
                .iter()
                .map(|s| DVec3::new(s[0][0] as f64, s[0][1] as f64, s[0][2] as f64))
                .collect(),
            spread: sums.iter().map(|s| s[1][0] as f64).collect(),
            log_denominators: log_den.iter().map(|&l| l as f64).sum(),
        })
    }

    fn kernel_product(&mut self, v: &Matrix) -> Result<Matrix> {
        let m = self.source.len();
        let mut out = Matrix::zeros(m, v.cols);
        let constants = EstepConstants {
            m: m as u32,
            n: m as u32,
            first: 0,
            end: 0,
            inv_two_sigma2: (0.5 / (self.beta * self.beta)) as f32,
            log_c: 0.0,
            piece: 0,
            pieces: 1,
        };
        for block in (0..v.cols).step_by(4) {
            let width = 4.min(v.cols - block);
            let columns: Vec<[f32; 4]> = (0..m)
                .map(|i| {
                    std::array::from_fn(|c| {
                        if c < width {
                            v.at(i, block + c) as f32
                        } else {
                            0.0
                        }
                    })
                })
                .collect();
            self.columns.write(0, &columns)?;
            let p = self.pipelines;
            let mut rec = Recorder::new(self.ctx)?;
            let bindings = [
                Binding::buffer(&self.source_points),
                Binding::buffer(&self.columns),
                Binding::buffer(&self.product),
            ];
            record_spans(&mut rec, &p.gauss, &bindings, constants, m as u32, m as u32);
            self.ctx.submit_and_wait(rec)?;
            let product = self.product.read_range::<[f32; 4]>(0, m)?;
            for (i, row) in product.iter().enumerate() {
                for c in 0..width {
                    out.set(i, block + c, row[c] as f64);
                }
            }
        }
        Ok(out)
    }
}

/// Records the kernel product: a dispatch per [`SPAN`] of the `other` set's points (in
/// order, each after the last), each serving all `own` points.
fn record_spans(
    rec: &mut Recorder,
    pipeline: &ComputePipeline,
    bindings: &[Binding],
    constants: EstepConstants,
    other: u32,
    own: u32,
) {
    for (first, end) in spans(other, SPAN) {
        let constants = EstepConstants {
            first,
            end,
            ..constants
        };
        rec.run_compute(
            pipeline,
            bindings,
            &constants,
            Groups::Count(own.div_ceil(64 * ROWS), 1, 1),
        );
        rec.memory_barrier();
    }
}
