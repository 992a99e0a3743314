//! One request end to end: decode, check version and limits, evaluate, encode.

use super::DaemonState;
use crate::map::aggregate::Aggregate;
use crate::map::grid::GridBox;
use crate::map::layers::{footprint_reach, LayerModel, MAX_FOOTPRINT_REACH};
use crate::map::query;
use crate::map::MapSnapshot;
use rangegp_proto::codec::{self, Encoding};
use rangegp_proto::fleet::{RobotCell, SourcesReply, SourcesRequest};
use rangegp_proto::keys::QueryKind;
use rangegp_proto::msg::*;
use rangegp_proto::PROTOCOL_VERSION;
use serde::{de::DeserializeOwned, Serialize};
use std::sync::atomic::Ordering::Relaxed;
use tracing::debug_span;

/// Which queryable a query arrived on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Endpoint {
    /// `rangegp/<map>/query/<kind>`.
    Query(QueryKind),
    /// `rangegp/<map>/status`.
    Status,
    /// `rangegp/<map>/corrections`.
    Corrections,
}

/// A request that is answered with `reply_err`.
#[derive(Debug, Clone, PartialEq)]
pub struct Failure {
    /// Error class.
    pub code: ErrorCode,
    /// Detail for the caller.
    pub message: String,
}

fn fail<T>(code: ErrorCode, message: impl Into<String>) -> Result<T, Failure> {
    Err(Failure {
        code,
        message: message.into(),
    })
}

/// Answers one request payload; the reply is in the request's encoding.
pub fn answer(
    endpoint: Endpoint,
    encoding: Encoding,
    payload: &[u8],
    state: &DaemonState,
) -> Result<Vec<u8>, Failure> {
    // Debug level: at the daemon's default `info`, a span formatted on every query cost more
    // than a tenth of a single-point answer (docs/ARCHITECTURE.md); `RUST_LOG=debug` shows it.
    let _span = debug_span!("query", endpoint = ?endpoint, bytes = payload.len()).entered();
    match endpoint {
        Endpoint::Status => {
            if !payload.is_empty() {
                decode::<StatusRequest>(encoding, payload)?;
            }
            encode(encoding, &status(state))
        }
        Endpoint::Corrections => {
            let req: CorrectionRequest = decode(encoding, payload)?;
            // Each correction is held (and run over every scan held) until applied.
            check_batch(req.corrections.len(), state)?;
            use super::corrections::{submit, SubmitError};
            let reply = submit(state, &req, std::time::Instant::now()).map_err(|e| Failure {
                code: match e {
                    SubmitError::Invalid(_) => ErrorCode::InvalidArgument,
                    SubmitError::Busy => ErrorCode::Overloaded,
                    SubmitError::Failed(_) | SubmitError::TimedOut => ErrorCode::Internal,
                },
                message: e.to_string(),
            })?;
            encode(encoding, &reply)
        }
        Endpoint::Query(QueryKind::Elevation) => {
            let req: ElevationRequest = decode(encoding, payload)?;
            check_points(&req.points, state)?;
            let snap = snapshot(state)?;
            let items = query::par_map(&req.points, state.batch_threads, |p| {
                query::elevation(&snap, p[0], p[1])
            });
            encode(
                encoding,
                &ElevationReply {
                    version: PROTOCOL_VERSION,
                    items,
                },
            )
        }
        Endpoint::Query(QueryKind::Variance) => {
            let req: VarianceRequest = decode(encoding, payload)?;
            check_points(&req.points, state)?;
            let snap = snapshot(state)?;
            let items = query::par_map(&req.points, state.batch_threads, |p| {
                query::variance(&snap, p[0], p[1])
            });
            encode(
                encoding,
                &VarianceReply {
                    version: PROTOCOL_VERSION,
                    items,
                },
            )
        }
        Endpoint::Query(QueryKind::Ray) => {
            let req: RayRequest = decode(encoding, payload)?;
            check_batch(req.rays.len(), state)?;
            for (i, r) in req.rays.iter().enumerate() {
                check_ray(i, r, state)?;
            }
            let snap = snapshot(state)?;
            let items = query::par_map(&req.rays, state.batch_threads, |r| query::ray(&snap, r));
            encode(
                encoding,
                &RayReply {
                    version: PROTOCOL_VERSION,
                    items,
                },
            )
        }
        Endpoint::Query(QueryKind::Grid) => {
            let req: GridRequest = decode(encoding, payload)?;
            encode(encoding, &grid(&req, state)?)
        }
        Endpoint::Query(QueryKind::View) => {
            let req: ViewRequest = decode(encoding, payload)?;
            encode(encoding, &view(&req, state)?)
        }
        Endpoint::Query(QueryKind::Sources) => {
            let req: SourcesRequest = decode(encoding, payload)?;
            check_points(&req.points, state)?;
            let items = match state.site_sources.load_full() {
                Some(site) => req.points.iter().map(|p| site.at(p[0], p[1])).collect(),
                None => {
                    let snap = snapshot(state)?;
                    req.points
                        .iter()
                        .map(|p| own_cell(state, &snap, p[0], p[1]))
                        .collect()
                }
            };
            encode(
                encoding,
                &SourcesReply {
                    version: PROTOCOL_VERSION,
                    items,
                },
            )
        }
        Endpoint::Query(QueryKind::Slope) => {
            let req: SlopeRequest = decode(encoding, payload)?;
            let snap = snapshot(state)?;
            let model = layer_model(req.robot, state, &snap)?;
            let samples = crate::map::grid::samples_per_point(&model);
            check_batch(req.points.len().saturating_mul(samples), state)?;
            check_points(&req.points, state)?;
            let reply = crate::map::grid::slopes(&snap, &req.points, &model, state.batch_threads);
            encode(encoding, &reply)
        }
    }
}

/// A robot's own aggregate cell under map (x, y), as `query/sources` gives it (none where it
/// holds no cell).
fn own_cell(state: &DaemonState, snap: &crate::map::MapSnapshot, x: f64, y: f64) -> Vec<RobotCell> {
    let Some(world) = &snap.aggregate else {
        return Vec::new();
    };
    world
        .cells()
        .get(&world.cell_of(x, y))
        .map(|cell| RobotCell {
            robot: state.keys.map_id().to_owned(),
            z_m: cell.z,
            var_m2: cell.var,
            scans: cell.scans,
            newest_scan_ns: world.newest_scan().map_or(0, |s| s.stamp_ns),
        })
        .into_iter()
        .collect()
}

/// The pixels of a validated view request: one ray each, cast like a ray query.
fn view(req: &ViewRequest, state: &DaemonState) -> Result<ViewReply, Failure> {
    // Before any ray is built: a 100 000 × 100 000 camera is a few bytes of request.
    check_batch(usize::try_from(req.camera.pixels()).unwrap_or(usize::MAX), state)?;
    let (rows, cols, rays) = crate::map::view::view_rays(req).map_err(|reason| Failure {
        code: ErrorCode::InvalidArgument,
        message: format!("view: {reason}"),
    })?;
    for (i, r) in rays.iter().enumerate() {
        check_ray(i, r, state)?;
    }
    let snap = snapshot(state)?;
    let items = query::par_map(&rays, state.batch_threads, |r| query::ray(&snap, r));
    Ok(ViewReply {
        version: PROTOCOL_VERSION,
        rows,
        cols,
        range_m: items.iter().map(|i| i.range_m.map(|r| r as f32)).collect(),
        sigma_m: items
            .iter()
            .map(|i| i.range_var_m2.map(|v| v.max(0.0).sqrt() as f32))
            .collect(),
        hit_probability: items
            .iter()
            .map(|i| i.hit_probability.map(|p| p as f32))
            .collect(),
        source: items.iter().map(|i| i.source).collect(),
        provenance: items.iter().map(|i| i.provenance).collect(),
    })
}

/// The robot `requested` for a layer query, else the daemon's, with `snap`'s error model.
fn layer_model(
    requested: Option<RobotModel>,
    state: &DaemonState,
    snap: &MapSnapshot,
) -> Result<LayerModel, Failure> {
    let robot = requested.unwrap_or(state.robot);
    if let Some(reason) = robot.problem() {
        return fail(ErrorCode::InvalidArgument, format!("robot: {reason}"));
    }
    Ok(LayerModel::new(robot, snap))
}

/// The layers of a validated grid request: cell centres evaluated like elevation queries, the
/// derived layers over the robot's footprint around each.
fn grid(req: &GridRequest, state: &DaemonState) -> Result<GridReply, Failure> {
    let Some((cols, rows)) = req.shape() else {
        return fail(
            ErrorCode::InvalidArgument,
            "grid: min_m below max_m, both finite, and resolution_m positive",
        );
    };
    let snap = snapshot(state)?;
    let model = layer_model(req.robot, state, &snap)?;
    let res = req.resolution_m;
    let derived = !req.layers.is_empty();
    if derived && res > model.robot.footprint_radius_m {
        return fail(
            ErrorCode::InvalidArgument,
            format!(
                "grid: layers need resolution_m ≤ the footprint radius ({} m): a coarser grid \
                 samples too few points of the footprint",
                model.robot.footprint_radius_m
            ),
        );
    }
    if derived && model.robot.footprint_radius_m / res > MAX_FOOTPRINT_REACH {
        return fail(
            ErrorCode::InvalidArgument,
            format!(
                "grid: layers need resolution_m ≥ the footprint radius / {MAX_FOOTPRINT_REACH} \
                 ({} m): a finer grid makes every cell's footprint too large to evaluate",
                model.robot.footprint_radius_m / MAX_FOOTPRINT_REACH
            ),
        );
    }
    let margin = if derived {
        footprint_reach(model.robot.footprint_radius_m, res) as u64
    } else {
        0
    };
    let evaluated = (cols + 2 * margin).saturating_mul(rows + 2 * margin);
    if evaluated > state.max_batch as u64 {
        return fail(
            ErrorCode::BatchTooLarge,
            format!(
                "grid of {cols} × {rows} cells ({evaluated} with the footprint margin) exceeds \
                 the limit of {} cells",
                state.max_batch
            ),
        );
    }
    let grid_box = GridBox {
        origin_m: [req.min_m[0] + res / 2.0, req.min_m[1] + res / 2.0],
        resolution_m: res,
        cols: cols as usize,
        rows: rows as usize,
    };
    Ok(crate::map::grid::grid(
        &snap,
        &grid_box,
        &req.layers,
        &model,
        state.batch_threads,
    ))
}

fn decode<T: DeserializeOwned>(encoding: Encoding, payload: &[u8]) -> Result<T, Failure> {
    if encoding == Encoding::Bincode && looks_like_json(payload) {
        return fail(
            ErrorCode::MalformedRequest,
            "the payload is JSON but labelled bincode (or not labelled): set the encoding to application/json",
        );
    }
    let version = codec::peek_version(encoding, payload);
    if version.is_some_and(|v| v != PROTOCOL_VERSION) {
        return fail(
            ErrorCode::UnsupportedVersion,
            format!(
                "protocol version {} not supported (daemon speaks {PROTOCOL_VERSION})",
                version.unwrap_or(0)
            ),
        );
    }
    codec::decode(encoding, payload).or_else(|e| {
        fail(
            ErrorCode::MalformedRequest,
            format!("cannot decode the request ({encoding:?}): {e}"),
        )
    })
}

/// Whether a payload is a JSON object or array (a bincode request starts with its version, a
/// small varint, never with `{` or `[`).
fn looks_like_json(payload: &[u8]) -> bool {
    let first = payload.iter().find(|b| !b.is_ascii_whitespace());
    matches!(first, Some(b'{' | b'[')) && serde_json::from_slice::<serde::de::IgnoredAny>(payload).is_ok()
}

fn encode<T: Serialize>(encoding: Encoding, value: &T) -> Result<Vec<u8>, Failure> {
    codec::encode(encoding, value)
        .or_else(|e| fail(ErrorCode::Internal, format!("cannot encode the reply: {e}")))
}

fn snapshot(state: &DaemonState) -> Result<std::sync::Arc<crate::map::MapSnapshot>, Failure> {
    let snap = state.snapshot.load_full();
    // A restarted daemon answers from its restored aggregate before the first new scan.
    if snap.maps().is_empty() && snap.aggregate.as_ref().is_none_or(|a| a.is_empty()) {
        return fail(ErrorCode::NoMap, "no scan has been mapped yet");
    }
    Ok(snap)
}

fn check_batch(len: usize, state: &DaemonState) -> Result<(), Failure> {
    if len > state.max_batch {
        return fail(
            ErrorCode::BatchTooLarge,
            format!("batch of {len} exceeds the limit of {}", state.max_batch),
        );
    }
    Ok(())
}

fn check_points(points: &[[f64; 2]], state: &DaemonState) -> Result<(), Failure> {
    check_batch(points.len(), state)?;
    match points.iter().position(|p| !p[0].is_finite() || !p[1].is_finite()) {
        Some(i) => fail(ErrorCode::InvalidArgument, format!("point {i} is not finite")),
        None => Ok(()),
    }
}

fn check_ray(i: usize, r: &Ray, state: &DaemonState) -> Result<(), Failure> {
    let finite = r.origin_m.iter().chain(&r.direction).all(|v| v.is_finite());
    let norm = r.direction.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !finite || norm < 1e-9 {
        return fail(
            ErrorCode::InvalidArgument,
            format!("ray {i}: origin and direction must be finite, direction non-zero"),
        );
    }
    let in_range = r.max_range_m.is_finite() && r.max_range_m > 0.0 && r.max_range_m <= state.max_ray_range_m;
    if !in_range {
        return fail(
            ErrorCode::InvalidArgument,
            format!("ray {i}: max_range_m must be in (0, {}]", state.max_ray_range_m),
        );
    }
    Ok(())
}

fn status(state: &DaemonState) -> StatusReply {
    let m = &state.metrics;
    let snap = state.snapshot.load();
    StatusReply {
        version: PROTOCOL_VERSION,
        map_id: state.keys.map_id().to_owned(),
        uptime_s: m.uptime_s(),
        scans_received: m.received.load(Relaxed),
        scans_accepted: m.accepted.load(Relaxed),
        scans_rejected: m.rejected_total(),
        rejections: m.rejections(),
        scans_skipped: m.skipped.load(Relaxed),
        hyperparameter_updates: m.hyper_updates.load(Relaxed),
        jittered_tiles: m.jittered_tiles.load(Relaxed),
        sequence_gaps: m.sequence_gaps.load(Relaxed),
        ingest: IngestInfo {
            connected: m.ingest_connected.load(Relaxed),
            error: m.ingest_error(),
            retries: m.ingest_retries.load(Relaxed),
            publisher_restarts: m.publisher_restarts.load(Relaxed),
            relocations: m.relocations.load(Relaxed),
        },
        window_len: snap.maps().len() as u32,
        window_capacity: state.window_capacity as u32,
        aggregate: AggregateInfo {
            enabled: state.aggregate_radius_m.is_some(),
            cells: snap.aggregate.as_ref().map_or(0, |a| a.len() as u64),
            tiles: snap.aggregate.as_ref().map_or(0, |a| a.tiles() as u64),
            radius_m: state.aggregate_radius_m.unwrap_or(0.0),
            inserts: m.aggregate_inserts.load(Relaxed),
            skipped: m.aggregate_skipped.load(Relaxed),
            failed: m.aggregate_failed.load(Relaxed),
            evicted_tiles: m.aggregate_evicted_tiles.load(Relaxed),
            reach_m: m.aggregate_reach_mm.load(Relaxed) as f64 * 1e-3,
            paged_out: m.aggregate_paged_out.load(Relaxed),
            paged_in: m.aggregate_paged_in.load(Relaxed),
            page_failures: m.aggregate_page_failures.load(Relaxed),
            ledger_scans: m.ledger_scans.load(Relaxed),
            ledger_mb: m.ledger_bytes.load(Relaxed) as f64 / f64::from(1 << 20),
            changed_cells: m.changed_cells.load(Relaxed),
        },
        corrections: m.corrections.load(Relaxed),
        hyperparameters: {
            let k = state.kernel.load();
            HyperparametersInfo {
                kernel: format!("{:?}", k.family),
                variance: k.variance,
                length_scale: k.length_scale,
                nugget: state.nugget_m2,
            }
        },
        fit_ms: m.fit.summary(),
        scan_to_queryable_ms: m.scan_to_queryable.summary(),
        aggregate_insert_ms: m.aggregate_insert.summary(),
        query_ms: m.query_latencies(),
        queries_ok: m.queries_ok.load(Relaxed),
        queries_failed: m.queries_failed.load(Relaxed),
        queries_expired: m.queries_expired.load(Relaxed),
        replies_dropped: m.replies_dropped.load(Relaxed),
        rss_mb: crate::metrics::rss_mb(),
        fleet: state
            .fleet
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone(),
    }
}
