//! `rangegp`: the lab's command line. The demo, queries to a rangegp daemon, and simulated
//! scans and load to drive it.

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use rangegp_client::{Client, ScanPublisher};
use rangegp_lab::cli::SimSensorArgs;
use rangegp_lab::dem::DemArgs;
use rangegp_lab::demo::{self, DemoOptions};
use rangegp_lab::load::{self, LoadOptions};
use rangegp_lab::replay::{self, ReplayOptions};
use rangegp_lab::scangen::{now_ns, ScanGenerator};
use rangegp_proto::msg::{Camera, GridRequest, Layer, PoseCorrection, Ray, Rigid, Source, ViewRequest};
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_sim::ScannerPreset;
use std::time::{Duration, Instant};

#[derive(Parser)]
#[command(
    version,
    about = "The rangegp lab: the demo, queries to a rangegp daemon over Zenoh, simulated scans over iceoryx2"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Args)]
struct Connection {
    /// Daemon endpoint.
    #[arg(long, default_value = "tcp/127.0.0.1:7447")]
    connect: String,
    /// Map id.
    #[arg(long, default_value = "default")]
    map_id: String,
    /// Per-query timeout, seconds.
    #[arg(long, default_value_t = 10.0)]
    timeout_s: f64,
}

impl Connection {
    fn open(&self) -> Result<Client> {
        let timeout = Duration::from_secs_f64(self.timeout_s);
        let client = Client::builder(&self.map_id)
            .connect([self.connect.clone()])
            .timeout(timeout)
            .open()?;
        client
            .wait_for_daemon(timeout)
            .with_context(|| format!("no daemon for map {:?} at {}", self.map_id, self.connect))?;
        Ok(client)
    }
}

#[derive(Subcommand)]
enum Command {
    /// The daemon on embedded defaults with a simulated rover (iceoryx2) and planner (Zenoh), all
    /// in this process on loopback; writes OUT/summary.json and pictures.
    Demo(DemoOptions),
    /// Print the daemon's counters as JSON; `--site` prints a site daemon's robots, tiles and
    /// storage state as a table instead.
    Status {
        #[command(flatten)]
        connection: Connection,
        /// The fleet view: robots (alive or not), their tiles and cells, and the storage.
        #[arg(long)]
        site: bool,
    },
    /// Write a CA, the daemon's certificate and one per planner into DIR, as the shipped
    /// mutual-TLS configuration (deploy/zenoh-*.json5) expects them. For trials, not production.
    Certs {
        /// Output directory.
        #[arg(long, default_value = "tls")]
        dir: std::path::PathBuf,
        /// Planner common names (each gets NAME.pem / NAME.key; the shipped daemon config lists
        /// planner-1 and planner-2).
        #[arg(long, default_values_t = ["planner-1".to_owned()])]
        planner: Vec<String>,
    },
    /// Correct past scans' poses and print what moved as JSON: a loop closure moves every scan
    /// taken since `--from-stamp-ns` by a rigid transform (`--transform`), or `--scan PUB SEQ`
    /// sets one scan's pose (`--transform` is then that pose).
    Correct {
        #[command(flatten)]
        connection: Connection,
        /// The transform (or the scan's pose): X Y Z (metres) and yaw (degrees, about +z).
        #[arg(long, num_args = 4, allow_negative_numbers = true, required = true)]
        transform: Vec<f64>,
        /// Move only scans taken at or after this stamp, ns since the Unix epoch.
        #[arg(long, default_value_t = 0)]
        from_stamp_ns: u64,
        /// Move only scans taken at or before this stamp (default: every scan since `from`).
        #[arg(long, default_value_t = u64::MAX)]
        until_stamp_ns: u64,
        /// Move only this publisher's scans.
        #[arg(long)]
        publisher: Option<u64>,
        /// Set the pose of one scan, named by publisher id and sequence.
        #[arg(long, num_args = 2, conflicts_with_all = ["from_stamp_ns", "until_stamp_ns", "publisher"])]
        scan: Option<Vec<u64>>,
    },
    /// Run one query and print the reply as JSON.
    Query {
        #[command(flatten)]
        connection: Connection,
        #[command(subcommand)]
        kind: QueryCommand,
    },
    /// Elevation and σ layers over a box, and the planner layers named by `--layers`: prints a
    /// summary as JSON, or the whole reply with `--json`; `--png FILE` draws elevation to FILE,
    /// σ to FILE with `_sigma` before `.png`, and each named layer with `_<layer>`.
    Grid {
        #[command(flatten)]
        connection: Connection,
        /// Box corners X0 Y0 X1 Y1, map frame, metres.
        #[arg(long, num_args = 4, allow_negative_numbers = true, required = true)]
        bbox: Vec<f64>,
        /// Cell side, metres (at most the robot's footprint radius with `--layers`).
        #[arg(long, default_value_t = 0.25)]
        res: f64,
        /// Planner layers, comma separated: slope, slope_sigma, aspect, roughness,
        /// roughness_sigma, step, step_sigma, slope_risk, step_risk, unknown_risk, risk,
        /// traversal_cost, cost; or `all`.
        #[arg(long, value_delimiter = ',')]
        layers: Vec<String>,
        /// Write the layers as PNG here.
        #[arg(long)]
        png: Option<std::path::PathBuf>,
        /// Print every cell.
        #[arg(long)]
        json: bool,
    },
    /// A range image of the map as a LiDAR preset would see it from a pose (any pose: never
    /// visited is fine): prints a summary as JSON, or the whole reply with `--json`; `--png FILE`
    /// draws the range to FILE and its σ beside it (`_sigma` before `.png`).
    View {
        #[command(flatten)]
        connection: Connection,
        /// Sensor position X Y Z (map frame, metres) and heading (degrees, counter-clockwise
        /// from +x).
        #[arg(long, num_args = 4, allow_negative_numbers = true, required = true)]
        pose: Vec<f64>,
        /// Sensor preset whose rings to use: seed000, vlp16 or os1-64.
        #[arg(long, default_value = "vlp16")]
        preset: String,
        /// Azimuths over a full turn.
        #[arg(long, default_value_t = 360)]
        columns: u32,
        /// Write the range image as PNG here.
        #[arg(long)]
        png: Option<std::path::PathBuf>,
        /// Print every pixel.
        #[arg(long)]
        json: bool,
    },
    /// Load test: publish simulated scans at a sensor's rate while planners query; measures
    /// scan-to-queryable latency, skipped scans, round trips against a bare Zenoh echo and the
    /// daemon's RSS; writes OUT/summary.json.
    Load {
        #[command(flatten)]
        connection: Connection,
        /// iceoryx2 scan service name (default `rangegp/<map-id>/scans`).
        #[arg(long)]
        service: Option<String>,
        /// Sensor preset: seed000, vlp16 or os1-64.
        #[arg(long, default_value = "os1-64")]
        preset: String,
        /// Scans per second.
        #[arg(long, default_value_t = 10.0)]
        rate_hz: f64,
        /// Length of the timed run, seconds.
        #[arg(long, default_value_t = 60.0)]
        seconds: f64,
        /// Simulated planners, each on its own Zenoh session.
        #[arg(long, default_value_t = 2)]
        planners: usize,
        /// Query rounds per second per planner.
        #[arg(long, default_value_t = 20.0)]
        planner_hz: f64,
        /// World seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Metres between poses.
        #[arg(long, default_value_t = 0.5)]
        step_m: f64,
        /// Output directory.
        #[arg(long, default_value = "load-out")]
        out: std::path::PathBuf,
    },
    /// Feed a rosbag2 MCAP recording (PointCloud2 with Odometry or /tf) to the daemon as scans;
    /// `--list` shows its topics.
    Replay {
        #[command(flatten)]
        options: ReplayOptions,
        #[command(flatten)]
        connection: Connection,
    },
    /// Write simulated scans along a path as a rosbag2 MCAP recording (/points, /odom, /tf), to
    /// try `replay` without a robot.
    RecordSim {
        /// Output file.
        out: std::path::PathBuf,
        /// Sensor preset: seed000, vlp16 or os1-64.
        #[arg(long, default_value = "vlp16")]
        preset: String,
        /// Scans to record.
        #[arg(long, default_value_t = 30)]
        count: usize,
        /// Scans per second (the recorded stamps' pace).
        #[arg(long, default_value_t = 2.0)]
        rate_hz: f64,
        /// World seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Metres between scans.
        #[arg(long, default_value_t = 1.0)]
        step_m: f64,
        /// A DEM to drive on instead of the cratered terrain.
        #[command(flatten)]
        dem: DemArgs,
        /// How the sensor rides and which returns it loses.
        #[command(flatten)]
        sensor: SimSensorArgs,
        /// Compress chunks with zstd.
        #[arg(long)]
        zstd: bool,
    },
    /// Publish simulated scans along a path at a rate (the scan generator).
    Scangen {
        /// iceoryx2 scan service name.
        #[arg(long, default_value = "rangegp/default/scans")]
        service: String,
        /// Sensor preset: seed000, vlp16 or os1-64.
        #[arg(long, default_value = "seed000")]
        preset: String,
        /// Scans to publish.
        #[arg(long, default_value_t = 50)]
        count: usize,
        /// Scans per second.
        #[arg(long, default_value_t = 10.0)]
        rate_hz: f64,
        /// World seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Metres between scans.
        #[arg(long, default_value_t = 1.0)]
        step_m: f64,
        /// A DEM to drive on instead of the cratered terrain.
        #[command(flatten)]
        dem: DemArgs,
        /// How the sensor rides and which returns it loses.
        #[command(flatten)]
        sensor: SimSensorArgs,
        /// Publisher id in the scan header.
        #[arg(long, default_value_t = 1)]
        publisher_id: u64,
    },
}

#[derive(Subcommand)]
enum QueryCommand {
    /// Elevation at X Y [X Y ...].
    Elevation {
        /// Coordinates in pairs, map frame, metres.
        #[arg(num_args = 2.., allow_negative_numbers = true, required = true)]
        coords: Vec<f64>,
    },
    /// Elevation variance at X Y [X Y ...].
    Variance {
        /// Coordinates in pairs, map frame, metres.
        #[arg(num_args = 2.., allow_negative_numbers = true, required = true)]
        coords: Vec<f64>,
    },
    /// Slope (with σ, aspect, normal and slope risk) over the daemon's robot footprint at
    /// X Y [X Y ...].
    Slope {
        /// Coordinates in pairs, map frame, metres.
        #[arg(num_args = 2.., allow_negative_numbers = true, required = true)]
        coords: Vec<f64>,
    },
    /// Cast one ray: origin OX OY OZ, direction DX DY DZ.
    Ray {
        /// ox oy oz dx dy dz.
        #[arg(num_args = 6, allow_negative_numbers = true, required = true)]
        values: Vec<f64>,
        /// Max range, metres.
        #[arg(long, default_value_t = 20.0)]
        max_range_m: f64,
    },
}

fn preset_named(name: &str) -> Result<ScannerPreset> {
    ScannerPreset::by_name(name).with_context(|| format!("unknown preset {name:?}: seed000, vlp16, os1-64"))
}

fn pairs(coords: &[f64]) -> Result<Vec<[f64; 2]>> {
    anyhow::ensure!(coords.len().is_multiple_of(2), "coordinates come in (x, y) pairs");
    Ok(coords.chunks(2).map(|c| [c[0], c[1]]).collect())
}

/// `--layers` names: one layer, or `all`.
fn parse_layers(name: &str) -> Result<Vec<Layer>> {
    if name == "all" {
        return Ok(Layer::ALL.to_vec());
    }
    Layer::parse(name).map(|l| vec![l]).with_context(|| {
        let names: Vec<&str> = Layer::ALL.iter().map(|l| l.as_str()).collect();
        format!("unknown layer {name:?}: one of {} or all", names.join(", "))
    })
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Demo(opts) => {
            let summary = demo::run(&opts)?;
            demo::print_table(&summary, &opts.out);
        }
        Command::Certs { dir, planner } => {
            rangegp_lab::certs::write_site(&dir, &planner)?;
            println!(
                "wrote ca.pem, rangegpd.pem/.key and {} planner certificate(s) to {}",
                planner.len(),
                dir.display()
            );
        }
        Command::Status { connection, site } => {
            let status = connection.open()?.status()?;
            if site {
                print!(
                    "{}",
                    rangegp_lab::fleet::site_table(&status, rangegp_lab::scangen::now_ns())
                );
            } else {
                println!("{}", serde_json::to_string_pretty(&status)?);
            }
        }
        Command::Correct {
            connection,
            transform,
            from_stamp_ns,
            until_stamp_ns,
            publisher,
            scan,
        } => {
            let half = transform[3].to_radians() / 2.0;
            let rigid = Rigid {
                translation_m: [transform[0], transform[1], transform[2]],
                rotation_xyzw: [0.0, 0.0, half.sin(), half.cos()],
            };
            let correction = match scan.as_deref() {
                Some(&[publisher_id, sequence]) => PoseCorrection::Scan {
                    publisher_id,
                    sequence,
                    pose: rigid,
                },
                _ => PoseCorrection::Transform {
                    publisher_id: publisher,
                    from_stamp_ns,
                    until_stamp_ns,
                    transform: rigid,
                },
            };
            let reply = connection.open()?.correct(&[correction])?;
            println!("{}", serde_json::to_string_pretty(&reply)?);
        }
        Command::Query { connection, kind } => {
            let client = connection.open()?;
            let json = match kind {
                QueryCommand::Elevation { coords } => {
                    serde_json::to_string_pretty(&client.elevation(&pairs(&coords)?)?)?
                }
                QueryCommand::Variance { coords } => {
                    serde_json::to_string_pretty(&client.variance(&pairs(&coords)?)?)?
                }
                QueryCommand::Slope { coords } => {
                    serde_json::to_string_pretty(&client.slope(&pairs(&coords)?, None)?)?
                }
                QueryCommand::Ray { values, max_range_m } => {
                    let ray = Ray {
                        origin_m: [values[0], values[1], values[2]],
                        direction: [values[3], values[4], values[5]],
                        max_range_m,
                    };
                    serde_json::to_string_pretty(&client.ray(&[ray])?)?
                }
            };
            println!("{json}");
        }
        Command::Grid {
            connection,
            bbox,
            res,
            layers,
            png,
            json,
        } => {
            let mut wanted: Vec<Layer> = Vec::new();
            for name in &layers {
                for l in parse_layers(name)? {
                    if !wanted.contains(&l) {
                        wanted.push(l);
                    }
                }
            }
            let rep = connection.open()?.grid_request(&GridRequest {
                version: PROTOCOL_VERSION,
                min_m: [bbox[0], bbox[1]],
                max_m: [bbox[2], bbox[3]],
                resolution_m: res,
                layers: wanted,
                robot: None,
            })?;
            if let Some(file) = &png {
                rangegp_lab::pictures::grid(&rep, file)?;
            }
            if json {
                println!("{}", serde_json::to_string(&rep)?);
            } else {
                let observed = rep.elevation_m.iter().flatten().count();
                let summary = serde_json::json!({
                    "cols": rep.cols,
                    "rows": rep.rows,
                    "origin_m": rep.origin_m,
                    "resolution_m": rep.resolution_m,
                    "observed_cells": observed,
                    "png": png,
                });
                println!("{}", serde_json::to_string_pretty(&summary)?);
            }
        }
        Command::View {
            connection,
            pose,
            preset,
            columns,
            png,
            json,
        } => {
            let preset = preset_named(&preset)?;
            let yaw = pose[3].to_radians();
            let req = ViewRequest {
                version: PROTOCOL_VERSION,
                position_m: [pose[0], pose[1], pose[2]],
                orientation_xyzw: [0.0, 0.0, (yaw / 2.0).sin(), (yaw / 2.0).cos()],
                camera: Camera::Lidar {
                    ring_elevations_rad: preset
                        .inclinations_rad
                        .iter()
                        .map(|i| std::f64::consts::FRAC_PI_2 - i)
                        .collect(),
                    columns,
                    max_range_m: preset.max_range_m,
                },
            };
            let rep = connection.open()?.view(&req)?;
            if let Some(file) = &png {
                rangegp_lab::pictures::view(&rep, &req, file)?;
            }
            if json {
                println!("{}", serde_json::to_string(&rep)?);
            } else {
                let count = |s: Source| rep.source.iter().filter(|&&v| v == s).count();
                let summary = serde_json::json!({
                    "rows": rep.rows,
                    "cols": rep.cols,
                    "hits": rep.range_m.iter().flatten().count(),
                    "from_window": count(Source::Window),
                    "from_aggregate": count(Source::Aggregate),
                    "unknown": count(Source::None),
                    "png": png,
                });
                println!("{}", serde_json::to_string_pretty(&summary)?);
            }
        }
        Command::Load {
            connection,
            service,
            preset,
            rate_hz,
            seconds,
            planners,
            planner_hz,
            seed,
            step_m,
            out,
        } => {
            let preset = preset_named(&preset)?;
            let opts = LoadOptions {
                service: service.unwrap_or_else(|| format!("rangegp/{}/scans", connection.map_id)),
                connect: connection.connect,
                map_id: connection.map_id,
                preset,
                rate_hz,
                seconds,
                planners,
                planner_hz,
                seed,
                step_m,
                // A fresh id per run: the daemon refuses replayed (publisher, sequence) pairs.
                publisher_id: now_ns(),
                out,
                timeout: Duration::from_secs_f64(connection.timeout_s),
            };
            let summary = load::run(&opts, |line| eprintln!("{line}"))?;
            load::print(&summary, &opts.out);
        }
        Command::Replay { options, connection } => {
            if options.list {
                println!(
                    "{:<32} {:<32} {:<8} {:>9} {:>9}",
                    "topic", "type", "encoding", "messages", "seconds"
                );
                for t in replay::list(&options.file)? {
                    let span = t.span_ns.1.saturating_sub(t.span_ns.0) as f64 * 1e-9;
                    println!(
                        "{:<32} {:<32} {:<8} {:>9} {:>9.1}",
                        t.topic, t.schema, t.encoding, t.messages, span
                    );
                }
            } else {
                let client = match options.pace {
                    replay::Pace::Accepted => Some(connection.open()?),
                    replay::Pace::Recorded => None,
                };
                let summary = replay::run(&options, client.as_ref(), |line| eprintln!("{line}"))?;
                println!("{}", serde_json::to_string_pretty(&summary)?);
            }
        }
        Command::RecordSim {
            out,
            preset,
            count,
            rate_hz,
            seed,
            step_m,
            dem,
            sensor,
            zstd,
        } => {
            let preset = sensor.preset(preset_named(&preset)?);
            anyhow::ensure!(rate_hz > 0.0, "--rate-hz must be positive");
            let mut world = generator(&dem, seed, preset, count, step_m)?.with_chassis(sensor.chassis_m);
            let t0 = now_ns();
            let period_ns = (1e9 / rate_hz) as u64;
            let scans: Vec<_> = (0..count)
                .map(|i| world.scan(i, t0 + i as u64 * period_ns))
                .collect();
            let file = std::fs::File::create(&out)?;
            let opts = replay::record::RecordOptions {
                zstd,
                ..Default::default()
            };
            replay::record::write(file, &scans, &opts)?;
            eprintln!("{count} scans written to {}", out.display());
        }
        Command::Scangen {
            service,
            preset,
            count,
            rate_hz,
            seed,
            step_m,
            dem,
            sensor,
            publisher_id,
        } => {
            let preset = sensor.preset(preset_named(&preset)?);
            anyhow::ensure!(rate_hz > 0.0, "--rate-hz must be positive");
            let rays = preset.ray_count();
            let mut world = generator(&dem, seed, preset, count, step_m)?.with_chassis(sensor.chassis_m);
            let mut publisher = ScanPublisher::new(&service, publisher_id, rays)?;
            let period = Duration::from_secs_f64(1.0 / rate_hz);
            for i in 0..count {
                let tick = Instant::now();
                let scan = world.scan(i, now_ns());
                let seq = publisher.publish(scan.header, &scan.points)?;
                eprintln!("scan {}/{count}: sequence {seq}, {rays} rays", i + 1);
                std::thread::sleep(period.saturating_sub(tick.elapsed()));
            }
        }
    }
    Ok(())
}

/// The scan generator of `scangen` and `record-sim`: on the DEM `--dem` names, else on a 100 m
/// cratered world from `seed`.
fn generator(
    dem: &DemArgs,
    seed: u64,
    preset: ScannerPreset,
    count: usize,
    step_m: f64,
) -> Result<ScanGenerator> {
    Ok(match dem.load()? {
        Some(dem) => {
            eprintln!(
                "terrain: {} ({:.1} m a side)",
                dem.name,
                2.0 * dem.map.half_extent()
            );
            ScanGenerator::on(dem.map, seed, preset, count, step_m)
        }
        None => ScanGenerator::new(seed, 100.0, preset, count, step_m),
    })
}
