//! Fleets over real transports: a Zenoh router with a memory storage (in this process), three
//! robot daemons and a site daemon (child processes, Zenoh clients of the router on loopback,
//! scouting off). Robots drive three parallel lines 15 m apart over one cratered world; their
//! aggregate tiles go through the router into the storage and the site.
//!
//! - The site answers exactly (1e-9) what a site map built from the stored tiles answers, and a
//!   point only robot 2 saw exactly what robot 2's stored tiles alone answer.
//! - A fleet query (`rangegp/*`) hears every robot, and fuses by inverse variance.
//! - Robot 2 killed (SIGKILL): the site still answers its ground, and says it is not alive.
//! - The site killed and restarted: it answers the same values, from the storage alone.
//!
//! A second test keeps two robots off their site (nothing subscribes to its tiles) and checks
//! that departed tiles wait within `fleet.max_held_departed_tiles`.

use anyhow::{ensure, Context, Result};
use rangegp_client::{Client, ScanPublisher};
use rangegp_lab::fleet::{daemon_config, site_table, StorageRouter};
use rangegp_lab::scangen::now_ns;
use rangegp_proto::codec::{decode, Encoding};
use rangegp_proto::fleet::{parse_tile_key, tile_key, FleetRole, TileUpdate};
use rangegp_proto::keys::MapKeys;
use rangegp_proto::msg::Source;
use rangegp_service::config::Config;
use rangegp_service::daemon::Daemon;
use rangegp_service::fleet::site_map::{SiteLimits, SiteMap};
use rangegp_service::map::aggregate::world::WorldParams;
use rangegp_service::map::{query, MapSnapshot};
use rangegp_sim::path::Path;
use rangegp_tests::child::{self, ChildProcess};
use rangegp_tests::{unique_id, world, TempDir, WAIT};
use rangegp_transport::{reserve_loopback_endpoint, zenoh_config};
use std::sync::Arc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// Child role: a daemon running the configuration file named in its arguments until killed.
#[test]
#[ignore = "child process of the fleet test"]
fn child_daemon() -> Result<()> {
    let Some(path) = child::args() else { return Ok(()) };
    let config = Config::load(std::path::Path::new(&path))?;
    let _daemon = Daemon::builder(config).start()?;
    child::say("ready");
    loop {
        std::thread::sleep(Duration::from_secs(3600));
    }
}

/// Writes `config` to a file of its own and starts a child daemon on it (the file goes with its
/// directory once the child has read it, or failed to).
fn spawn_daemon(config: &Config) -> Result<ChildProcess> {
    let dir = TempDir::new("fleet")?;
    let path = dir.path().join("rangegpd.toml");
    std::fs::write(&path, toml::to_string(config)?)?;
    let mut child = ChildProcess::spawn("child_daemon", &path.display().to_string())?;
    child.expect("ready", WAIT)?;
    Ok(child)
}

fn client(map_id: &str, router: &str) -> Result<Client> {
    let client = Client::builder(map_id).connect([router]).timeout(WAIT).open()?;
    client.wait_for_daemon(WAIT)?;
    Ok(client)
}

/// Polls `probe` until it returns `Some` (bounded by [`WAIT`]).
fn wait_for<T>(what: &str, mut probe: impl FnMut() -> Result<Option<T>>) -> Result<T> {
    let deadline = Instant::now() + WAIT;
    loop {
        if let Some(v) = probe()? {
            return Ok(v);
        }
        ensure!(Instant::now() < deadline, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The stored tiles, decoded (keys checked).
fn stored(router: &StorageRouter, site: &MapKeys) -> Result<Vec<TileUpdate>> {
    router
        .stored(site, WAIT)?
        .into_iter()
        .map(|(key, bytes)| {
            let update: TileUpdate = decode(Encoding::Bincode, &bytes)?;
            ensure!(
                parse_tile_key(site, &key)
                    == Some((update.robot.clone(), (update.tile_column, update.tile_row))),
                "stored tile {key} names another robot or tile"
            );
            Ok(update)
        })
        .collect()
}

/// What a site map of `tiles` answers at `points` (z, variance), through the daemon's query code.
fn expected(tiles: Vec<TileUpdate>, points: &[[f64; 2]]) -> Result<Vec<Option<(f64, f64)>>> {
    let mut site = SiteMap::new(
        WorldParams::default(),
        SiteLimits {
            robots: usize::MAX,
            tiles: usize::MAX,
        },
    );
    let refused = site.offer(tiles).map_err(|(e, _)| e)?;
    ensure!(refused.is_empty(), "stored tiles refused: {refused:?}");
    let snapshot = MapSnapshot::new(Vec::new(), Some(Arc::new(site.world().clone())))
        .with_max_sigma(Config::default().query.max_sigma_m);
    Ok(points
        .iter()
        .map(|p| {
            let e = query::elevation(&snapshot, p[0], p[1]);
            e.z_m.zip(e.z_var_m2)
        })
        .collect())
}

/// The site's answers at `points` equal `want` to 1e-9 (value and variance; both absent alike).
fn answers_equal(site: &Client, points: &[[f64; 2]], want: &[Option<(f64, f64)>]) -> Result<bool> {
    let got = site.elevation(points)?;
    Ok(got
        .iter()
        .zip(want)
        .all(|(g, w)| match (g.z_m.zip(g.z_var_m2), w) {
            (Some((z, v)), Some((wz, wv))) => (z - wz).abs() <= 1e-9 && (v - wv).abs() <= 1e-9,
            (None, None) => true,
            _ => false,
        }))
}

#[test]
fn three_robots_one_site_through_a_zenoh_storage() -> Result<()> {
    let reserved = reserve_loopback_endpoint()?;
    let endpoint = reserved.endpoint().to_owned();
    let site_id = unique_id("site");
    let site_keys = MapKeys::new(&site_id)?;
    let router = StorageRouter::start(&endpoint, &site_keys, WAIT)?;
    drop(reserved);

    let mut site_config = daemon_config(&site_id, &endpoint);
    site_config.fleet.role = FleetRole::Site;
    // Room for the three robots and no fourth (checked at the end).
    site_config.fleet.max_site_robots = 3;
    let mut site_daemon = spawn_daemon(&site_config)?;
    let site = client(&site_id, &endpoint)?;

    // Three robots on parallel lines 15 m apart (y = −15, 0, 15), heading +x, on one world.
    let mut robots = Vec::new();
    let ids: Vec<String> = (1..=3).map(|k| unique_id(&format!("robot{k}"))).collect();
    for id in &ids {
        let mut c = daemon_config(id, &endpoint);
        c.ingest.service_name = format!("rangegp/{}/scans", unique_id("svc"));
        c.fleet.site = site_id.clone();
        c.fleet.tile_period_ms = 100;
        let child = spawn_daemon(&c)?;
        robots.push((c, child, client(id, &endpoint)?));
    }
    let mut w = world(11, 6);
    let mut last_stamp = [0u64; 3];
    for (k, (c, _, robot)) in robots.iter().enumerate() {
        let y = -15.0 + 15.0 * k as f64;
        w.path = Path {
            waypoints: (0..6).map(|i| [-12.0 + i as f64, y, 0.0]).collect(),
        };
        let mut publisher = ScanPublisher::new(&c.scan_service_name(), 1, 4096)?;
        for i in 0..6 {
            let scan = w.scan(i, now_ns());
            last_stamp[k] = scan.header.stamp_ns;
            let before = robot.status()?.aggregate.inserts;
            publisher.publish(scan.header, &scan.points)?;
            wait_for("the scan fused", || {
                Ok((robot.status()?.aggregate.inserts > before).then_some(()))
            })?;
        }
    }
    // Every robot's tiles published: the site has a tile of the robot's last scan (so the
    // robot's tile thread has walked its map since that insert), and the robot has none waiting.
    for (k, (_, _, robot)) in robots.iter().enumerate() {
        wait_for("the tiles published", || {
            let site_has_last = site
                .status()?
                .fleet
                .robots
                .iter()
                .any(|r| r.robot == ids[k] && r.newest_scan_ns == last_stamp[k]);
            let waiting = robot.status()?.fleet.tiles_pending;
            Ok((site_has_last && waiting == 0).then_some(()))
        })?;
    }
    let mut published = 0;
    for (_, _, robot) in &robots {
        published += robot.status()?.fleet.tiles_published;
    }

    // Probe points: ahead of each robot, and between the lines (seen by two robots).
    let points: Vec<[f64; 2]> = (0..3)
        .flat_map(|k| {
            let y = -15.0 + 15.0 * k as f64;
            (0..8).flat_map(move |i| [[-4.0 + i as f64, y + 1.0], [-4.0 + i as f64, y - 7.5]])
        })
        .collect();
    // The storage and the site each take the robots' puts from the router in their own time:
    // wait until the site has taken in every put (its count follows its map), then read the
    // storage again until the site answers what its tiles answer.
    wait_for("the site taking in every put", || {
        Ok((site.status()?.fleet.tiles_received >= published).then_some(()))
    })?;
    let (tiles, want) = wait_for("the site answering the stored tiles", || {
        let tiles = stored(&router, &site_keys)?;
        if !ids.iter().all(|id| tiles.iter().any(|t| &t.robot == id)) {
            return Ok(None);
        }
        let want = expected(tiles.clone(), &points)?;
        Ok(answers_equal(&site, &points, &want)?.then_some((tiles, want)))
    })?;
    let answered = want.iter().filter(|w| w.is_some()).count();
    ensure!(
        answered >= points.len() / 2,
        "only {answered} of {} probes answerable",
        points.len()
    );
    println!(
        "site answers {answered} of {} probe points exactly as the stored tiles",
        points.len()
    );

    // A point ahead of robot 2 only: the site answers from robot 2's tiles alone.
    let only2 = [[0.0, 1.0]];
    let robot2_tiles: Vec<TileUpdate> = tiles.iter().filter(|t| t.robot == ids[1]).cloned().collect();
    let from2 = expected(robot2_tiles, &only2)?;
    ensure!(from2[0].is_some(), "robot 2's tiles do not answer {only2:?}");
    ensure!(
        answers_equal(&site, &only2, &from2)?,
        "the site does not answer robot 2's ground from its tiles"
    );
    // The site refreshes its list of robots once a second, its map with every batch: the list
    // may lag the answers by up to a second.
    let status = wait_for("the site listing every robot", || {
        let s = site.status()?;
        Ok((s.fleet.robots.len() == 3).then_some(s))
    })?;
    ensure!(status.fleet.storage_answered, "the site found no storage");
    // What `rangegp status --site` prints: the storage, then every robot, alive.
    let table = site_table(&status, now_ns());
    println!("{table}");
    ensure!(table.contains("storage: answered"), "{table}");
    for id in &ids {
        let row = table
            .lines()
            .find(|l| l.starts_with(id.as_str()))
            .context("robot row")?;
        ensure!(row.split_whitespace().nth(1) == Some("yes"), "{table}");
    }

    // Provenance: the site's answer there stands on robot 2's cell alone, the very cell robot 2
    // holds.
    let under = site.sources(&only2)?.remove(0);
    let names: Vec<&str> = under.iter().map(|c| c.robot.as_str()).collect();
    ensure!(
        names == [ids[1].as_str()],
        "sources at robot 2's point: {names:?}"
    );
    let own = robots[1].2.sources(&only2)?.remove(0);
    ensure!(own == under, "robot 2 holds {own:?}, the site lists {under:?}");

    // The fleet query: every robot answers; robot 2 alone gives a height at its point.
    let fleet = site.fleet_elevation(&only2, WAIT, &[&site_id])?;
    let heard: Vec<&str> = fleet.maps.iter().map(|(m, _)| m.as_str()).collect();
    let mut want_heard: Vec<&str> = ids.iter().map(String::as_str).collect();
    want_heard.sort();
    ensure!(heard == want_heard, "fleet query heard {heard:?}");
    let fused = fleet.fused[0]
        .as_ref()
        .context("no robot answered robot 2's point")?;
    ensure!(fused.maps == [ids[1].clone()], "fused over {:?}", fused.maps);
    let own = &fleet
        .maps
        .iter()
        .find(|(m, _)| m == &ids[1])
        .context("robot 2 missing")?
        .1[0];
    ensure!(
        own.source == Source::Window && own.z_m.is_some_and(|z| (z - fused.z_m).abs() < 1e-12),
        "robot 2 own answer: {own:?}"
    );

    // Robot 2 killed: its ground still answers from the site, and it is not alive.
    let (_, robot2, _) = robots.remove(1);
    robot2.kill()?;
    wait_for("robot 2 reported gone", || {
        let robots = site.status()?.fleet.robots;
        Ok(robots.iter().any(|r| r.robot == ids[1] && !r.alive).then_some(()))
    })?;
    ensure!(
        answers_equal(&site, &points, &want)?,
        "the site changed its answers when robot 2 died"
    );
    ensure!(
        answers_equal(&site, &only2, &from2)?,
        "robot 2's ground no longer answers"
    );
    let fleet = site.fleet_elevation(&only2, WAIT, &[&site_id])?;
    ensure!(
        fleet.maps.len() == 2,
        "after the kill the fleet query heard {:?}",
        fleet.maps
    );

    // The site killed and restarted: the same answers, from the storage alone.
    site_daemon.kill()?;
    site_daemon = spawn_daemon(&site_config)?;
    let site = client(&site_id, &endpoint)?;
    // Alive means recovered: the first answers are the stored map's, on the same cells.
    ensure!(
        site.sources(&only2)?.remove(0) == under,
        "the restarted site lists other sources"
    );
    ensure!(
        answers_equal(&site, &points, &want)?,
        "the restarted site answers otherwise"
    );
    let status = site.status()?;
    ensure!(
        status.fleet.storage_answered
            && status.fleet.tiles_from_storage == tiles.len() as u64
            && status.fleet.robots.len() == 3
            && status.fleet.robots.iter().filter(|r| r.alive).count() == 2,
        "restarted site: {:?}",
        status.fleet
    );
    println!(
        "restarted site: {} tiles from the storage, {} robots",
        status.fleet.tiles_from_storage,
        status.fleet.robots.len()
    );

    // Tile messages no robot sends: 1 MiB (over any valid tile: refused unread), a few
    // undecodable bytes, and a valid tile from a fourth robot, beyond the site's room for
    // three. All refused and counted; the site answers as before and lists three robots.
    let config = zenoh_config("client", &[], std::slice::from_ref(&endpoint), false)?;
    let peer = zenoh::open(config).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    let key = tile_key(&site_keys, &MapKeys::new(&ids[0])?, (0, 0));
    let mut fourth = tiles[0].clone();
    fourth.robot = unique_id("robot4");
    let fourth_key = tile_key(
        &site_keys,
        &MapKeys::new(&fourth.robot)?,
        (fourth.tile_column, fourth.tile_row),
    );
    let fourth_bytes = rangegp_proto::codec::encode(Encoding::Bincode, &fourth)?;
    for (key, payload) in [
        (&key, vec![0u8; 1 << 20]),
        (&key, vec![0xff; 16]),
        (&fourth_key, fourth_bytes),
    ] {
        peer.put(key, payload)
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let refused_before = status.fleet.tiles_refused;
    wait_for("the three tile messages refused", || {
        Ok((site.status()?.fleet.tiles_refused >= refused_before + 3).then_some(()))
    })?;
    ensure!(
        site.status()?.fleet.robots.len() == 3,
        "the site took a fourth robot beyond its limit"
    );
    ensure!(
        answers_equal(&site, &points, &want)?,
        "bad tile messages changed the site's answers"
    );
    drop(site_daemon);
    Ok(())
}

/// A robot whose site is unreachable holds departed tiles' unsent cells only up to
/// `fleet.max_held_departed_tiles` (checkpoints off, so no page holds them): two robots drive
/// the same path with no subscriber to the site's tiles, one with room for every departed tile
/// and one with room for three. When a subscriber appears, the bounded robot sends some of the
/// other's tiles and no other, having counted at least as many changes forgotten as it misses
/// (which are its oldest: a unit test in `fleet::publish`).
#[test]
fn a_robot_off_its_site_holds_departed_tiles_within_its_bound() -> Result<()> {
    let reserved = reserve_loopback_endpoint()?;
    let endpoint = reserved.endpoint().to_owned();
    drop(reserved);
    let router = zenoh::open(zenoh_config(
        "router",
        std::slice::from_ref(&endpoint),
        &[],
        false,
    )?)
    .wait()
    .map_err(|e| anyhow::anyhow!("router: {e}"))?;
    let site_id = unique_id("site");
    let site_keys = MapKeys::new(&site_id)?;

    let mut robots = Vec::new();
    for (name, bound) in [("roomy", 100_000), ("tight", 3)] {
        let id = unique_id(name);
        let mut c = daemon_config(&id, &endpoint);
        c.ingest.service_name = format!("rangegp/{}/scans", unique_id("svc"));
        c.fleet.site = site_id.clone();
        c.fleet.tile_period_ms = 100;
        c.fleet.max_held_departed_tiles = bound;
        c.aggregate.radius_m = 4.0;
        // A whole core keeps the fusion's reach at 10 m in both (the same cells in both).
        c.aggregate.cpu_share = 1.0;
        let daemon = Daemon::builder(c.clone()).start()?;
        robots.push((id.clone(), c, daemon, client(&id, &endpoint)?));
    }
    let mut w = world(12, 14);
    w.path = Path {
        waypoints: (0..14).map(|i| [-7.0 + i as f64, 0.0, 0.0]).collect(),
    };
    for (_, c, _, robot) in &robots {
        let mut publisher = ScanPublisher::new(&c.scan_service_name(), 1, 4096)?;
        for i in 0..14 {
            let scan = w.scan(i, now_ns());
            let before = robot.status()?.aggregate.inserts;
            publisher.publish(scan.header, &scan.points)?;
            wait_for("the scan fused", || {
                Ok((robot.status()?.aggregate.inserts > before).then_some(()))
            })?;
        }
    }
    // Tiles have left both radii (the tight robot forgot some), and none was sent.
    wait_for("the tight robot forgetting", || {
        Ok((robots[1].3.status()?.fleet.tiles_dropped > 0).then_some(()))
    })?;
    for (id, _, _, robot) in &robots {
        let f = robot.status()?.fleet;
        ensure!(
            f.tiles_published == 0,
            "{id} published {} tiles to no one",
            f.tiles_published
        );
    }
    ensure!(
        robots[0].3.status()?.fleet.tiles_dropped == 0,
        "the roomy robot forgot tiles"
    );

    // A subscriber appears: every robot sends what it holds.
    let received = Arc::new(std::sync::Mutex::new(Vec::<(String, (i32, i32))>::new()));
    let sink = Arc::clone(&received);
    let keys = site_keys.clone();
    let _subscriber = router
        .declare_subscriber(rangegp_proto::fleet::site_tiles(&site_keys))
        .callback(move |sample| {
            if let Some(key) = parse_tile_key(&keys, sample.key_expr().as_str()) {
                sink.lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .push(key);
            }
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("subscriber: {e}"))?;
    for (id, _, _, robot) in &robots {
        wait_for("every waiting tile sent", || {
            let f = robot.status()?.fleet;
            Ok((f.tiles_published > 0 && f.tiles_pending == 0).then_some(()))
        })
        .with_context(|| id.clone())?;
    }
    let mut published = 0;
    for (_, _, _, robot) in &robots {
        published += robot.status()?.fleet.tiles_published;
    }
    wait_for("every put received", || {
        let n = received
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .len() as u64;
        Ok((n >= published).then_some(()))
    })?;
    // Read once every departure was taken: the scans were fused before the sends began.
    let dropped = robots[1].3.status()?.fleet.tiles_dropped;
    let got = received
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .clone();
    let tiles_of = |id: &str| -> std::collections::BTreeSet<(i32, i32)> {
        got.iter().filter(|(r, _)| r == id).map(|&(_, k)| k).collect()
    };
    let (roomy, tight) = (tiles_of(&robots[0].0), tiles_of(&robots[1].0));
    println!(
        "roomy robot sent {} tiles, tight robot {} and forgot {dropped} changes",
        roomy.len(),
        tight.len()
    );
    ensure!(
        tight.is_subset(&roomy),
        "the tight robot sent tiles the roomy one did not"
    );
    // A tile beyond the 4 m radius departs again with each scan that reaches it (the sensor
    // sees 10 m), so the count of forgotten changes may exceed the tiles missing.
    let missing = roomy.difference(&tight).count() as u64;
    ensure!(
        missing > 0 && dropped >= missing,
        "{missing} tiles missing, {dropped} changes counted forgotten"
    );
    Ok(())
}
