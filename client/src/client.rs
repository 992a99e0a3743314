//! Typed Zenoh client: one method per query, each bounded by a timeout.

use rangegp_proto::codec::{self, CodecError, Encoding};
use rangegp_proto::keys::{InvalidMapId, MapKeys, QueryKind};
use rangegp_proto::msg::*;
use rangegp_proto::PROTOCOL_VERSION;
use rangegp_transport::{zenoh_config, TransportConfigError};
use serde::{de::DeserializeOwned, Serialize};
use std::time::{Duration, Instant};
use thiserror::Error;
use zenoh::query::QueryTarget;
use zenoh::Wait;

/// A query failed.
#[derive(Debug, Error)]
pub enum ClientError {
    /// The map id cannot be used in a key expression.
    #[error(transparent)]
    MapId(#[from] InvalidMapId),
    /// The Zenoh configuration is invalid.
    #[error(transparent)]
    Config(#[from] TransportConfigError),
    /// Zenoh could not open a session, declare a subscriber or send the query.
    #[error("zenoh could not {action}")]
    Transport {
        /// What the client was doing.
        action: &'static str,
        /// Zenoh's error.
        #[source]
        source: zenoh::Error,
    },
    /// No daemon answered within the timeout (none running, or not reachable yet).
    #[error("no reply from the daemon within {0:?}")]
    Timeout(Duration),
    /// The daemon answered with an error.
    #[error("daemon refused the query ({code:?}): {message}")]
    Server {
        /// Error class.
        code: ErrorCode,
        /// Detail.
        message: String,
    },
    /// The reply could not be decoded.
    #[error("undecodable reply: {0}")]
    Codec(#[from] CodecError),
    /// The reply has the wrong number of items.
    #[error("reply has {got} items for {sent} requested")]
    BatchMismatch {
        /// Items requested.
        sent: usize,
        /// Items received.
        got: usize,
    },
}

/// Builder of a [`Client`].
#[derive(Debug, Clone)]
pub struct ClientBuilder {
    map_id: String,
    connect: Vec<String>,
    mode: String,
    timeout: Duration,
    encoding: Encoding,
    config_file: Option<std::path::PathBuf>,
}

impl ClientBuilder {
    /// A full Zenoh JSON5 configuration (TLS certificates, router endpoints); when set,
    /// [`ClientBuilder::connect`] and [`ClientBuilder::mode`] are ignored. See
    /// `deploy/zenoh-planner.json5`.
    pub fn config_file(mut self, path: impl Into<std::path::PathBuf>) -> Self {
        self.config_file = Some(path.into());
        self
    }

    /// Endpoints to connect to (for example `tcp/127.0.0.1:7447`).
    pub fn connect(mut self, endpoints: impl IntoIterator<Item = impl Into<String>>) -> Self {
        self.connect = endpoints.into_iter().map(Into::into).collect();
        self
    }

    /// Per-query timeout (default 10 s).
    pub fn timeout(mut self, timeout: Duration) -> Self {
        self.timeout = timeout;
        self
    }

    /// Payload encoding (default bincode).
    pub fn encoding(mut self, encoding: Encoding) -> Self {
        self.encoding = encoding;
        self
    }

    /// Zenoh mode of the client session (default `client`: a planner connects to the daemon or a
    /// router and routes for no one; `peer` joins a peer mesh).
    pub fn mode(mut self, mode: impl Into<String>) -> Self {
        self.mode = mode.into();
        self
    }

    /// Opens the Zenoh session (blocking).
    pub fn open(self) -> Result<Client, ClientError> {
        let keys = MapKeys::new(&self.map_id)?;
        let config = match &self.config_file {
            Some(path) => zenoh::Config::from_file(path).map_err(|source| ClientError::Transport {
                action: "read the zenoh config file",
                source,
            })?,
            None => zenoh_config(&self.mode, &[], &self.connect, false)?,
        };
        let session = zenoh::open(config)
            .wait()
            .map_err(|source| ClientError::Transport {
                action: "open a session",
                source,
            })?;
        Ok(Client {
            session,
            keys,
            timeout: self.timeout,
            encoding: self.encoding,
        })
    }
}

/// A connection to one map of a rangegp daemon.
#[derive(Debug, Clone)]
pub struct Client {
    session: zenoh::Session,
    keys: MapKeys,
    timeout: Duration,
    encoding: Encoding,
}

impl Client {
    /// Starts building a client for `map_id`.
    pub fn builder(map_id: impl Into<String>) -> ClientBuilder {
        ClientBuilder {
            map_id: map_id.into(),
            connect: Vec::new(),
            mode: "client".into(),
            timeout: Duration::from_secs(10),
            encoding: Encoding::Bincode,
            config_file: None,
        }
    }

    /// Waits until the daemon's liveliness token is visible (its queryables are routed).
    pub fn wait_for_daemon(&self, timeout: Duration) -> Result<(), ClientError> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let replies = self
                .session
                .liveliness()
                .get(self.keys.alive())
                .timeout(left.min(Duration::from_millis(500)))
                .wait()
                .map_err(|source| ClientError::Transport {
                    action: "query liveliness",
                    source,
                })?;
            // Only a token counts: an error reply (an access-control refusal, say) is not the
            // daemon.
            if replies.iter().any(|reply| reply.result().is_ok()) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                return Err(ClientError::Timeout(timeout));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Elevation at map (x, y) points.
    pub fn elevation(&self, points: &[[f64; 2]]) -> Result<Vec<ElevationItem>, ClientError> {
        let req = ElevationRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
        };
        let rep: ElevationReply = self.call(&self.keys.query(QueryKind::Elevation), &req)?;
        check_len(points.len(), rep.items)
    }

    /// Elevation variance at map (x, y) points.
    pub fn variance(&self, points: &[[f64; 2]]) -> Result<Vec<VarianceItem>, ClientError> {
        let req = VarianceRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
        };
        let rep: VarianceReply = self.call(&self.keys.query(QueryKind::Variance), &req)?;
        check_len(points.len(), rep.items)
    }

    /// Casts rays through the map.
    pub fn ray(&self, rays: &[Ray]) -> Result<Vec<RayItem>, ClientError> {
        let req = RayRequest {
            version: PROTOCOL_VERSION,
            rays: rays.to_vec(),
        };
        let rep: RayReply = self.call(&self.keys.query(QueryKind::Ray), &req)?;
        check_len(rays.len(), rep.items)
    }

    /// A range image (σ, hit probability, source and provenance per pixel) of the map as the
    /// sensor `req` describes would see it from its pose (`query/view`).
    pub fn view(&self, req: &ViewRequest) -> Result<ViewReply, ClientError> {
        let rep: ViewReply = self.call(&self.keys.query(QueryKind::View), req)?;
        let pixels = rep.rows as usize * rep.cols as usize;
        if rep.range_m.len() != pixels {
            return Err(ClientError::BatchMismatch {
                sent: pixels,
                got: rep.range_m.len(),
            });
        }
        Ok(rep)
    }

    /// Elevation and variance layers over the box `min_m`..`max_m` at `resolution_m`.
    pub fn grid(
        &self,
        min_m: [f64; 2],
        max_m: [f64; 2],
        resolution_m: f64,
    ) -> Result<GridReply, ClientError> {
        self.grid_request(&GridRequest {
            version: PROTOCOL_VERSION,
            min_m,
            max_m,
            resolution_m,
            layers: Vec::new(),
            robot: None,
        })
    }

    /// A grid with the planner layers `req.layers` (slope, σ, roughness, step, risk, cost) for
    /// `req.robot` (or the daemon's robot); the resolution must not exceed the footprint radius.
    pub fn grid_request(&self, req: &GridRequest) -> Result<GridReply, ClientError> {
        let rep: GridReply = self.call(&self.keys.query(QueryKind::Grid), req)?;
        let cells = rep.cols as usize * rep.rows as usize;
        let costmap = req.layers.contains(&Layer::Cost).then_some(rep.costmap.len());
        let lens = [rep.elevation_m.len(), rep.variance_m2.len()]
            .into_iter()
            .chain(rep.layers.iter().map(|l| l.values.len()))
            .chain(costmap);
        for got in lens {
            if got != cells {
                return Err(ClientError::BatchMismatch { sent: cells, got });
            }
        }
        Ok(rep)
    }

    /// Slope, its σ, aspect, normal and slope risk at map (x, y) points, over the footprint of
    /// `robot` (or the daemon's robot).
    pub fn slope(&self, points: &[[f64; 2]], robot: Option<RobotModel>) -> Result<SlopeReply, ClientError> {
        let req = SlopeRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
            robot,
        };
        let mut rep: SlopeReply = self.call(&self.keys.query(QueryKind::Slope), &req)?;
        rep.items = check_len(points.len(), rep.items)?;
        Ok(rep)
    }

    /// Corrects the poses of past scans (a loop closure, a relocalisation): the window's maps
    /// and the aggregate move; the reply comes once queries see the corrected map. Give the
    /// client a timeout of a few seconds: a correction over a long trajectory takes up to ~1 s.
    pub fn correct(&self, corrections: &[PoseCorrection]) -> Result<CorrectionReply, ClientError> {
        self.call(
            &self.keys.corrections(),
            &CorrectionRequest {
                version: PROTOCOL_VERSION,
                corrections: corrections.to_vec(),
            },
        )
    }

    /// The daemon's counters.
    pub fn status(&self) -> Result<StatusReply, ClientError> {
        self.call(
            &self.keys.status(),
            &StatusRequest {
                version: PROTOCOL_VERSION,
            },
        )
    }

    /// Async form of [`Client::elevation`].
    pub async fn elevation_async(&self, points: &[[f64; 2]]) -> Result<Vec<ElevationItem>, ClientError> {
        let req = ElevationRequest {
            version: PROTOCOL_VERSION,
            points: points.to_vec(),
        };
        let rep: ElevationReply = self
            .call_async(&self.keys.query(QueryKind::Elevation), &req)
            .await?;
        check_len(points.len(), rep.items)
    }

    /// Async form of [`Client::status`].
    pub async fn status_async(&self) -> Result<StatusReply, ClientError> {
        self.call_async(
            &self.keys.status(),
            &StatusRequest {
                version: PROTOCOL_VERSION,
            },
        )
        .await
    }

    /// Sends raw bytes to `rangegp/<map>/query/<kind>` and returns the raw reply (for tools and
    /// tests of the daemon's error handling).
    pub fn call_raw(
        &self,
        key: &str,
        payload: Vec<u8>,
        encoding: Encoding,
    ) -> Result<Result<Vec<u8>, ErrorReply>, ClientError> {
        let replies = self
            .session
            .get(key)
            .payload(payload)
            .encoding(rangegp_transport::zenoh_encoding(encoding))
            .target(QueryTarget::AllComplete)
            .timeout(self.timeout)
            .wait()
            .map_err(|source| ClientError::Transport {
                action: "send the query",
                source,
            })?;
        let reply = replies.recv().map_err(|_| ClientError::Timeout(self.timeout))?;
        decode_reply(reply, encoding)
    }

    /// Sends `payload` to the daemon's bare echo queryable and returns what came back (the
    /// transport's round trip without any map work).
    pub fn echo(&self, payload: Vec<u8>) -> Result<Vec<u8>, ClientError> {
        match self.call_raw(&self.keys.echo(), payload, Encoding::Bincode)? {
            Ok(bytes) => Ok(bytes),
            Err(e) => Err(e.into()),
        }
    }

    /// Calls `on_update` with every [`MapUpdate`] the daemon publishes (a scan's map answering
    /// queries); undecodable events are skipped. Dropping the subscriber stops the calls.
    pub fn subscribe_map_updates(
        &self,
        on_update: impl Fn(MapUpdate) + Send + Sync + 'static,
    ) -> Result<zenoh::pubsub::Subscriber<()>, ClientError> {
        self.subscribe(self.keys.map_updates(), on_update)
    }

    /// Calls `on_change` with every [`ChangeEvent`] the daemon publishes (aggregate cells
    /// replaced by disagreeing scans: something appeared, left or moved); drop the subscriber to
    /// stop.
    pub fn subscribe_changes(
        &self,
        on_change: impl Fn(ChangeEvent) + Send + Sync + 'static,
    ) -> Result<zenoh::pubsub::Subscriber<()>, ClientError> {
        self.subscribe(self.keys.changes(), on_change)
    }

    /// Calls `on_event` with every event of type `T` published (bincode) on `key`; samples that
    /// do not decode (another protocol version) are skipped.
    fn subscribe<T: DeserializeOwned>(
        &self,
        key: String,
        on_event: impl Fn(T) + Send + Sync + 'static,
    ) -> Result<zenoh::pubsub::Subscriber<()>, ClientError> {
        self.session
            .declare_subscriber(key)
            .callback(move |sample| {
                let bytes = sample.payload().to_bytes();
                if let Ok(event) = codec::decode::<T>(Encoding::Bincode, &bytes) {
                    on_event(event);
                }
            })
            .wait()
            .map_err(|source| ClientError::Transport {
                action: "declare a subscriber",
                source,
            })
    }

    /// The keys of the map this client talks to.
    pub fn keys(&self) -> &MapKeys {
        &self.keys
    }

    /// The Zenoh session (for the fleet queries beside this module).
    pub(crate) fn session(&self) -> &zenoh::Session {
        &self.session
    }

    pub(crate) fn call<Q: Serialize, R: DeserializeOwned>(
        &self,
        key: &str,
        req: &Q,
    ) -> Result<R, ClientError> {
        let payload = codec::encode(self.encoding, req)?;
        match self.call_raw(key, payload, self.encoding)? {
            Ok(bytes) => Ok(codec::decode(self.encoding, &bytes)?),
            Err(e) => Err(e.into()),
        }
    }

    async fn call_async<Q: Serialize, R: DeserializeOwned>(
        &self,
        key: &str,
        req: &Q,
    ) -> Result<R, ClientError> {
        let payload = codec::encode(self.encoding, req)?;
        let replies = self
            .session
            .get(key)
            .payload(payload)
            .encoding(rangegp_transport::zenoh_encoding(self.encoding))
            .target(QueryTarget::AllComplete)
            .timeout(self.timeout)
            .await
            .map_err(|source| ClientError::Transport {
                action: "send the query",
                source,
            })?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| ClientError::Timeout(self.timeout))?;
        match decode_reply(reply, self.encoding)? {
            Ok(bytes) => Ok(codec::decode(self.encoding, &bytes)?),
            Err(e) => Err(e.into()),
        }
    }
}

impl From<ErrorReply> for ClientError {
    fn from(e: ErrorReply) -> Self {
        ClientError::Server {
            code: e.code,
            message: e.message,
        }
    }
}

fn decode_reply(
    reply: zenoh::query::Reply,
    encoding: Encoding,
) -> Result<Result<Vec<u8>, ErrorReply>, ClientError> {
    match reply.result() {
        Ok(sample) => Ok(Ok(sample.payload().to_bytes().into_owned())),
        Err(err) => {
            let bytes = err.payload().to_bytes();
            Ok(Err(codec::decode::<ErrorReply>(encoding, &bytes)?))
        }
    }
}

fn check_len<T>(sent: usize, items: Vec<T>) -> Result<Vec<T>, ClientError> {
    if items.len() == sent {
        Ok(items)
    } else {
        Err(ClientError::BatchMismatch {
            sent,
            got: items.len(),
        })
    }
}
