//! A Zenoh router with the storage manager in this process: the memory storage of a site's tiles
//! for tests and the fleet simulation. Production runs `zenohd` with the same plugin and a
//! persistent volume (docs/FLEET.md); the configuration below is the same JSON5 either way.

use anyhow::{Context, Result};
use rangegp_proto::fleet::site_tiles;
use rangegp_proto::keys::MapKeys;
use std::time::{Duration, Instant};
use zenoh::internal::plugins::RunningPlugin;
use zenoh::internal::runtime::{DynamicRuntime, Runtime, RuntimeBuilder};
use zenoh::Wait;
use zenoh_plugin_storage_manager::StoragesPlugin;
use zenoh_plugin_trait::Plugin;

/// A daemon configuration for a fleet on one machine: a Zenoh client of `router` (everything
/// goes through it, nothing listens), nothing on disk, no metrics port.
pub fn daemon_config(map_id: &str, router: &str) -> rangegp_service::config::Config {
    let mut c = rangegp_service::config::Config {
        map_id: map_id.into(),
        ..Default::default()
    };
    c.zenoh.mode = "client".into();
    c.zenoh.listen = Vec::new();
    c.zenoh.connect = vec![router.into()];
    c.checkpoint.enabled = false;
    c.metrics.listen = String::new();
    c
}

/// The plugin's name, and its key under `plugins` in the router's configuration.
const PLUGIN: &str = "storage_manager";

/// The router configuration: listen on `endpoint` only, no scouting, timestamps on (the
/// storage needs them), and one memory storage of `site`'s tiles.
pub fn router_config(endpoint: &str, site: &MapKeys) -> String {
    format!(
        r#"{{
  mode: "router",
  listen: {{ endpoints: ["{endpoint}"] }},
  scouting: {{ multicast: {{ enabled: false }}, gossip: {{ enabled: false }} }},
  timestamping: {{ enabled: {{ router: true, peer: true, client: true }} }},
  plugins: {{ {PLUGIN}: {{ storages: {{ tiles: {{ key_expr: "{key}", volume: {{ id: "memory" }} }} }} }} }}
}}"#,
        key = site_tiles(site)
    )
}

/// A running router with a storage of one site's tiles; dropped, it closes.
pub struct StorageRouter {
    runtime: Runtime,
    _plugin: RunningPlugin,
    session: zenoh::Session,
    tokio: tokio::runtime::Runtime,
    endpoint: String,
}

impl StorageRouter {
    /// Starts a router listening on `endpoint` (a loopback TCP endpoint) with a memory storage
    /// of `site`'s tiles, and waits (bounded by `timeout`) until the storage answers queries.
    pub fn start(endpoint: &str, site: &MapKeys, timeout: Duration) -> Result<Self> {
        let tokio = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .thread_name("rangegp-router")
            .build()
            .context("cannot start the router's tokio runtime")?;
        let config = zenoh::Config::from_json5(&router_config(endpoint, site))
            .map_err(|e| anyhow::anyhow!("router configuration: {e}"))?;
        let (runtime, plugin, session) = tokio.block_on(async {
            let mut runtime = RuntimeBuilder::new(config)
                .build()
                .await
                .map_err(|e| anyhow::anyhow!("cannot build the router: {e}"))?;
            let dynamic: DynamicRuntime = runtime.clone().into();
            let plugin = StoragesPlugin::start(PLUGIN, &dynamic)
                .map_err(|e| anyhow::anyhow!("cannot start the storage manager: {e}"))?;
            runtime
                .start()
                .await
                .map_err(|e| anyhow::anyhow!("cannot listen on {endpoint}: {e}"))?;
            let session = zenoh::session::init(dynamic)
                .await
                .map_err(|e| anyhow::anyhow!("cannot open the router's session: {e}"))?;
            anyhow::Ok((runtime, plugin, session))
        })?;
        let router = Self {
            runtime,
            _plugin: plugin,
            session,
            tokio,
            endpoint: endpoint.to_owned(),
        };
        router.wait_for_storage(site, timeout)?;
        Ok(router)
    }

    /// The endpoint robots and sites connect to.
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// A session inside the router (to read the storage directly).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// Waits until the storage's queryable is declared (it starts in a task of its own).
    fn wait_for_storage(&self, site: &MapKeys, timeout: Duration) -> Result<()> {
        let querier = self
            .session
            .declare_querier(site_tiles(site))
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot declare a querier: {e}"))?;
        let deadline = Instant::now() + timeout;
        while !querier.matching_status().wait().is_ok_and(|m| m.matching()) {
            anyhow::ensure!(
                Instant::now() < deadline,
                "the storage did not start within {timeout:?}"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(())
    }

    /// Every tile the storage holds: key and bytes.
    pub fn stored(&self, site: &MapKeys, timeout: Duration) -> Result<Vec<(String, Vec<u8>)>> {
        let replies = self
            .session
            .get(site_tiles(site))
            .timeout(timeout)
            .wait()
            .map_err(|e| anyhow::anyhow!("cannot query the storage: {e}"))?;
        Ok(rangegp_service::fleet::assemble::arrivals(&replies))
    }
}

impl Drop for StorageRouter {
    fn drop(&mut self) {
        let (runtime, session) = (self.runtime.clone(), self.session.clone());
        self.tokio.block_on(async move {
            let _ = session.close().await;
            let _ = runtime.close().await;
        });
    }
}

/// A site daemon's fleet state as a table (`rangegp status --site`): the storage, the site map,
/// then one row per robot with its tiles, cells, the age of its newest scan at `now_ns` and
/// whether its daemon is alive.
pub fn site_table(status: &rangegp_proto::msg::StatusReply, now_ns: u64) -> String {
    use std::fmt::Write;
    let f = &status.fleet;
    let mut out = String::new();
    let _ = writeln!(
        out,
        "map {} (role {:?}, site {})",
        status.map_id,
        f.role,
        f.site.as_deref().unwrap_or("none")
    );
    let _ = writeln!(
        out,
        "storage: {}; {} tiles recovered at start, {} received live, {} refused, {} dropped",
        if f.storage_answered {
            "answered"
        } else {
            "did not answer"
        },
        f.tiles_from_storage,
        f.tiles_received,
        f.tiles_refused,
        f.tiles_dropped
    );
    let _ = writeln!(
        out,
        "site map: {} cells in {} tiles",
        status.aggregate.cells, status.aggregate.tiles
    );
    let _ = writeln!(
        out,
        "{:<32} {:>6} {:>8} {:>10} {:>20}",
        "robot", "alive", "tiles", "cells", "newest scan (s ago)"
    );
    for r in &f.robots {
        let age = now_ns.saturating_sub(r.newest_scan_ns) as f64 * 1e-9;
        let _ = writeln!(
            out,
            "{:<32} {:>6} {:>8} {:>10} {:>20.1}",
            r.robot,
            if r.alive { "yes" } else { "no" },
            r.tiles,
            r.cells,
            age
        );
    }
    out
}
