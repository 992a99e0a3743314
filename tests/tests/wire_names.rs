//! The iceoryx2 type names of the shared-memory types are the documented constants (peers in
//! other languages name the types by them). Here, not in the proto crate, because reading them
//! is an `unsafe` trait call and the proto crate forbids unsafe code.

#![allow(unsafe_code)] // The one unsafe call below, with its SAFETY comment.

use iceoryx2::prelude::ZeroCopySend;
use rangegp_proto::scan::{ScanHeader, ScanPoint, SCAN_HEADER_TYPE_NAME, SCAN_POINT_TYPE_NAME};

#[test]
fn type_names_are_the_documented_constants() {
    // SAFETY: `type_name` returns the static string given to the derive; nothing is read from
    // shared memory.
    let (header, point) = unsafe {
        (
            <ScanHeader as ZeroCopySend>::type_name(),
            <ScanPoint as ZeroCopySend>::type_name(),
        )
    };
    assert_eq!(header, SCAN_HEADER_TYPE_NAME);
    assert_eq!(point, SCAN_POINT_TYPE_NAME);
}
