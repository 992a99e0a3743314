//! Measurements behind `rangegp-bench`: the GP engine's speed ([`gp`]) and online against
//! batch hyperparameters ([`hyper`]), the CPU cost of each query kind ([`query`]), a site's
//! latency against a robot's ([`fleet`]).

pub mod fleet;
pub mod gp;
pub mod hyper;
pub mod query;
