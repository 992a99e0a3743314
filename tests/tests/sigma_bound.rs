//! The σ bound over the real transports: with `query.max_sigma_m` set below what the maps can
//! claim, elevation and variance answers come back refused `too_uncertain` (observed, no value),
//! never as a number; ground no map saw is refused `unobserved`.

use rangegp_lab::scangen::now_ns;
use rangegp_proto::msg::{Provenance, Refusal, Source};
use rangegp_tests::{world, Harness};

#[test]
fn answers_wider_than_the_bound_are_refused_with_their_reason() -> anyhow::Result<()> {
    // 0.5 mm: near the sensor the maps claim less, farther out more.
    let bound = 5e-4;
    // Nothing changes the answers between the two queries below: no aggregate inserts, no σ
    // scales learnt after the last scan was announced.
    let h = Harness::start(|c| {
        c.query.max_sigma_m = bound;
        c.aggregate.enabled = false;
        c.gp.prequential_calibration = false;
    })?;
    let mut publisher = h.publisher(9)?;
    let mut w = world(3, 2);
    let mut last = None;
    for i in 0..2 {
        let scan = w.scan(i, now_ns());
        h.publish_fitted(&mut publisher, &scan)?;
        last = Some(scan.pose);
    }
    h.wait_status("2 accepted scans", |s| s.scans_accepted == 2)?;
    let pose = last.expect("two scans");
    // A fan of points 0.5–9 m ahead of the last sensor, and one 500 m away.
    let mut points: Vec<[f64; 2]> = (0..60)
        .map(|k| {
            let (r, a) = (0.5 + 8.5 * (k % 20) as f64 / 20.0, -1.0 + (k / 20) as f64);
            let p = pose * nalgebra::Point3::new(r * f64::cos(a), r * f64::sin(a), 0.0);
            [p.x, p.y]
        })
        .collect();
    let s = pose.translation.vector;
    points.push([s.x + 500.0, s.y]);

    let items = h.client.elevation(&points)?;
    let (mut given, mut too_uncertain) = (0, 0);
    for item in &items[..60] {
        match (item.z_var_m2, item.refusal) {
            (Some(var), None) => {
                assert!(var.sqrt() <= bound, "σ {} above the bound {bound}", var.sqrt());
                assert!(item.z_m.is_some() && item.source != Source::None);
                given += 1;
            }
            (None, Some(Refusal::TooUncertain)) => {
                assert!(item.z_m.is_none() && item.source == Source::None);
                assert_eq!(item.provenance, Provenance::None);
                too_uncertain += 1;
            }
            (None, Some(Refusal::Unobserved)) => assert_eq!(item.provenance, Provenance::None),
            other => panic!("inconsistent item {item:?} ({other:?})"),
        }
    }
    assert!(
        too_uncertain > 0,
        "no answer exceeded a 0.5 mm bound ({given} given)"
    );
    let far = &items[60];
    assert_eq!(
        (far.refusal, far.provenance, far.z_m),
        (Some(Refusal::Unobserved), Provenance::None, None)
    );

    // Variance answers refuse the same points for the same reason.
    let variances = h.client.variance(&points)?;
    for (e, v) in items.iter().zip(&variances) {
        assert_eq!(e.refusal, v.refusal);
        assert_eq!(e.z_var_m2, v.z_var_m2);
    }
    Ok(())
}
