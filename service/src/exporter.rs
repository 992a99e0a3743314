//! The metrics exporter: Prometheus text exposition of [`crate::metrics::Metrics`] on a loopback HTTP port (`GET /metrics`).
//!
//! Counters are read from the daemon's own atomics and sizes from the current snapshot at scrape
//! time (the same sources as `status`, no second bookkeeping); latencies are the histograms kept beside the status rings.
//! `prometheus-client` (the Prometheus project's Rust client) does the encoding; `tiny_http`
//! serves it from one small thread, independent of the async runtime and of the query workers.

use crate::map::aggregate::Aggregate;
use crate::metrics::{rss_mb, Latency, PublisherCounts};
use crate::scan::RejectReason;
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use prometheus_client::collector::Collector;
use prometheus_client::encoding::{DescriptorEncoder, EncodeMetric};
use prometheus_client::metrics::counter::ConstCounter;
use prometheus_client::metrics::gauge::ConstGauge;
use prometheus_client::metrics::MetricType;
use prometheus_client::registry::Registry;
use rangegp_proto::keys::QueryKind;
use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use thiserror::Error;
use tracing::{info, warn};

/// The exporter could not start.
#[derive(Debug, Error)]
pub enum ExporterError {
    /// The listen address could not be bound (in use, not local, malformed).
    #[error("cannot listen for metrics on {addr}")]
    Bind {
        /// Address asked for.
        addr: String,
        /// Cause (tiny_http's).
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The listen address is not an IP address (a Unix socket path, say).
    #[error("cannot listen for metrics on {0}: not an IP address")]
    NotIp(String),
    /// The serving thread could not be spawned.
    #[error("cannot spawn the metrics thread: {0}")]
    Spawn(#[from] std::io::Error),
}

/// A running exporter; dropping it stops the thread.
pub struct Exporter {
    server: Arc<tiny_http::Server>,
    addr: SocketAddr,
    stop: Shutdown,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for Exporter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Exporter").field("addr", &self.addr).finish()
    }
}

impl Exporter {
    /// Serves the daemon's metrics (counters, and sizes read off the current snapshot) at
    /// `http://<listen>/metrics` (port 0 picks a free port).
    pub fn start(listen: &str, state: Arc<DaemonState>) -> Result<Self, ExporterError> {
        let server = tiny_http::Server::http(listen).map_err(|source| ExporterError::Bind {
            addr: listen.to_owned(),
            source,
        })?;
        let addr = server
            .server_addr()
            .to_ip()
            .ok_or_else(|| ExporterError::NotIp(listen.to_owned()))?;
        let server = Arc::new(server);
        let mut registry = Registry::with_prefix("rangegp");
        registry.register_collector(Box::new(DaemonCollector(state)));
        let stop = Shutdown::new();
        let thread = {
            let (server, stop) = (Arc::clone(&server), stop.clone());
            std::thread::Builder::new()
                .name("rangegp-metrics".into())
                .spawn(move || serve(&server, &registry, &stop))?
        };
        info!(%addr, "prometheus metrics at http://{addr}/metrics");
        Ok(Self {
            server,
            addr,
            stop,
            thread: Some(thread),
        })
    }

    /// The bound address (useful with port 0).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for Exporter {
    fn drop(&mut self) {
        self.stop.trigger();
        self.server.unblock();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn serve(server: &tiny_http::Server, registry: &Registry, stop: &Shutdown) {
    while !stop.is_triggered() {
        let request = match server.recv_timeout(Duration::from_millis(200)) {
            Ok(Some(r)) => r,
            Ok(None) => continue,
            Err(e) => {
                warn!(error = %e, "metrics listener failed");
                return;
            }
        };
        let path = request.url().split('?').next().unwrap_or("");
        let response = if path == "/metrics" {
            let mut body = String::new();
            match prometheus_client::encoding::text::encode(&mut body, registry) {
                Ok(()) => match tiny_http::Header::from_bytes("Content-Type", CONTENT_TYPE) {
                    Ok(h) => tiny_http::Response::from_string(body).with_header(h),
                    Err(()) => tiny_http::Response::from_string(body),
                },
                Err(_) => tiny_http::Response::from_string("encoding failed").with_status_code(500),
            }
        } else {
            tiny_http::Response::from_string("see /metrics").with_status_code(404)
        };
        if let Err(e) = request.respond(response) {
            warn!(error = %e, "metrics response failed");
        }
    }
}

/// OpenMetrics text, what `prometheus_client::encoding::text` writes.
const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Encodes the daemon's metrics on each scrape.
#[derive(Debug)]
struct DaemonCollector(Arc<DaemonState>);

fn counter(enc: &mut DescriptorEncoder, name: &str, help: &str, value: u64) -> std::fmt::Result {
    let c = ConstCounter::new(value);
    c.encode(enc.encode_descriptor(name, help, None, c.metric_type())?)
}

fn gauge(enc: &mut DescriptorEncoder, name: &str, help: &str, value: f64) -> std::fmt::Result {
    let g = ConstGauge::new(value);
    g.encode(enc.encode_descriptor(name, help, None, g.metric_type())?)
}

fn histogram(enc: &mut DescriptorEncoder, name: &str, help: &str, latency: &Latency) -> std::fmt::Result {
    let h = latency.histogram();
    h.encode(enc.encode_descriptor(name, help, None, h.metric_type())?)
}

impl Collector for DaemonCollector {
    fn encode(&self, mut enc: DescriptorEncoder) -> std::fmt::Result {
        let m = &self.0.metrics;
        let snap = self.0.snapshot.load();
        let (cells, tiles) = snap.aggregate.as_ref().map_or((0, 0), |a| (a.len(), a.tiles()));
        let e = &mut enc;
        counter(
            e,
            "scans_received",
            "Scans taken from shared memory",
            m.received.load(Relaxed),
        )?;
        counter(
            e,
            "scans_accepted",
            "Scans fitted into the window",
            m.accepted.load(Relaxed),
        )?;
        counter(
            e,
            "scans_skipped",
            "Valid scans skipped: fitting fell behind",
            m.skipped.load(Relaxed),
        )?;
        counter(
            e,
            "sequence_gaps",
            "Missing sequence numbers",
            m.sequence_gaps.load(Relaxed),
        )?;
        {
            let mut family = e.encode_descriptor(
                "scans_rejected",
                "Scans rejected, by reason",
                None,
                MetricType::Counter,
            )?;
            for &r in RejectReason::ALL.iter() {
                ConstCounter::new(m.rejected(r)).encode(family.encode_family(&[("reason", r.as_str())])?)?;
            }
        }
        let publishers = m.publishers();
        for (name, help, value) in [
            (
                "publisher_scans",
                "Valid scans by publisher id",
                (|c: &PublisherCounts| c.scans) as fn(&PublisherCounts) -> u64,
            ),
            (
                "publisher_sequence_gaps",
                "Missing sequence numbers by publisher id",
                |c: &PublisherCounts| c.gaps,
            ),
        ] {
            let mut family = e.encode_descriptor(name, help, None, MetricType::Counter)?;
            for (id, counts) in &publishers {
                let id = id.to_string();
                ConstCounter::new(value(counts))
                    .encode(family.encode_family(&[("publisher", id.as_str())])?)?;
            }
        }
        counter(e, "queries_ok", "Queries answered", m.queries_ok.load(Relaxed))?;
        counter(
            e,
            "queries_failed",
            "Queries answered with an error",
            m.queries_failed.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_inserts",
            "Scans folded into the aggregate",
            m.aggregate_inserts.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_skipped",
            "Fitted scans the aggregate passed over",
            m.aggregate_skipped.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_failed",
            "Failed aggregate inserts",
            m.aggregate_failed.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_evicted_tiles",
            "Aggregate tiles evicted beyond the radius",
            m.aggregate_evicted_tiles.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_paged_out",
            "Tiles written to the site map",
            m.aggregate_paged_out.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_paged_in",
            "Tiles read back from the site map",
            m.aggregate_paged_in.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_page_failures",
            "Tile pages not written or not read",
            m.aggregate_page_failures.load(Relaxed),
        )?;
        counter(
            e,
            "pose_corrections",
            "Pose corrections applied",
            m.corrections.load(Relaxed),
        )?;
        counter(
            e,
            "aggregate_changed_cells",
            "Aggregate cells replaced by disagreeing scans",
            m.changed_cells.load(Relaxed),
        )?;
        gauge(
            e,
            "aggregate_ledger_scans",
            "Fused scans a pose correction can move",
            m.ledger_scans.load(Relaxed) as f64,
        )?;
        gauge(
            e,
            "aggregate_ledger_bytes",
            "Memory the ledger of fused scans holds",
            m.ledger_bytes.load(Relaxed) as f64,
        )?;
        gauge(
            e,
            "aggregate_reach_meters",
            "Reach each scan is fused out to now",
            m.aggregate_reach_mm.load(Relaxed) as f64 * 1e-3,
        )?;
        counter(
            e,
            "checkpoints_written",
            "Aggregate checkpoints written",
            m.checkpoints_written.load(Relaxed),
        )?;
        counter(
            e,
            "checkpoint_failures",
            "Checkpoint writes that failed",
            m.checkpoint_failures.load(Relaxed),
        )?;
        counter(
            e,
            "checkpoints_rejected",
            "Checkpoint files rejected at start",
            m.checkpoints_rejected.load(Relaxed),
        )?;
        gauge(
            e,
            "window_maps",
            "Local maps in the window",
            snap.maps().len() as f64,
        )?;
        gauge(e, "aggregate_cells", "Fused aggregate cells", cells as f64)?;
        gauge(e, "aggregate_tiles", "Fitted aggregate tiles", tiles as f64)?;
        gauge(e, "uptime_seconds", "Seconds since start", m.uptime_s())?;
        if let Some(mb) = rss_mb() {
            gauge(
                e,
                "resident_memory_bytes",
                "Resident set size",
                mb * 1024.0 * 1024.0,
            )?;
        }
        histogram(e, "fit_seconds", "Fit of one scan", &m.fit)?;
        histogram(
            e,
            "scan_to_queryable_seconds",
            "Scan taken from shared memory to its map answering queries",
            &m.scan_to_queryable,
        )?;
        histogram(
            e,
            "calibrate_seconds",
            "One scan's test of the maps before it (prequential σ calibration)",
            &m.calibrate,
        )?;
        histogram(
            e,
            "aggregate_insert_seconds",
            "One aggregate insert",
            &m.aggregate_insert,
        )?;
        histogram(
            e,
            "checkpoint_write_seconds",
            "One checkpoint write",
            &m.checkpoint_write,
        )?;
        let mut family = e.encode_descriptor(
            "query_seconds",
            "Query handling by kind",
            None,
            MetricType::Histogram,
        )?;
        let kinds = QueryKind::ALL.iter().map(|&k| (Some(k), k.as_str()));
        for (kind, name) in kinds.chain([(None, "status")]) {
            m.query(kind)
                .histogram()
                .encode(family.encode_family(&[("kind", name)])?)?;
        }
        Ok(())
    }
}
