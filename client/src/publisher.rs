//! Zero-copy scan publishing over iceoryx2: loan a slice in shared memory, write, send.

use iceoryx2::prelude::*;
use rangegp_proto::scan::{node_builder, open_scan_service, ScanHeader, ScanPoint, ScanServiceError};
use thiserror::Error;

/// The publisher could not be created or a scan could not be sent. iceoryx2's own error is
/// kept as the source.
#[derive(Debug, Error)]
pub enum PublishError {
    /// The service name is not a valid iceoryx2 service name.
    #[error("invalid iceoryx2 service name {name:?}")]
    ServiceName {
        /// Name given.
        name: String,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::service::service_name::ServiceNameError,
    },
    /// The iceoryx2 node could not be created (shared memory or permissions).
    #[error("cannot create the iceoryx2 node")]
    Node(#[source] iceoryx2::node::NodeCreationFailure),
    /// The scan service could not be opened or created (another party created it with
    /// different settings or types).
    #[error("cannot open the scan service")]
    Service(#[source] ScanServiceError),
    /// The publisher port could not be created (too many publishers on the service).
    #[error("cannot create the publisher")]
    Publisher(#[source] iceoryx2::port::publisher::PublisherCreateError),
    /// No shared-memory sample could be loaned (all in flight, or the scan is too large).
    #[error("cannot loan a sample of {points} points")]
    Loan {
        /// Points requested.
        points: usize,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::port::LoanError,
    },
    /// The sample could not be delivered.
    #[error("send failed")]
    Send(#[source] iceoryx2::port::SendError),
}

/// Publishes scans to the daemon through shared memory.
pub struct ScanPublisher {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, [ScanPoint], ScanHeader>,
    publisher_id: u64,
    next_sequence: u64,
    _service: rangegp_proto::scan::ScanService,
    _node: Node<ipc::Service>,
}

impl std::fmt::Debug for ScanPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ScanPublisher")
            .field("publisher_id", &self.publisher_id)
            .field("next_sequence", &self.next_sequence)
            .finish()
    }
}

impl ScanPublisher {
    /// Opens `service_name` and creates a publisher sized for `max_points` per scan (it grows by
    /// powers of two if a larger scan comes).
    pub fn new(service_name: &str, publisher_id: u64, max_points: usize) -> Result<Self, PublishError> {
        let name = ServiceName::new(service_name).map_err(|source| PublishError::ServiceName {
            name: service_name.to_owned(),
            source,
        })?;
        let node = node_builder()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<ipc::Service>()
            .map_err(PublishError::Node)?;
        let service = open_scan_service(&node, &name).map_err(PublishError::Service)?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(max_points.max(1))
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .max_loaned_samples(2)
            .create()
            .map_err(PublishError::Publisher)?;
        Ok(Self {
            publisher,
            publisher_id,
            next_sequence: 1,
            _service: service,
            _node: node,
        })
    }

    /// The sequence number the next [`ScanPublisher::publish`] will use (the first is 1).
    pub fn next_sequence(&self) -> u64 {
        self.next_sequence
    }

    /// Publishes one scan: fills in version, publisher id, point count and the next sequence
    /// number, then sends `points` zero-copy. Returns the sequence number used.
    pub fn publish(&mut self, header: ScanHeader, points: &[ScanPoint]) -> Result<u64, PublishError> {
        let sequence = self.next_sequence;
        let header = ScanHeader {
            protocol_version: rangegp_proto::PROTOCOL_VERSION,
            publisher_id: self.publisher_id,
            sequence,
            point_count: u32::try_from(points.len()).unwrap_or(u32::MAX),
            ..header
        };
        self.publish_raw(header, points)?;
        self.next_sequence += 1;
        Ok(sequence)
    }

    /// Sends `header` and `points` exactly as given (no field filled in): for tools and tests
    /// that must produce malformed scans.
    pub fn publish_raw(&self, header: ScanHeader, points: &[ScanPoint]) -> Result<(), PublishError> {
        let mut sample =
            self.publisher
                .loan_slice_uninit(points.len())
                .map_err(|source| PublishError::Loan {
                    points: points.len(),
                    source,
                })?;
        *sample.user_header_mut() = header;
        let sample = sample.write_from_fn(|i| points[i]);
        sample.send().map_err(PublishError::Send)?;
        Ok(())
    }
}
