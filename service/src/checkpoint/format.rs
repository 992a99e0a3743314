//! The checkpoint file layout, little-endian:
//!
//! | bytes | field |
//! |---|---|
//! | 8 | magic `RGPCKPT\0` |
//! | 4 | format version ([`FORMAT_VERSION`]) |
//! | 8 | identity hash ([`super::identity`]) |
//! | 8 | payload length |
//! | n | payload: [`Checkpoint`] in bincode (the protocol's codec) |
//! | 8 | xxh3-64 of every byte before it |
//!
//! Paged-out tiles ([`super::pages`]) use the same frame with the magic `RGPTILE\0` and a
//! [`TilePage`](crate::map::aggregate::world::TilePage) payload.

use super::format3::{self, CheckpointV3};
use super::format4::{self, CheckpointV4};
use super::format5::{self, CheckpointV5};
use super::Checkpoint;
use rangegp_proto::codec::{self, Encoding, MAX_DECODE_BYTES};
use serde::de::DeserializeOwned;
use serde::Serialize;
use thiserror::Error;

/// First bytes of every checkpoint.
pub const MAGIC: [u8; 8] = *b"RGPCKPT\0";
/// Layout version; bumped when [`Checkpoint`] changes (4: the aggregate keeps where its last
/// scans stood; 5: and the departure weights each scan of its history was fused with; 6: and
/// how each cell was seen, with the learnt σ scales).
pub const FORMAT_VERSION: u32 = 6;
const HEADER_LEN: usize = 8 + 4 + 8 + 8;
const TRAILER_LEN: usize = 8;

/// Why bytes are not a checkpoint of this map.
#[derive(Debug, Error, PartialEq)]
pub enum FormatError {
    /// Shorter than header and trailer.
    #[error("{0} bytes: too short for a checkpoint")]
    TooShort(usize),
    /// The magic bytes are wrong (not a checkpoint).
    #[error("not a rangegp checkpoint (bad magic)")]
    BadMagic,
    /// Written by another format version.
    #[error("format version {found}, this daemon reads {reads}")]
    Version {
        /// Version in the file.
        found: u32,
        /// The version this daemon reads.
        reads: u32,
    },
    /// Written for another map or other aggregate settings.
    #[error("foreign checkpoint: identity {found:016x}, expected {expected:016x}")]
    Foreign {
        /// Identity in the file.
        found: u64,
        /// This daemon's identity.
        expected: u64,
    },
    /// The declared payload length does not match the file.
    #[error("payload length {declared} does not match the {actual} bytes present")]
    Length {
        /// Declared.
        declared: u64,
        /// Present.
        actual: usize,
    },
    /// The checksum does not match (a torn or corrupted file).
    #[error("checksum mismatch")]
    Checksum,
    /// The payload does not decode.
    #[error("payload: {0}")]
    Payload(String),
}

/// Encodes `checkpoint` for the map with identity `identity`.
pub fn encode(checkpoint: &Checkpoint, identity: u64) -> Result<Vec<u8>, FormatError> {
    encode_framed(MAGIC, FORMAT_VERSION, checkpoint, identity)
}

/// Decodes a checkpoint, checking magic, version, identity, length and checksum before the
/// payload is parsed; format-3, -4 and -5 ones are read too ([`super::format3`],
/// [`super::format4`], [`super::format5`]).
pub fn decode(bytes: &[u8], identity: u64) -> Result<Checkpoint, FormatError> {
    match decode_framed(MAGIC, FORMAT_VERSION, bytes, identity) {
        Err(FormatError::Version {
            found: format3::VERSION,
            ..
        }) => decode_framed::<CheckpointV3>(MAGIC, format3::VERSION, bytes, identity).map(Checkpoint::from),
        Err(FormatError::Version {
            found: format4::VERSION,
            ..
        }) => decode_framed::<CheckpointV4>(MAGIC, format4::VERSION, bytes, identity).map(Checkpoint::from),
        Err(FormatError::Version {
            found: format5::VERSION,
            ..
        }) => decode_framed::<CheckpointV5>(MAGIC, format5::VERSION, bytes, identity).map(Checkpoint::from),
        decoded => decoded,
    }
}

/// Encodes `value` in the frame above with `magic` and layout `version`, for the map with
/// identity `identity`.
pub fn encode_framed<T: Serialize>(
    magic: [u8; 8],
    version: u32,
    value: &T,
    identity: u64,
) -> Result<Vec<u8>, FormatError> {
    let payload = codec::encode(Encoding::Bincode, value).map_err(|e| FormatError::Payload(e.to_string()))?;
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len() + TRAILER_LEN);
    out.extend_from_slice(&magic);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&identity.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
    out.extend_from_slice(&payload);
    let sum = xxhash_rust::xxh3::xxh3_64(&out);
    out.extend_from_slice(&sum.to_le_bytes());
    Ok(out)
}

/// Decodes a value framed with `magic` and layout `version`, checking magic, version, identity,
/// length and checksum before the payload is parsed.
pub fn decode_framed<T: DeserializeOwned>(
    magic: [u8; 8],
    version: u32,
    bytes: &[u8],
    identity: u64,
) -> Result<T, FormatError> {
    if bytes.len() < HEADER_LEN + TRAILER_LEN {
        return Err(FormatError::TooShort(bytes.len()));
    }
    let u64_at = |at: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[at..at + 8]);
        u64::from_le_bytes(b)
    };
    if bytes[..8] != magic {
        return Err(FormatError::BadMagic);
    }
    let mut v = [0u8; 4];
    v.copy_from_slice(&bytes[8..12]);
    let found = u32::from_le_bytes(v);
    if found != version {
        return Err(FormatError::Version {
            found,
            reads: version,
        });
    }
    let found = u64_at(12);
    if found != identity {
        return Err(FormatError::Foreign {
            found,
            expected: identity,
        });
    }
    let declared = u64_at(20);
    let actual = bytes.len() - HEADER_LEN - TRAILER_LEN;
    if declared != actual as u64 || actual > MAX_DECODE_BYTES {
        return Err(FormatError::Length { declared, actual });
    }
    let body = bytes.len() - TRAILER_LEN;
    if xxhash_rust::xxh3::xxh3_64(&bytes[..body]) != u64_at(body) {
        return Err(FormatError::Checksum);
    }
    codec::decode(Encoding::Bincode, &bytes[HEADER_LEN..body])
        .map_err(|e| FormatError::Payload(e.to_string()))
}
