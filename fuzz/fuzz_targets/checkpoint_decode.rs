//! Checkpoint files: any bytes are refused or decode into something `drop_invalid_scales` and
//! `restore` check; no panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rangegp_service::checkpoint::{decode, identity};
use rangegp_service::map::aggregate::world::WorldParams;

fuzz_target!(|data: &[u8]| {
    let params = WorldParams::default();
    let id = identity("fuzz", &params);
    if let Ok(mut checkpoint) = decode(data, id) {
        checkpoint.drop_invalid_scales();
        let _ = checkpoint.restore(&params);
    }
});
