//! Every configuration value checked against its domain before the daemon uses it.

use super::{Config, ConfigError};
use crate::gp::KernelFamily;
use rangegp_proto::keys::MapKeys;
use rangegp_transport::zenoh_config;

/// Most returns a scan may carry: four times an OS1-128's 262 144 (each costs shared memory
/// and an ingest copy up front).
const MAX_POINTS: usize = 1 << 22;
/// Longest ingest or aggregate queue, scans: a queue is memory held, not throughput.
const MAX_QUEUE_LEN: usize = 4096;
/// Most window maps (each holds its scan's factors: some MB).
const MAX_WINDOW: usize = 256;
/// Largest batch a query may carry, items or grid cells (its reply is held in memory whole).
const MAX_BATCH: usize = 1 << 22;
/// Most query threads (each one a thread started at once).
const MAX_QUERY_THREADS: usize = 64;
/// Most departed tiles a robot may hold for its site (about 3 KiB each: 3 GiB at most).
const MAX_HELD_DEPARTED: u64 = 1 << 20;
/// Most robots a site may hold.
const MAX_SITE_ROBOTS: u64 = 1 << 16;
/// Most tiles a site may hold over all robots (at 3 KiB each, 48 GiB: beyond any machine it runs on).
const MAX_SITE_TILES: u64 = 1 << 24;

impl Config {
    /// Checks every value's domain; the error names the first field out of it.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        let ordered = |b: [f64; 2]| b[0] > 0.0 && b[1] > b[0] && b[1].is_finite();
        let (g, o, i, q, a) = (
            &self.gp,
            &self.gp.online,
            &self.ingest,
            &self.query,
            &self.aggregate,
        );
        let alpha_ok = match g.kernel {
            KernelFamily::RationalQuadratic { alpha } => positive(alpha),
            _ => true,
        };
        let service_ok =
            i.service_name.is_empty() || iceoryx2::prelude::ServiceName::new(&i.service_name).is_ok();
        let listen_ok =
            self.metrics.listen.is_empty() || self.metrics.listen.parse::<std::net::SocketAddr>().is_ok();
        let checks: [(bool, &'static str, &str); 45] = [
            (
                MapKeys::new(&self.map_id).is_ok(),
                "map_id",
                "must be a non-empty key-expression chunk (no '/', '*', '$', '?', '#')",
            ),
            (
                self.fleet.site.is_empty() || MapKeys::new(&self.fleet.site).is_ok(),
                "fleet.site",
                "must be empty (no fleet) or a key-expression chunk like map_id",
            ),
            (
                (10..=600_000).contains(&self.fleet.tile_period_ms),
                "fleet.tile_period_ms",
                "must be in 10..=600000",
            ),
            (
                self.fleet.max_kib_per_s > 0 && self.fleet.storage_wait_ms <= 600_000,
                "fleet.max_kib_per_s / fleet.storage_wait_ms",
                "must be positive / at most 600000",
            ),
            (
                (1..=MAX_HELD_DEPARTED).contains(&self.fleet.max_held_departed_tiles),
                "fleet.max_held_departed_tiles",
                "must be 1 to 1 048 576",
            ),
            (
                (1..=MAX_SITE_ROBOTS).contains(&self.fleet.max_site_robots)
                    && (1..=MAX_SITE_TILES).contains(&self.fleet.max_site_tiles),
                "fleet.max_site_robots / fleet.max_site_tiles",
                "must be 1 to 65 536 / 1 to 16 777 216",
            ),
            (
                service_ok,
                "ingest.service_name",
                "must be empty (the default) or a valid iceoryx2 service name",
            ),
            (
                (1..=MAX_POINTS).contains(&i.max_points),
                "ingest.max_points",
                "must be 1 to 4 194 304",
            ),
            (
                i.poll_interval_ms > 0,
                "ingest.poll_interval_ms",
                "must be positive",
            ),
            (
                i.cleanup_interval_s > 0,
                "ingest.cleanup_interval_s",
                "must be positive",
            ),
            (
                (1..=MAX_QUEUE_LEN).contains(&i.queue_len),
                "ingest.queue_len",
                "must be 1 to 4096",
            ),
            (
                i.sequence_restart_window > 0,
                "ingest.sequence_restart_window",
                "must be positive",
            ),
            (
                positive(i.map_bounds_m),
                "ingest.map_bounds_m",
                "must be a positive number of metres",
            ),
            (
                positive(i.max_speed_mps),
                "ingest.max_speed_mps",
                "must be positive",
            ),
            (
                non_negative(i.pose_slack_m),
                "ingest.pose_slack_m",
                "must be finite and non-negative",
            ),
            (
                i.pose_confirm_scans >= 2,
                "ingest.pose_confirm_scans",
                "must be at least 2",
            ),
            (
                i.max_retry_interval_ms > 0,
                "ingest.max_retry_interval_ms",
                "must be positive",
            ),
            (alpha_ok, "gp.kernel.alpha", "must be positive and finite"),
            (
                positive(g.kernel_variance),
                "gp.kernel_variance",
                "must be positive",
            ),
            (positive(g.length_scale), "gp.length_scale", "must be positive"),
            (
                (0.0..=10.0).contains(&g.view_disagreement),
                "gp.view_disagreement",
                "must be a weight in [0, 10]",
            ),
            (
                g.sphere_radius_m.is_none_or(positive),
                "gp.sphere_radius_m",
                "must be positive when set",
            ),
            (
                non_negative(g.nugget_m2),
                "gp.nugget_m2",
                "must be finite and non-negative",
            ),
            (
                g.max_training_rays > 0,
                "gp.max_training_rays",
                "must be positive",
            ),
            (
                (8..=4096).contains(&g.max_rays_per_tile),
                "gp.max_rays_per_tile",
                "must be in 8..=4096",
            ),
            (
                (0.01..=0.45).contains(&g.tile_overlap),
                "gp.tile_overlap",
                "must be in [0.01, 0.45]",
            ),
            (
                positive(g.sensor_height_m),
                "gp.sensor_height_m",
                "must be positive",
            ),
            (
                positive(g.constant_range_m),
                "gp.constant_range_m",
                "must be positive",
            ),
            (o.iterations > 0, "gp.online.iterations", "must be at least 1"),
            (
                o.smoothing > 0.0 && o.smoothing <= 1.0,
                "gp.online.smoothing",
                "must be in (0, 1]",
            ),
            (o.subset_rays >= 8, "gp.online.subset_rays", "must be at least 8"),
            (
                ordered(o.variance_bounds),
                "gp.online.variance_bounds",
                "must be [min, max] with 0 < min < max",
            ),
            (
                ordered(o.length_scale_bounds),
                "gp.online.length_scale_bounds",
                "must be [min, max] with 0 < min < max",
            ),
            (
                (1..=MAX_WINDOW).contains(&self.window.capacity),
                "window.capacity",
                "must be 1 to 256",
            ),
            (
                (1..=MAX_QUEUE_LEN).contains(&a.queue_len),
                "aggregate.queue_len",
                "must be 1 to 4096",
            ),
            (
                a.cpu_share > 0.0 && a.cpu_share <= 1.0,
                "aggregate.cpu_share",
                "must be in (0, 1]",
            ),
            (
                (1..=65_536).contains(&a.ledger_mib),
                "aggregate.ledger_mib",
                "must be 1 to 65536",
            ),
            (
                positive(a.radius_m),
                "aggregate.radius_m",
                "must be a positive number of metres",
            ),
            (
                matches!(self.zenoh.mode.as_str(), "peer" | "client" | "router"),
                "zenoh.mode",
                "must be peer, client or router",
            ),
            (
                (1..=MAX_BATCH).contains(&q.max_batch),
                "query.max_batch",
                "must be 1 to 4 194 304",
            ),
            (
                (1..=MAX_QUERY_THREADS).contains(&q.threads),
                "query.threads",
                "must be 1 to 64",
            ),
            (
                positive(q.max_ray_range_m),
                "query.max_ray_range_m",
                "must be a positive number of metres",
            ),
            (
                q.queue_deadline_ms > 0,
                "query.queue_deadline_ms",
                "must be positive",
            ),
            (
                positive(q.max_sigma_m),
                "query.max_sigma_m",
                "must be a positive number of metres",
            ),
            (
                listen_ok,
                "metrics.listen",
                "must be host:port with an IP host, or empty to disable",
            ),
        ];
        let invalid = |field: &'static str, reason: &str| ConfigError::Invalid {
            field,
            reason: reason.to_owned(),
        };
        if let Some((_, field, reason)) = checks.iter().find(|(ok, _, _)| !ok) {
            return Err(invalid(field, reason));
        }
        if let Some(reason) = self.layers.robot().problem() {
            return Err(invalid("layers", reason));
        }
        if !self.fleet.site.is_empty() && !self.aggregate.enabled {
            return Err(invalid(
                "fleet.site",
                "needs aggregate.enabled: the tiles a robot publishes are its aggregate's",
            ));
        }
        if self.checkpoint.interval_ms == 0 {
            return Err(invalid("checkpoint.interval_ms", "must be positive"));
        }
        if self.checkpoint.keep < 2 {
            return Err(invalid("checkpoint.keep", "must be at least 2"));
        }
        // The endpoints are checked by building the session configuration they describe.
        if self.zenoh.config_file.is_none() {
            zenoh_config(
                &self.zenoh.mode,
                &self.zenoh.listen,
                &self.zenoh.connect,
                self.zenoh.multicast_scouting,
            )
            .map_err(|e| ConfigError::Invalid {
                field: "zenoh.listen / zenoh.connect",
                reason: format!("are not valid endpoints ({})", e.source),
            })?;
        }
        Ok(())
    }
}
