//! Key expressions (Zenoh) and service names (iceoryx2) derived from a map id.

use thiserror::Error;

/// A map id is not usable inside a key expression.
#[derive(Debug, Error, PartialEq, Eq)]
#[error("invalid map id {0:?}: use 1-64 characters from [A-Za-z0-9_-]")]
pub struct InvalidMapId(pub String);

/// Query kinds served under `rangegp/<map_id>/query/<kind>`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QueryKind {
    /// Elevation (z mean and variance) at (x, y).
    Elevation,
    /// Elevation variance only, the cheap path.
    Variance,
    /// Expected hit along rays.
    Ray,
    /// Elevation and variance layers over a box.
    Grid,
    /// A range image as a sensor would see the map from a pose.
    View,
    /// Slope with σ and risk at (x, y), over a robot's footprint.
    Slope,
    /// Whose cells stand behind the aggregate's answer at (x, y): each robot's own cell there.
    Sources,
}

impl QueryKind {
    /// Every kind, for declaring queryables.
    pub const ALL: [QueryKind; 7] = [
        QueryKind::Elevation,
        QueryKind::Variance,
        QueryKind::Ray,
        QueryKind::Grid,
        QueryKind::View,
        QueryKind::Slope,
        QueryKind::Sources,
    ];

    /// The last key chunk of this kind.
    pub fn as_str(self) -> &'static str {
        match self {
            QueryKind::Elevation => "elevation",
            QueryKind::Variance => "variance",
            QueryKind::Ray => "ray",
            QueryKind::Grid => "grid",
            QueryKind::View => "view",
            QueryKind::Slope => "slope",
            QueryKind::Sources => "sources",
        }
    }
}

/// Validated map id with the key expressions that hang off it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MapKeys {
    map_id: String,
}

impl MapKeys {
    /// Validates `map_id` (so that no wildcard or separator can leak into a key expression).
    pub fn new(map_id: &str) -> Result<Self, InvalidMapId> {
        let ok = !map_id.is_empty()
            && map_id.len() <= 64
            && map_id
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
        if ok {
            Ok(Self {
                map_id: map_id.to_owned(),
            })
        } else {
            Err(InvalidMapId(map_id.to_owned()))
        }
    }

    /// The map id.
    pub fn map_id(&self) -> &str {
        &self.map_id
    }

    /// `rangegp/<map_id>/query/<kind>`.
    pub fn query(&self, kind: QueryKind) -> String {
        format!("rangegp/{}/query/{}", self.map_id, kind.as_str())
    }

    /// `rangegp/<map_id>/status`.
    pub fn status(&self) -> String {
        format!("rangegp/{}/status", self.map_id)
    }

    /// `rangegp/<map_id>/echo`: a bare queryable on the daemon's session that returns the
    /// request's bytes (the transport floor a round trip is compared against).
    pub fn echo(&self) -> String {
        format!("rangegp/{}/echo", self.map_id)
    }

    /// `rangegp/<map_id>/events/map`, where [`crate::msg::MapUpdate`]s are published.
    pub fn map_updates(&self) -> String {
        format!("rangegp/{}/events/map", self.map_id)
    }

    /// `rangegp/<map_id>/events/change`, where [`crate::msg::ChangeEvent`]s are published.
    pub fn changes(&self) -> String {
        format!("rangegp/{}/events/change", self.map_id)
    }

    /// `rangegp/<map_id>/corrections`, where [`crate::msg::CorrectionRequest`]s are sent.
    pub fn corrections(&self) -> String {
        format!("rangegp/{}/corrections", self.map_id)
    }

    /// `rangegp/<map_id>/@alive`, the daemon's liveliness token.
    pub fn alive(&self) -> String {
        format!("rangegp/{}/@alive", self.map_id)
    }

    /// Default iceoryx2 service name for scans of this map: `rangegp/<map_id>/scans`.
    pub fn scan_service(&self) -> String {
        format!("rangegp/{}/scans", self.map_id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_built_from_a_valid_id() {
        let k = MapKeys::new("rover_1").expect("valid id");
        assert_eq!(k.query(QueryKind::Elevation), "rangegp/rover_1/query/elevation");
        assert_eq!(k.status(), "rangegp/rover_1/status");
        assert_eq!(k.alive(), "rangegp/rover_1/@alive");
        assert_eq!(k.map_updates(), "rangegp/rover_1/events/map");
        assert_eq!(k.echo(), "rangegp/rover_1/echo");
        assert_eq!(k.corrections(), "rangegp/rover_1/corrections");
        assert_eq!(k.changes(), "rangegp/rover_1/events/change");
        assert_eq!(k.scan_service(), "rangegp/rover_1/scans");
    }

    #[test]
    fn wildcards_and_separators_are_refused() {
        for bad in ["", "a/b", "*", "a**", "x$y", "@a", "ü"] {
            assert!(MapKeys::new(bad).is_err(), "{bad:?} accepted");
        }
        assert!(MapKeys::new(&"a".repeat(65)).is_err());
    }
}
