//! The application on the vkdr engine (the `vkdr` command line's library): a generated
//! category dataset, the evaluation protocol of the paper's Table 1, pictures, and the
//! checks of users' own categories.

pub mod bop;
pub mod check;
pub mod dataset;
pub mod eval;
pub mod metrics;
pub mod plot;
pub mod reference;
pub mod surface;
