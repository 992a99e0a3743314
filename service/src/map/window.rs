//! The rolling window of recent local maps and the immutable snapshot queries read.

use super::aggregate::world::WorldAggregate;
use super::local::LocalRangeMap;
use std::collections::VecDeque;
use std::sync::Arc;

/// The last `capacity` local maps, newest first.
#[derive(Debug, Clone)]
pub struct Window {
    capacity: usize,
    maps: VecDeque<Arc<LocalRangeMap>>,
}

impl Window {
    /// An empty window; panics on zero capacity (a configuration error caught at load).
    pub fn new(capacity: usize) -> Self {
        assert!(capacity > 0, "window capacity must be positive");
        Self {
            capacity,
            maps: VecDeque::with_capacity(capacity),
        }
    }

    /// Adds the newest map, evicting the oldest when full.
    pub fn push(&mut self, map: Arc<LocalRangeMap>) {
        if self.maps.len() == self.capacity {
            self.maps.pop_back();
        }
        self.maps.push_front(map);
    }

    /// Maps held now.
    pub fn len(&self) -> usize {
        self.maps.len()
    }

    /// True before the first scan.
    pub fn is_empty(&self) -> bool {
        self.maps.is_empty()
    }

    /// Capacity.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// An immutable view for queries.
    pub fn snapshot(&self) -> MapSnapshot {
        MapSnapshot {
            maps: self.maps.iter().cloned().collect(),
            aggregate: None,
        }
    }
}

/// What a query sees: the window's maps and the aggregate at one instant; swapped atomically.
#[derive(Debug, Clone, Default)]
pub struct MapSnapshot {
    /// Local maps, newest first.
    pub maps: Vec<Arc<LocalRangeMap>>,
    /// The world aggregate as of its last insert (when enabled).
    pub aggregate: Option<Arc<WorldAggregate>>,
}
