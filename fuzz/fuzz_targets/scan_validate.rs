//! A scan as it sits in shared memory (header bytes + point bytes): validation accepts or rejects,
//! never panics, and what it accepts is finite and within the sensor's range.
#![no_main]

use libfuzzer_sys::fuzz_target;
use rangegp_proto::scan::{ScanHeader, ScanPoint};
use rangegp_service::ingest::validate::{validate, ValidationLimits};

fuzz_target!(|data: &[u8]| {
    let header_len = std::mem::size_of::<ScanHeader>();
    let point_len = std::mem::size_of::<ScanPoint>();
    if data.len() < header_len {
        return;
    }
    // SAFETY: ScanHeader and ScanPoint are repr(C) plain data of integers and floats, for which
    // every bit pattern is a valid value; read_unaligned copes with any alignment.
    let header: ScanHeader = unsafe { std::ptr::read_unaligned(data.as_ptr().cast()) };
    let points: Vec<ScanPoint> = data[header_len..]
        .chunks_exact(point_len)
        .map(|c| unsafe { std::ptr::read_unaligned(c.as_ptr().cast()) })
        .collect();
    let limits = ValidationLimits {
        max_points: 4096,
        max_future_ns: 1_000_000_000,
    };
    if let Ok(scan) = validate(&header, &points, &limits, u64::MAX / 2) {
        assert!(!scan.rays.is_empty());
        for r in &scan.rays {
            assert!(r.range.is_finite() && r.range > 0.0 && r.range < scan.max_range_m);
        }
    }
});
