//! Grid queries over the real transports: layers larger than one Zenoh batch (64 KiB) arrive
//! whole, agree with single-point elevation queries and with the ground truth, and bad boxes get
//! their error codes.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::msg::{ErrorCode, Source};
use rangegp_tests::{error_code, rms, world, Harness};

#[test]
fn a_grid_larger_than_64_kib_matches_point_queries_and_the_ground_truth() -> anyhow::Result<()> {
    let h = Harness::start(|_| {})?;
    let mut publisher = h.publisher(4)?;
    let mut w = world(7, 4);
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for i in 0..4 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
        let s = scan.pose.translation.vector;
        for k in 0..2 {
            lo[k] = lo[k].min(s[k] - 10.0);
            hi[k] = hi[k].max(s[k] + 10.0);
        }
    }
    // The maps stop changing (the aggregate fused all four): grid and points read one snapshot.
    h.wait_status("4 scans in window and aggregate", |s| {
        s.scans_accepted == 4 && s.aggregate.inserts == 4
    })?;

    let rep = h.client.grid(lo, hi, 0.15)?;
    let cells = rep.cols as usize * rep.rows as usize;
    let bytes = codec::encode(Encoding::Bincode, &rep)?.len();
    assert!(
        bytes > 64 * 1024,
        "reply of {bytes} bytes does not exercise fragmentation"
    );
    assert_eq!(rep.elevation_m.len(), cells);

    let mut errors = Vec::new();
    for (k, (z, var)) in rep.elevation_m.iter().zip(&rep.variance_m2).enumerate() {
        let (Some(z), Some(var)) = (z, var) else {
            assert!(
                z.is_none() && var.is_none(),
                "cell {k}: one layer without the other"
            );
            continue;
        };
        assert!(*var > 0.0, "cell {k}: σ must be positive");
        let [x, y] = rep.centre(k as u32 % rep.cols, k as u32 / rep.cols);
        errors.push(*z as f64 - w.terrain.height(x, y).expect("on the map"));
    }
    assert!(
        errors.len() > cells / 10 && errors.len() < cells,
        "{} of {cells} cells observed",
        errors.len()
    );
    let e = rms(&errors);
    assert!(e < 0.05, "grid elevation RMSE {e} over {} cells", errors.len());

    // Every 997th cell against a single-point query at its centre.
    let picks: Vec<usize> = (0..cells).step_by(997).collect();
    let points: Vec<[f64; 2]> = picks
        .iter()
        .map(|&k| rep.centre(k as u32 % rep.cols, k as u32 / rep.cols))
        .collect();
    for (item, &k) in h.client.elevation(&points)?.iter().zip(&picks) {
        assert_eq!(item.z_m.map(|z| z as f32), rep.elevation_m[k], "cell {k}");
        assert_eq!(item.source == Source::None, rep.elevation_m[k].is_none());
    }
    Ok(())
}

/// A planner speaking JSON (Python) gets exactly the point answer at every cell centre: floats
/// cross JSON without rounding (serde_json's `float_roundtrip`), so the centre it computes from
/// the reply is the point the daemon evaluated.
#[test]
fn a_json_grid_equals_point_queries_at_every_cell_centre() -> anyhow::Result<()> {
    let h = Harness::start(|c| {
        c.aggregate.queue_len = 8;
    })?;
    let mut publisher = h.publisher(6)?;
    let mut w = world(9, 4);
    for i in 0..4 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
    }
    // The maps stop changing: the grid and the point queries read the same snapshot.
    h.wait_status("4 scans in window and aggregate", |s| {
        s.scans_accepted == 4 && s.aggregate.inserts == 4
    })?;
    let json = rangegp_client::Client::builder(&h.config.map_id)
        .connect([h.endpoint.clone()])
        .encoding(Encoding::Json)
        .timeout(rangegp_tests::WAIT)
        .open()?;
    // An origin and a resolution with long decimal expansions.
    let rep = json.grid([0.1 / 3.0, -4.0 / 7.0], [9.1, 4.3], 0.07)?;
    let cells = rep.cols as usize * rep.rows as usize;
    let points: Vec<[f64; 2]> = (0..cells)
        .map(|k| rep.centre(k as u32 % rep.cols, k as u32 / rep.cols))
        .collect();
    let items = json.elevation(&points)?;
    let observed = items.iter().filter(|i| i.z_m.is_some()).count();
    assert!(observed > cells / 10, "{observed} of {cells} cells observed");
    for (k, item) in items.iter().enumerate() {
        assert_eq!(
            item.z_m.map(|z| z as f32),
            rep.elevation_m[k],
            "cell {k} at {:?}",
            points[k]
        );
        assert_eq!(item.z_var_m2.map(|v| v as f32), rep.variance_m2[k], "cell {k}");
    }
    Ok(())
}

#[test]
fn bad_and_oversized_boxes_are_refused_with_their_codes() -> anyhow::Result<()> {
    let h = Harness::start(|c| c.query.max_batch = 1000)?;
    let mut publisher = h.publisher(5)?;
    let scan = world(8, 1).scan(0, now_ns());
    publisher.publish(scan.header, &scan.points)?;
    h.wait_status("scan", |s| s.scans_accepted == 1)?;
    let c = &h.client;
    assert_eq!(
        error_code(c.grid([0.0, 0.0], [10.0, 10.0], 0.1).expect_err("10 000 cells")),
        ErrorCode::BatchTooLarge
    );
    assert_eq!(
        error_code(c.grid([5.0, 0.0], [0.0, 10.0], 0.5).expect_err("inverted")),
        ErrorCode::InvalidArgument
    );
    assert_eq!(
        error_code(c.grid([0.0, 0.0], [10.0, 10.0], f64::NAN).expect_err("nan")),
        ErrorCode::InvalidArgument
    );
    let ok = c.grid([0.0, 0.0], [10.0, 10.0], 0.5)?;
    assert_eq!((ok.cols, ok.rows), (20, 20));
    Ok(())
}
