//! Measurements behind `rangegp-bench`: the GP engine's speed ([`gp`]) and online against
//! batch hyperparameters ([`hyper`]), the CPU cost of each query kind ([`query`]).

pub mod gp;
pub mod hyper;
pub mod query;
