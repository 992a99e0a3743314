//! Measurements behind `rangegp-bench`: the GP engine's speed ([`gp`]) and online against
//! batch hyperparameters ([`hyper`]).

pub mod gp;
pub mod hyper;
