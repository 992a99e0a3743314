//! A bounded hand-off where the newest item wins: when full, the oldest waiting item is dropped.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, PoisonError};
use std::time::Duration;

/// Bounded multi-producer queue that never blocks the producer.
#[derive(Debug)]
pub struct LatestQueue<T> {
    capacity: usize,
    items: Mutex<VecDeque<T>>,
    ready: Condvar,
}

impl<T> LatestQueue<T> {
    /// A queue holding at most `capacity` items (panics on zero: configuration is validated).
    pub fn new(capacity: usize) -> Self {
        assert!(capacity > 0, "queue capacity must be positive");
        Self {
            capacity,
            items: Mutex::new(VecDeque::with_capacity(capacity)),
            ready: Condvar::new(),
        }
    }

    /// Enqueues `item`; returns the item it displaced, if the queue was full.
    pub fn push(&self, item: T) -> Option<T> {
        let mut items = self.items.lock().unwrap_or_else(PoisonError::into_inner);
        let dropped = if items.len() == self.capacity {
            items.pop_front()
        } else {
            None
        };
        items.push_back(item);
        self.ready.notify_one();
        dropped
    }

    /// Takes every waiting item, oldest first, waiting at most `timeout` for the first.
    pub fn drain_timeout(&self, timeout: Duration) -> Vec<T> {
        let items = self.items.lock().unwrap_or_else(PoisonError::into_inner);
        let (mut items, _) = self
            .ready
            .wait_timeout_while(items, timeout, |q| q.is_empty())
            .unwrap_or_else(PoisonError::into_inner);
        items.drain(..).collect()
    }

    /// Takes the oldest waiting item, waiting at most `timeout`.
    pub fn pop_timeout(&self, timeout: Duration) -> Option<T> {
        let items = self.items.lock().unwrap_or_else(PoisonError::into_inner);
        let (mut items, _) = self
            .ready
            .wait_timeout_while(items, timeout, |q| q.is_empty())
            .unwrap_or_else(PoisonError::into_inner);
        items.pop_front()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn newest_wins_when_full() {
        let q = LatestQueue::new(2);
        assert_eq!(q.push(1), None);
        assert_eq!(q.push(2), None);
        assert_eq!(q.push(3), Some(1));
        assert_eq!(q.pop_timeout(Duration::ZERO), Some(2));
        assert_eq!(q.pop_timeout(Duration::ZERO), Some(3));
        assert_eq!(q.pop_timeout(Duration::from_millis(1)), None);
    }

    #[test]
    fn a_drain_takes_everything_waiting_in_order() {
        let q = LatestQueue::new(4);
        for i in 1..=3 {
            q.push(i);
        }
        assert_eq!(q.drain_timeout(Duration::ZERO), vec![1, 2, 3]);
        assert!(q.drain_timeout(Duration::from_millis(1)).is_empty());
    }
}
