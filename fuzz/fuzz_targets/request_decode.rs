//! Every query decoder, both encodings: any bytes give a value or an error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rangegp_proto::codec::{decode, peek_version, Encoding};
use rangegp_proto::msg::{ElevationRequest, GridRequest, RayRequest, StatusRequest, VarianceRequest};

fuzz_target!(|data: &[u8]| {
    for encoding in [Encoding::Bincode, Encoding::Json] {
        let _ = peek_version(encoding, data);
        let _ = decode::<ElevationRequest>(encoding, data);
        let _ = decode::<VarianceRequest>(encoding, data);
        let _ = decode::<RayRequest>(encoding, data);
        let _ = decode::<GridRequest>(encoding, data);
        let _ = decode::<StatusRequest>(encoding, data);
    }
});
