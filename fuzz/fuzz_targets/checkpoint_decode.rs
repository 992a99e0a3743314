//! Checkpoint files: any bytes are refused or decode into something `restore` checks; no panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rangegp_service::checkpoint::{decode, identity};
use rangegp_service::map::aggregate::world::WorldParams;

fuzz_target!(|data: &[u8]| {
    let params = WorldParams::default();
    let id = identity("fuzz", &params);
    if let Ok(checkpoint) = decode(data, id) {
        let _ = checkpoint.restore(&params);
    }
});
