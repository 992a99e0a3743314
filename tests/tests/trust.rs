//! Processes of the daemon's own user can take the scan service's subscriber slots or create
//! the service first with other settings. The daemon must not exit (under `Restart=on-failure`
//! that is a crash loop): it serves queries, says in `status` why it cannot subscribe, retries
//! with back-off, and takes scans as soon as the way is free.

use anyhow::Result;
use iceoryx2::prelude::*;
use rangegp_lab::scangen::now_ns;
use rangegp_proto::scan::{open_scan_service, ScanHeader, ScanPoint, SCAN_SERVICE_MAX_SUBSCRIBERS};
use rangegp_tests::{world, Harness};

fn node() -> Result<Node<ipc::Service>> {
    Ok(NodeBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()?)
}

/// Starts a daemon on `service`, checks that it waits, lets `free` clear the way, and checks that
/// a scan is then taken.
fn waits_then_maps(service: &str, free: impl FnOnce()) -> Result<()> {
    let h = Harness::start(|c| {
        c.ingest.service_name = service.to_owned();
        c.ingest.max_retry_interval_ms = 100;
    })?;
    let s = h.wait_status("a failed attempt to subscribe", |s| s.ingest.retries >= 2)?;
    assert!(!s.ingest.connected, "{:?}", s.ingest);
    let why = s.ingest.error.clone().unwrap_or_default();
    assert!(why.contains("scan"), "a reason a person can act on: {why}");
    free();
    h.wait_status("the subscriber", |s| s.ingest.connected)?;
    let mut publisher = h.publisher(1)?;
    let scan = world(1, 1).scan(0, now_ns());
    publisher.publish(scan.header, &scan.points)?;
    let s = h.wait_status("the scan mapped", |s| s.scans_accepted == 1)?;
    assert!(s.ingest.error.is_none());
    Ok(())
}

#[test]
fn a_service_created_first_with_other_settings_is_waited_out() -> Result<()> {
    let service = format!("rangegp/{}/scans", rangegp_tests::unique_id("squat"));
    let squatter = node()?;
    let taken = squatter
        .service_builder(&ServiceName::new(&service)?)
        .publish_subscribe::<[ScanPoint]>()
        .user_header::<ScanHeader>()
        .max_subscribers(1)
        .create()?;
    waits_then_maps(&service, move || {
        drop(taken);
        drop(squatter);
    })
}

#[test]
fn taken_subscriber_slots_are_waited_out() -> Result<()> {
    let service = format!("rangegp/{}/scans", rangegp_tests::unique_id("slots"));
    let squatter = node()?;
    let scans = open_scan_service(&squatter, &ServiceName::new(&service)?)?;
    let mut slots = Vec::new();
    for _ in 0..SCAN_SERVICE_MAX_SUBSCRIBERS {
        slots.push(scans.subscriber_builder().create()?);
    }
    waits_then_maps(&service, move || {
        slots.pop();
    })
}
