//! The one encode / decode pair of the query protocol: bincode 2 (default) or JSON.
//!
//! bincode is pinned at 2.0.1 (3.0.0 is a deliberate compile error upstream) and lives only here,
//! so it can be swapped without touching any caller.

use serde::{de::DeserializeOwned, Deserialize, Serialize};
use thiserror::Error;

/// MIME type of bincode payloads (`bincode::config::standard()`, varint integers).
pub const BINCODE_MIME: &str = "application/x-bincode";
/// MIME type of JSON payloads.
pub const JSON_MIME: &str = "application/json";
/// Largest payload a decoder accepts, bytes (bounds allocation on hostile input).
pub const MAX_DECODE_BYTES: usize = 64 << 20;

/// Payload encoding of a request; replies use the request's encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Encoding {
    /// bincode 2, standard configuration.
    #[default]
    Bincode,
    /// UTF-8 JSON.
    Json,
}

impl Encoding {
    /// Picks the encoding from a MIME string: JSON for `application/json` (with or without a
    /// `;schema` suffix), bincode for anything else.
    pub fn from_mime(mime: &str) -> Self {
        if mime.split(';').next().map(str::trim) == Some(JSON_MIME) {
            Encoding::Json
        } else {
            Encoding::Bincode
        }
    }

    /// The MIME string to label payloads with.
    pub fn mime(self) -> &'static str {
        match self {
            Encoding::Bincode => BINCODE_MIME,
            Encoding::Json => JSON_MIME,
        }
    }
}

/// Why a payload could not be encoded or decoded.
#[derive(Debug, Error)]
pub enum CodecError {
    /// The payload exceeds [`MAX_DECODE_BYTES`].
    #[error("payload of {0} bytes exceeds the {MAX_DECODE_BYTES}-byte limit")]
    TooLarge(usize),
    /// bincode could not encode the value (a type serde cannot express in bincode).
    #[error("bincode: {0}")]
    BincodeEncode(bincode::error::EncodeError),
    /// bincode rejected the payload (its reason is part of the message peers receive).
    #[error("bincode: {0}")]
    BincodeDecode(bincode::error::DecodeError),
    /// JSON rejected the payload.
    #[error("json: {0}")]
    Json(#[from] serde_json::Error),
    /// The payload decoded but left bytes over.
    #[error("{0} trailing bytes after the message")]
    TrailingBytes(usize),
}

fn bincode_config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_DECODE_BYTES>()
}

/// Encodes `value` in `encoding`.
pub fn encode<T: Serialize>(encoding: Encoding, value: &T) -> Result<Vec<u8>, CodecError> {
    match encoding {
        Encoding::Bincode => {
            bincode::serde::encode_to_vec(value, bincode_config()).map_err(CodecError::BincodeEncode)
        }
        Encoding::Json => Ok(serde_json::to_vec(value)?),
    }
}

/// Decodes a whole payload in `encoding` (trailing bytes are an error).
pub fn decode<T: DeserializeOwned>(encoding: Encoding, bytes: &[u8]) -> Result<T, CodecError> {
    if bytes.len() > MAX_DECODE_BYTES {
        return Err(CodecError::TooLarge(bytes.len()));
    }
    match encoding {
        Encoding::Bincode => {
            let (value, used) = bincode::serde::decode_from_slice(bytes, bincode_config())
                .map_err(CodecError::BincodeDecode)?;
            if used != bytes.len() {
                return Err(CodecError::TrailingBytes(bytes.len() - used));
            }
            Ok(value)
        }
        Encoding::Json => Ok(serde_json::from_slice(bytes)?),
    }
}

/// Reads only the leading protocol version of any message, so that a request from another
/// version is answered "unsupported version" rather than "malformed".
pub fn peek_version(encoding: Encoding, bytes: &[u8]) -> Option<u32> {
    #[derive(Deserialize)]
    struct VersionOnly {
        version: u32,
    }
    match encoding {
        Encoding::Bincode => bincode::serde::decode_from_slice::<u32, _>(bytes, bincode_config())
            .ok()
            .map(|(v, _)| v),
        Encoding::Json => serde_json::from_slice::<VersionOnly>(bytes)
            .ok()
            .map(|v| v.version),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::*;
    use crate::PROTOCOL_VERSION;

    fn sample() -> ElevationReply {
        ElevationReply {
            version: PROTOCOL_VERSION,
            items: vec![
                ElevationItem {
                    z_m: Some(-0.25),
                    z_var_m2: Some(1e-4),
                    point_sigma_m: Some([0.01, 0.002, 0.005]),
                    source: Source::Window,
                    provenance: Provenance::Observed,
                    refusal: None,
                },
                ElevationItem {
                    z_m: None,
                    z_var_m2: None,
                    point_sigma_m: None,
                    source: Source::None,
                    provenance: Provenance::None,
                    refusal: Some(Refusal::Unobserved),
                },
            ],
        }
    }

    #[test]
    fn both_encodings_round_trip() {
        for enc in [Encoding::Bincode, Encoding::Json] {
            let bytes = encode(enc, &sample()).expect("encode");
            let back: ElevationReply = decode(enc, &bytes).expect("decode");
            assert_eq!(back, sample());
            assert_eq!(peek_version(enc, &bytes), Some(PROTOCOL_VERSION));
        }
    }

    #[test]
    fn json_is_the_documented_shape() {
        let req = ElevationRequest {
            version: 1,
            points: vec![[1.0, 2.5]],
        };
        let text = String::from_utf8(encode(Encoding::Json, &req).expect("encode")).expect("utf8");
        assert_eq!(text, r#"{"version":1,"points":[[1.0,2.5]]}"#);
        let err: ErrorReply = decode(
            Encoding::Json,
            br#"{"version":1,"code":"batch_too_large","message":"m"}"#,
        )
        .expect("decode");
        assert_eq!(err.code, ErrorCode::BatchTooLarge);
    }

    #[test]
    fn trailing_and_truncated_bytes_are_errors() {
        let mut bytes = encode(Encoding::Bincode, &sample()).expect("encode");
        bytes.push(0);
        assert!(matches!(
            decode::<ElevationReply>(Encoding::Bincode, &bytes),
            Err(CodecError::TrailingBytes(1))
        ));
        bytes.truncate(bytes.len() - 3);
        assert!(decode::<ElevationReply>(Encoding::Bincode, &bytes).is_err());
    }

    #[test]
    fn mime_selects_the_encoding() {
        assert_eq!(Encoding::from_mime("application/json"), Encoding::Json);
        assert_eq!(Encoding::from_mime("application/json;x"), Encoding::Json);
        assert_eq!(Encoding::from_mime("zenoh/bytes"), Encoding::Bincode);
        assert_eq!(Encoding::from_mime(BINCODE_MIME), Encoding::Bincode);
    }

    /// Seeded random cases (the failing seed is in the message).
    mod properties {
        use super::*;
        use rand::{Rng, SeedableRng};
        use rand_pcg::Pcg64;

        fn decode_all(encoding: Encoding, bytes: &[u8]) {
            // Any outcome but a panic or an unbounded allocation.
            let _ = decode::<ElevationRequest>(encoding, bytes);
            let _ = decode::<VarianceRequest>(encoding, bytes);
            let _ = decode::<RayRequest>(encoding, bytes);
            let _ = decode::<GridRequest>(encoding, bytes);
            let _ = decode::<SlopeRequest>(encoding, bytes);
            let _ = decode::<StatusRequest>(encoding, bytes);
            let _ = decode::<StatusReply>(encoding, bytes);
            let _ = decode::<MapUpdate>(encoding, bytes);
            let _ = peek_version(encoding, bytes);
        }

        const CASES: u64 = 512;

        #[test]
        fn arbitrary_bytes_never_panic_a_decoder() {
            for seed in 0..CASES {
                let mut rng = Pcg64::seed_from_u64(seed);
                let n = rng.random_range(0..256);
                let bytes: Vec<u8> = (0..n).map(|_| rng.random()).collect();
                decode_all(Encoding::Bincode, &bytes);
                decode_all(Encoding::Json, &bytes);
            }
        }

        #[test]
        fn huge_declared_lengths_are_refused_without_allocating() {
            for seed in 0..CASES {
                let mut rng = Pcg64::seed_from_u64(seed);
                let len: u64 = rng.random_range((1u64 << 32)..u64::MAX);
                let version: u32 = rng.random_range(0..4);
                let mut bytes = encode(Encoding::Bincode, &version).expect("version");
                bytes.push(253);
                bytes.extend_from_slice(&len.to_le_bytes());
                assert!(
                    decode::<ElevationRequest>(Encoding::Bincode, &bytes).is_err(),
                    "seed {seed}"
                );
                assert!(
                    decode::<RayRequest>(Encoding::Bincode, &bytes).is_err(),
                    "seed {seed}"
                );
            }
        }

        #[test]
        fn requests_round_trip_in_both_encodings() {
            for seed in 0..CASES {
                let mut rng = Pcg64::seed_from_u64(seed);
                // Dyadic values: serde_json (without float_roundtrip) may move the last bit of others.
                let points: Vec<[f64; 2]> = (0..rng.random_range(0..64))
                    .map(|_| [rng.random::<i32>() as f64 / 8.0, rng.random::<i32>() as f64 / 4.0])
                    .collect();
                let e = ElevationRequest {
                    version: PROTOCOL_VERSION,
                    points,
                };
                let rays = (0..rng.random_range(0..16))
                    .map(|_| Ray {
                        origin_m: [0; 3].map(|_| rng.random::<i16>() as f64 / 16.0),
                        direction: [0; 3].map(|_| f64::from(rng.random::<i16>())),
                        max_range_m: f64::from(rng.random::<u16>()),
                    })
                    .collect();
                let r = RayRequest {
                    version: PROTOCOL_VERSION,
                    rays,
                };
                for enc in [Encoding::Bincode, Encoding::Json] {
                    let back: ElevationRequest =
                        decode(enc, &encode(enc, &e).expect("encode")).expect("decode");
                    assert_eq!(back, e, "seed {seed}");
                    let back: RayRequest = decode(enc, &encode(enc, &r).expect("encode")).expect("decode");
                    assert_eq!(back, r, "seed {seed}");
                }
            }
        }
    }
}
