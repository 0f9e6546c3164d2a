//! The engine's choices as the command line names them (`clap::ValueEnum`: `--help` lists
//! them, and a wrong name is refused with the list).

use vkdr::loss::Loss;
use vkdr::register::Optimizer;

/// A loss (`vkdr::loss::Loss`).
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum LossChoice {
    /// Mean squared error of the antialiased image against the observation.
    Mse,
    /// 1 - soft intersection over union.
    Iou,
    /// Rendered coverage weighted by the signed distance to the observed mask's boundary.
    Distance,
}

impl From<LossChoice> for Loss {
    fn from(choice: LossChoice) -> Self {
        match choice {
            LossChoice::Mse => Loss::Mse,
            LossChoice::Iou => Loss::Iou,
            LossChoice::Distance => Loss::Distance,
        }
    }
}

/// An optimiser (`vkdr::register::Optimizer`).
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum OptimizerChoice {
    /// Gradient descent with momentum and a decaying step.
    Sgd,
    /// Adam.
    Adam,
    /// Quasi-Newton (BFGS) with bounds on the code.
    Bfgs,
}

impl From<OptimizerChoice> for Optimizer {
    fn from(choice: OptimizerChoice) -> Self {
        match choice {
            OptimizerChoice::Sgd => Optimizer::Sgd,
            OptimizerChoice::Adam => Optimizer::Adam,
            OptimizerChoice::Bfgs => Optimizer::Bfgs,
        }
    }
}
