//! How to register: [`RegisterParams`], the schedules the front ends use, and the bounds
//! and constants the device's optimisers share.

use crate::diff::{DepthLoss, Shading};
use crate::error::{Error, Result};
use crate::loss::Loss;

use super::Optimizer;

/// The most iterations (or alignment iterations) one registration may ask for.
pub const MAX_ITERATIONS: usize = 100_000;

/// How to register.
#[derive(Clone, Copy, Debug)]
pub struct RegisterParams {
    /// Iterations of the registration, besides the pose alignment's `align`.
    pub iterations: usize,
    /// Momentum of SGD (Adam's first-moment decay), in `[0, 1)`.
    pub momentum: f64,
    /// Learning-rate decay per iteration.
    pub decay: f64,
    /// Length of the first latent step, in standard deviations of the training codes
    /// (SGD's learning rate is set from the first gradient so that its step has this length).
    pub latent_step: f64,
    /// Update the pose once every this many iterations (0: the pose stays fixed).
    pub pose_every: usize,
    /// With pose optimisation: iterations before `iterations` that align the pose alone
    /// with `align_loss` (the shape would otherwise bend to explain a misaligned
    /// silhouette, and a distance loss reaches further than a mask loss).
    pub align: usize,
    /// Loss of the pose alignment stage.
    pub align_loss: Loss,
    /// Let the z translation move too (ill-posed with shape from one view).
    pub optimize_z: bool,
    /// First translation and rotation steps of the pose (metres, radians).
    pub translation_step: f64,
    /// First rotation step of the pose, radians.
    pub rotation_step: f64,
    /// How the code (and the pose) are updated.
    pub optimizer: Optimizer,
    /// Loss against each job's mask after the alignment.
    pub loss: Loss,
    /// Compare Lambert shading with each job's `shaded` image instead of the mask (the
    /// pose alignment still compares masks); the loss must be mse.
    pub shading: Option<Shading>,
    /// Compare each job's observed depth too (the pose alignment does not); the loss
    /// must be mse. With depth the z translation is observed: set `optimize_z`.
    pub depth: Option<DepthLoss>,
    /// Weight of a Gaussian prior on the code: `code_prior * |s|^2` joins the loss, s the
    /// code in training standard deviations (each dimension over its spread in the
    /// training set), so a typical training shape costs about the weight times the
    /// dimensions. It decides what the images leave open, such as a shape shifted in its
    /// own frame against a shifted pose. 0 (the default): none.
    pub code_prior: f64,
    /// After the fit, hold the directions of the code the images hardly constrain with a
    /// strong prior and fit on from there (`evidence::held_prior`): the schedules do. It
    /// applies to BFGS fits without depth ([`RegisterParams::holds_unseen`]). Costs up to
    /// the fit's iterations again where a direction is held.
    pub hold_unseen: bool,
    /// With the pose known and depth observed: iterations of a stage before the fit that
    /// compares the mask alone ([`STAGE_MASK_FIRST`]); the fit goes on from its code. The
    /// depth's bounded cost pulls a shape far from the instance's along directions the
    /// silhouette settles quickly (a generated bottle from 2.96 to 1.56 times its oracle's
    /// error). 0 (the default): none; the known-pose schedule runs [`MASK_FIRST`].
    pub mask_first: usize,
    /// Fit one uniform scale of the shape too (an instance larger or smaller than the
    /// training set's), within [`SCALE_RANGE`]: observable where depth or a further view
    /// tells the distance; from one mask a scale trades against the distance.
    pub optimize_scale: bool,
    /// Read the loss back every this many iterations; stop when it improved by less than
    /// `plateau` (relative) over the last chunk.
    pub check_every: usize,
    /// Relative improvement over a chunk below which a registration stops, in
    /// `[0, 1)`.
    pub plateau: f64,
    /// The pixels across the object a single view is rendered and compared at, at least:
    /// an object larger in its image is rendered at a coarser whole step (each pixel the
    /// mean of step x step of the image's, [`super::Region`]), which costs a step squared fewer
    /// pixels. 0 (the default): the image's own pixels, where the loss and gradients are
    /// exactly the whole image's. The schedules use [`DETAIL`].
    pub detail: u32,
    /// The depth samples across the object, at least, where a region of interest is cut
    /// (`detail` not 0): the depth is compared at every step-th pixel of the region along
    /// each axis, at the coarsest whole step that keeps this many across
    /// ([`super::Region::depth_step`]), each sample weighted by the step squared. The
    /// depth's per-pixel passes cost most of an iteration with depth on a CPU driver, and
    /// this takes a registration on a real mug from 0.9 to 0.6 s at the same error (32,
    /// lavapipe); but with independent noise in every pixel's depth it throws away the
    /// averaging of the pixels it skips (a generated bottle's known-pose error 0.23 -> 0.40
    /// mm with 2 mm noise): docs/evaluation.md. 0 (the default, and the schedules'): at
    /// every pixel. The depth reach ([`RegisterParams::reach`]) always compares every pixel.
    pub depth_detail: u32,
}

/// A registration's stage ([`super::Registration::stages`]): the fit (with the pose known, or the
/// joint fit of pose and shape after an alignment).
pub const STAGE_FIT: &str = "fit";
/// The pose aligned alone (`RegisterParams::align`).
pub const STAGE_ALIGN: &str = "pose alignment";
/// The pose brought to the measured depth ([`RegisterParams::reach`]).
pub const STAGE_REACH: &str = "depth reach";
/// The stage before the fit with the pose known and depth observed, that compares the
/// mask alone ([`RegisterParams::mask_first`]).
pub const STAGE_MASK_FIRST: &str = "mask first";
/// The fit again from where it stopped, with the directions of the code the images hardly
/// constrain held by a strong prior (`evidence::held_prior`).
pub const STAGE_HELD: &str = "fit with the unseen held";
/// The joint fit again from a turned start that scored better (the registration from
/// starts), in place of the first joint fit.
pub const STAGE_TURNED: &str = "fit from a turn";
/// The joint fit again from its pose moved along the line of sight to the measured depth,
/// where it had settled off it, in place of the joint fit (`depth_settle`).
pub const STAGE_SETTLED: &str = "fit moved to the depth";
/// Every stage's name ([`super::Registration::stages`] holds some of them).
pub const STAGES: [&str; 7] = [
    STAGE_MASK_FIRST,
    STAGE_ALIGN,
    STAGE_REACH,
    STAGE_FIT,
    STAGE_TURNED,
    STAGE_SETTLED,
    STAGE_HELD,
];

/// The detail of the registration schedules ([`RegisterParams::detail`]): an object over
/// 128 pixels across is rendered at a step of 2 or more. On a real 640 x 480 frame (a mug
/// 230 pixels across, a step of 3) a registration from pose noise costs a third of the
/// full resolution's, its error within 1% (docs/evaluation.md).
pub const DETAIL: u32 = 64;

/// Iterations of the mask-only stage the known-pose schedule runs before a fit with depth
/// ([`RegisterParams::mask_first`]). Measured on the generated seeds 1 and 11 with depth
/// (3 trials, known pose / oracle): 15 took the bottles from 1.42, 1.02, 1.64, 2.96 to
/// 1.25, 1.06, 1.06, 1.56 and kept every other instance within 0.04 (30: the same
/// bottles 1.24, 0.99, 1.29, 1.56, a bowl 0.73 to 0.83).
pub const MASK_FIRST: usize = 15;

impl RegisterParams {
    /// An error naming the first parameter out of range: 1 to [`MAX_ITERATIONS`]
    /// iterations (the optimiser's state holds every iteration's loss and code, with f32
    /// indices on the device), steps, momentum, decay and plateau finite and in range, and
    /// a valid depth loss.
    pub fn validate(&self) -> Result<()> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let problem = if self.iterations == 0 {
            Some("registration needs at least one iteration".to_string())
        } else if let Some((what, count)) = [
            ("iterations", self.iterations),
            ("alignment iterations", self.align),
            ("mask-first iterations", self.mask_first),
        ]
        .into_iter()
        .find(|&(_, count)| count > MAX_ITERATIONS)
        {
            Some(format!(
                "{count} {what}: at most {MAX_ITERATIONS} are supported"
            ))
        } else if !(positive(self.latent_step) && self.latent_step <= 3.0) {
            Some(format!(
                "latent step {} must be in (0, 3] training standard deviations",
                crate::error::show(self.latent_step)
            ))
        } else if !(positive(self.translation_step) && self.translation_step <= 1.0) {
            Some(format!(
                "translation step {} must be in (0, 1] m",
                crate::error::show(self.translation_step)
            ))
        } else if !(positive(self.rotation_step) && self.rotation_step <= 1.0) {
            Some(format!(
                "rotation step {} must be in (0, 1] rad",
                crate::error::show(self.rotation_step)
            ))
        } else if !(0.0..1.0).contains(&self.momentum)
            || !(0.0..=1.0).contains(&self.decay)
            || self.decay == 0.0
        {
            Some(format!(
                "momentum {} must be in [0, 1) and decay {} in (0, 1]",
                self.momentum, self.decay
            ))
        } else if !(0.0..=1.0).contains(&self.code_prior) {
            Some(format!(
                "code prior {} must be in [0, 1]",
                crate::error::show(self.code_prior)
            ))
        } else if !(0.0..1.0).contains(&self.plateau) {
            Some(format!("plateau {} must be in [0, 1)", self.plateau))
        } else if self.depth_detail != 0 && self.depth_detail < 8 {
            Some(format!(
                "depth detail {} must be 0 (every pixel) or at least 8 samples",
                self.depth_detail
            ))
        } else if self.detail != 0 && self.detail < 16 {
            Some(format!(
                "detail {} must be 0 (the image's pixels) or at least 16 pixels",
                self.detail
            ))
        } else {
            None
        };
        if let Some(p) = problem {
            return Err(Error::InvalidInput(p));
        }
        if let Some(depth) = &self.depth {
            depth.validate()?;
        }
        Ok(())
    }

    /// Whether the fit of a job with `views` views is followed by the stage that holds the
    /// directions of the code the images hardly constrain (`hold_unseen`): with BFGS (whose
    /// inverse Hessian estimate tells them), without depth, and with two views or more
    /// (with one mask it gained on the generated bowls what it lost on the bottles). With
    /// depth it made the generated seed-1 set worse (known pose, 3 trials: a bottle from
    /// 1.4 to 2.0 times its oracle's error, a bowl from 0.73 to 1.10; another bowl from
    /// 0.46 to 0.42).
    pub fn holds_unseen(&self, views: usize) -> bool {
        self.hold_unseen && self.optimizer == Optimizer::Bfgs && self.depth.is_none() && views > 1
    }

    /// Iterations at most, the pose alignment's included (and with depth and z free, the
    /// stage that brings the aligned pose to the measured depth; with `hold_unseen`, the
    /// fit's again for the held stage, as with two views or more).
    pub fn total_iterations(&self) -> usize {
        let aligned = self.pose_every > 0 && self.align > 0;
        let held = self.holds_unseen(2);
        self.iterations
            + if aligned { self.align } else { 0 }
            + self.reach().map_or(0, |reach| reach.iterations)
            + if held { self.iterations } else { 0 }
            + self.masks_first().map_or(0, |first| first.iterations)
    }

    /// The mask-only stage before the fit ([`RegisterParams::mask_first`]), where it runs:
    /// the pose known, depth observed and `mask_first` iterations asked for.
    pub fn masks_first(&self) -> Option<RegisterParams> {
        (self.pose_every == 0 && self.depth.is_some() && self.mask_first > 0).then_some(
            RegisterParams {
                iterations: self.mask_first,
                shading: None,
                depth: None,
                ..*self
            },
        )
    }

    /// The stage after the alignment that brings the pose to the measured depth
    /// ([`REACH`]), where it runs: with an alignment, depth and z free. It compares the
    /// depth at every pixel (`depth_detail` 0): the pose moves most here, and with every
    /// second pixel's depth one trial of 30 on the real can (frame 13, `depth_detail` 32)
    /// was caught 47 mm nearer than the truth, at 5.5 times the others' loss.
    pub fn reach(&self) -> Option<RegisterParams> {
        let depth = self.depth?;
        (self.pose_every > 0 && self.align > 0 && self.optimize_z).then_some(RegisterParams {
            iterations: REACH_ITERATIONS,
            shading: None,
            depth: Some(DepthLoss {
                scale: depth.scale * REACH,
                ..depth
            }),
            depth_detail: 0,
            ..*self
        })
    }
}

impl RegisterParams {
    /// The schedule `vkdr register` and `vkdr eval` use with the pose known, for views of
    /// `pixels` pixels: 30 BFGS iterations of the code, the prior those pixels imply
    /// ([`observation_prior`]), a large object rendered at [`DETAIL`].
    pub fn known_pose(pixels: usize) -> Self {
        Self {
            iterations: 30,
            optimizer: Optimizer::Bfgs,
            code_prior: observation_prior(pixels),
            hold_unseen: true,
            mask_first: MASK_FIRST,
            detail: DETAIL,
            ..Self::default()
        }
    }

    /// The schedule `vkdr register --optimize-pose` and `vkdr eval` use with the pose
    /// free (chosen on a validation dataset, another seed than the reported one): the pose
    /// aligned alone for 15 iterations with the distance loss (with depth and `optimize_z`
    /// then [`REACH_ITERATIONS`] with mask and depth at a wide scale, [`REACH`]), then 60 of
    /// pose and shape together with BFGS. The z translation stays fixed: set `optimize_z`
    /// where depth or a further view observes it.
    pub fn free_pose(pixels: usize) -> Self {
        Self {
            iterations: 60,
            pose_every: 1,
            align: 15,
            align_loss: Loss::Distance,
            translation_step: 0.01,
            rotation_step: 0.05,
            ..Self::known_pose(pixels)
        }
    }
}

impl Default for RegisterParams {
    fn default() -> Self {
        Self {
            iterations: 30,
            momentum: 0.9,
            decay: 0.95,
            latent_step: 0.5,
            pose_every: 0,
            align: 0,
            align_loss: Loss::Distance,
            optimize_z: false,
            translation_step: 0.004,
            rotation_step: 0.02,
            optimizer: Optimizer::Sgd,
            loss: Loss::Mse,
            shading: None,
            depth: None,
            code_prior: 0.0,
            hold_unseen: false,
            mask_first: 0,
            optimize_scale: false,
            check_every: 10,
            plateau: 1e-4,
            detail: 0,
            depth_detail: 0,
        }
    }
}

/// The code prior's weight ([`RegisterParams::code_prior`]) that an observation of
/// `pixels` pixels per view implies. The loss is a mean of per-pixel squared residuals
/// over the N pixels; with pixel noise of variance sigma^2 its negative log-likelihood is
/// N loss / (2 sigma^2), and the Gaussian prior's is |s|^2 / 2 in training standard
/// deviations, so the posterior's is (N / 2 sigma^2) (loss + sigma^2 / N |s|^2): weight
/// sigma^2 / N. sigma = 1/8: a mask's boundary placed to an eighth of a pixel's coverage
/// (calibrated on the generated set: with sigma^2 = 1/4, a binary pixel's largest variance,
/// known-pose errors of the seed-1 bottles rose from 0.30 to 0.47 mm; at 1/64 they stay).
/// Weak where the images decide, it makes the far tails of the training distribution cost:
/// a code 30 SD out in one dimension costs as much as 14 wrong pixels.
pub fn observation_prior(pixels: usize) -> f64 {
    1.0 / (64.0 * pixels.max(1) as f64)
}

/// The range of [`RegisterParams::optimize_scale`]'s scale: its optimiser coordinate is
/// bounded to +-3 units (`SCALE_BOUND`), one unit a quarter of the size: 0.25
/// to 1.75 (a real master chef can is 1.55 times the mean of the two training cans whose
/// space registers it; at 0.5 to 1.5 it ended on the bound, 4% small and 10 mm off in z).
pub const SCALE_RANGE: (f64, f64) = (
    1.0 - SCALE_BOUND * SCALE_UNIT,
    1.0 + SCALE_BOUND * SCALE_UNIT,
);
/// The relative scale of one optimiser unit of the scale coordinate.
pub(super) const SCALE_UNIT: f64 = 0.25;
/// The bound of the scale coordinate, in its units ([`SCALE_UNIT`]).
pub(super) const SCALE_BOUND: f64 = 3.0;

/// The optimisers keep each code coordinate within this many of its units of the mean
/// shape (`optimizer_coordinates`: training standard deviations for SGD and Adam, RMS
/// training deformations for BFGS, 3 standard deviations or more), as
/// `glsl/optimizer.comp` and `glsl/bfgs.comp` do. A safety net against a runaway where the
/// space only extrapolates, not a prior (that is [`RegisterParams::code_prior`]'s work,
/// and [`RegisterParams::hold_unseen`]'s). Bounds in standard deviations were worse both
/// ways (`gen-dataset` seed 1, known pose, 3 trials): at 3 they held fits short of their
/// test instances, whose own codes lie up to 8.8 out (two silhouettes of a bottle: 18
/// times its oracle's error, against 2.5); at 10 the depth fits ran away (a bottle with
/// depth: 4.6 times, against 1.4).
pub const CODE_BOUND: f64 = 3.0;

/// With depth and z free, after the alignment: the pose (with `optimize_scale` the shape
/// too) moves by mask and depth with the depth cost's scale REACH times the joint fit's,
/// for REACH_ITERATIONS iterations, so that a start centimetres off in depth reaches the
/// measured depth before the joint fit (`Registrar::register_batch`).
pub const REACH: f64 = 10.0;
/// See [`REACH`].
pub const REACH_ITERATIONS: usize = 10;
