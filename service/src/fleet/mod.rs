//! Fleets (docs/FLEET.md): a robot publishes the aggregate tiles it changes into its site's Zenoh
//! key space ([`publish`]); a Zenoh storage keeps the latest of each; a site daemon, with no
//! sensor, assembles every robot's tiles ([`assemble`]) into one map ([`site_map`]) and answers
//! the same queries as a robot.

pub mod assemble;
pub mod publish;
pub mod site_map;
