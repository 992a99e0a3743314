//! rangegp-transport: the Zenoh glue both ends share. Zenoh configuration from plain settings (mode, endpoints, scouting), and the Zenoh labels
//! of the protocol's encodings.

#![deny(missing_docs)]
#![forbid(unsafe_code)]

use rangegp_proto::codec::Encoding;
use std::sync::LazyLock;
use thiserror::Error;

/// The label of bincode payloads, built once.
static BINCODE_LABEL: LazyLock<zenoh::bytes::Encoding> =
    LazyLock::new(|| zenoh::bytes::Encoding::from(Encoding::Bincode.mime()));

/// The label of JSON payloads (one of Zenoh's predefined encodings).
static JSON_LABEL: LazyLock<zenoh::bytes::Encoding> =
    LazyLock::new(|| zenoh::bytes::Encoding::from(Encoding::Json.mime()));

/// The Zenoh encoding label of `encoding`: a clone of one built at first use. Building the
/// custom bincode label afresh for every message (parse plus a new schema buffer) was measured
/// at +40–55 µs of round trip per reply on a 2-core machine; a clone shares the buffer.
pub fn zenoh_encoding(encoding: Encoding) -> zenoh::bytes::Encoding {
    match encoding {
        Encoding::Bincode => BINCODE_LABEL.clone(),
        Encoding::Json => JSON_LABEL.clone(),
    }
}

/// The protocol encoding a Zenoh label names: JSON for JSON, bincode otherwise (the default).
pub fn protocol_encoding(label: &zenoh::bytes::Encoding) -> Encoding {
    if label == &*JSON_LABEL {
        Encoding::Json
    } else if label == &*BINCODE_LABEL {
        Encoding::Bincode
    } else {
        Encoding::from_mime(&label.to_string())
    }
}

/// A Zenoh configuration could not be built.
#[derive(Debug, Error)]
#[error("invalid zenoh setting {key}")]
pub struct TransportConfigError {
    /// Configuration key.
    pub key: String,
    /// Zenoh's error.
    #[source]
    pub source: zenoh::Error,
}

/// Builds a Zenoh configuration: `mode` (peer / client / router), endpoints to listen on and
/// connect to, multicast scouting on or off (off keeps traffic on the named endpoints).
pub fn zenoh_config(
    mode: &str,
    listen: &[String],
    connect: &[String],
    multicast_scouting: bool,
) -> Result<zenoh::Config, TransportConfigError> {
    let mut config = zenoh::Config::default();
    let set = |config: &mut zenoh::Config, key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|source| TransportConfigError {
                key: key.to_owned(),
                source,
            })
    };
    let list = |v: &[String]| serde_json::to_string(v).unwrap_or_else(|_| "[]".into());
    set(&mut config, "mode", serde_json::Value::from(mode).to_string())?;
    set(&mut config, "listen/endpoints", list(listen))?;
    set(&mut config, "connect/endpoints", list(connect))?;
    set(
        &mut config,
        "scouting/multicast/enabled",
        multicast_scouting.to_string(),
    )?;
    Ok(config)
}

/// A loopback TCP port held for a listener that is about to start: a bound, not listening,
/// `SO_REUSEADDR` socket. While it is held the kernel hands the port to no other `bind(0)` and no
/// outgoing connection, yet a listener that also sets `SO_REUSEADDR` (Zenoh's TCP link does) may
/// bind it, in this process or a child. Drop it once the listener is up. Probing a free port and
/// releasing it before the listener binds left a window in which a parallel test took the port.
#[derive(Debug)]
pub struct ReservedEndpoint {
    _socket: socket2::Socket,
    port: u16,
    endpoint: String,
}

impl ReservedEndpoint {
    /// The Zenoh endpoint of the held port, `tcp/127.0.0.1:<port>`.
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// The held port (for configuration files that name it apart from the address).
    pub fn port(&self) -> u16 {
        self.port
    }
}

/// Holds a loopback TCP port the OS just handed out, for demos and tests that must not collide
/// with each other or with a running daemon (see [`ReservedEndpoint`]).
pub fn reserve_loopback_endpoint() -> std::io::Result<ReservedEndpoint> {
    use socket2::{Domain, Protocol, Socket, Type};
    let socket = Socket::new(Domain::IPV4, Type::STREAM, Some(Protocol::TCP))?;
    socket.set_reuse_address(true)?;
    socket.bind(&std::net::SocketAddr::from(([127, 0, 0, 1], 0)).into())?;
    let port = socket
        .local_addr()?
        .as_socket()
        .ok_or_else(|| std::io::Error::other("a TCP socket without an IP address"))?
        .port();
    Ok(ReservedEndpoint {
        _socket: socket,
        port,
        endpoint: format!("tcp/127.0.0.1:{port}"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_reserved_port_takes_a_listener_and_no_second_reservation() {
        let reserved = reserve_loopback_endpoint().expect("reserve");
        let port = reserved.port();
        assert_eq!(reserved.endpoint(), format!("tcp/127.0.0.1:{port}"));
        let others: Vec<ReservedEndpoint> = (0..64)
            .map(|_| reserve_loopback_endpoint().expect("reserve"))
            .collect();
        assert!(others.iter().all(|o| o.endpoint() != reserved.endpoint()));
        // std's listener sets SO_REUSEADDR, as Zenoh's does: it binds the held port.
        let listener = std::net::TcpListener::bind(("127.0.0.1", port)).expect("listen");
        let _client = std::net::TcpStream::connect(("127.0.0.1", port)).expect("connect");
        listener.accept().expect("accept");
    }
}
