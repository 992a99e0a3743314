//! Bad requests get a `reply_err` with the right code, in the request's encoding.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::keys::QueryKind;
use rangegp_proto::msg::{
    Camera, ElevationReply, ElevationRequest, ErrorCode, PoseCorrection, Ray, Rigid, RobotModel, ViewRequest,
};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_tests::{error_code, world, Harness};

#[test]
fn every_bad_request_has_its_code() -> anyhow::Result<()> {
    let h = Harness::start(|c| c.query.max_batch = 100)?;
    let c = &h.client;
    assert_eq!(
        error_code(c.elevation(&[[0.0, 0.0]]).expect_err("no map yet")),
        ErrorCode::NoMap
    );
    assert_eq!(c.status()?.queries_failed, 1);

    let mut publisher = h.publisher(2)?;
    let mut w = world(2, 1);
    let scan = w.scan(0, now_ns());
    publisher.publish(scan.header, &scan.points)?;
    h.wait_status("scan", |s| s.scans_accepted == 1)?;

    assert_eq!(
        error_code(c.elevation(&vec![[0.0, 0.0]; 101]).expect_err("too big")),
        ErrorCode::BatchTooLarge
    );
    assert_eq!(
        error_code(c.elevation(&[[f64::NAN, 0.0]]).expect_err("nan")),
        ErrorCode::InvalidArgument
    );
    let zero_dir = Ray {
        origin_m: [0.0; 3],
        direction: [0.0; 3],
        max_range_m: 5.0,
    };
    assert_eq!(
        error_code(c.ray(&[zero_dir]).expect_err("zero direction")),
        ErrorCode::InvalidArgument
    );

    let key = c.keys().query(QueryKind::Elevation);
    for enc in [Encoding::Bincode, Encoding::Json] {
        let garbage = c
            .call_raw(&key, b"\xff\x00garbage".to_vec(), enc)?
            .expect_err("garbage");
        assert_eq!(garbage.code, ErrorCode::MalformedRequest, "{enc:?}");
        let future = ElevationRequest {
            version: 999,
            points: vec![[0.0, 0.0]],
        };
        let refused = c
            .call_raw(&key, codec::encode(enc, &future)?, enc)?
            .expect_err("version");
        assert_eq!(refused.code, ErrorCode::UnsupportedVersion, "{enc:?}");
    }
    // JSON in, JSON out: what a Python planner sends.
    let body = format!(r#"{{"version":{PROTOCOL_VERSION},"points":[[1.0,2.0]]}}"#).into_bytes();
    let reply = c
        .call_raw(&key, body.clone(), Encoding::Json)?
        .expect("json answer");
    let parsed: ElevationReply = serde_json::from_slice(&reply)?;
    assert_eq!(parsed.items.len(), 1);
    // JSON labelled bincode (or not labelled): a hint, not "version 123".
    let mislabelled = c
        .call_raw(&key, body, Encoding::Bincode)?
        .expect_err("mislabelled");
    assert_eq!(mislabelled.code, ErrorCode::MalformedRequest, "{mislabelled:?}");
    assert!(
        mislabelled.message.contains("application/json"),
        "{}",
        mislabelled.message
    );
    // An error never echoes a whole hostile value.
    let huge = format!(
        r#"{{"version":{PROTOCOL_VERSION},"points":"{}"}}"#,
        "x".repeat(1 << 20)
    );
    let refused = c
        .call_raw(&key, huge.into_bytes(), Encoding::Json)?
        .expect_err("a string for points");
    assert_eq!(refused.code, ErrorCode::MalformedRequest);
    assert!(
        refused.message.len() < 1024,
        "{} bytes of message",
        refused.message.len()
    );
    // Requests of a few bytes that ask for unbounded work: refused before any of it is done.
    let huge_view = ViewRequest {
        version: PROTOCOL_VERSION,
        position_m: [0.0, 0.0, 1.0],
        orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
        camera: Camera::Pinhole {
            width: 100_000,
            height: 100_000,
            hfov_rad: 1.0,
            max_range_m: 10.0,
        },
    };
    assert_eq!(
        error_code(c.view(&huge_view).expect_err("10¹⁰ pixels")),
        ErrorCode::BatchTooLarge
    );
    let identity = Rigid {
        translation_m: [0.0; 3],
        rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
    };
    let many = vec![
        PoseCorrection::Scan {
            publisher_id: 2,
            sequence: 0,
            pose: identity,
        };
        101
    ];
    assert_eq!(
        error_code(c.correct(&many).expect_err("101 corrections")),
        ErrorCode::BatchTooLarge
    );
    // A subnormal footprint once divided to a zero resolution and panicked a query thread.
    let speck = RobotModel {
        footprint_radius_m: 5e-324,
        max_slope_deg: 20.0,
        max_step_m: 0.2,
        lethal_risk: 0.5,
    };
    assert_eq!(
        error_code(c.slope(&[[1.0, 1.0]], Some(speck)).expect_err("radius")),
        ErrorCode::InvalidArgument
    );
    // The daemon counted every failure and still serves.
    let s = c.status()?;
    assert_eq!(s.queries_failed, 1 + 3 + 4 + 2 + 3);
    assert_eq!(c.slope(&[[1.0, 1.0]], None)?.items.len(), 1);
    Ok(())
}
