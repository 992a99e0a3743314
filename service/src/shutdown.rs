//! The daemon's one shutdown primitive: a flag every thread polls between units of work, and a
//! sleep that wakes the moment the flag is set (aggregate pacing, checkpoint interval, ingest
//! retries). Its own module so that every thread's module can use it without depending on the
//! daemon that wires them.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Instant;

/// A cloneable stop signal: [`Shutdown::trigger`] once, every clone sees it.
#[derive(Debug, Clone, Default)]
pub struct Shutdown(Arc<Inner>);

#[derive(Debug, Default)]
struct Inner {
    /// Read on every loop turn: a relaxed load, no lock.
    flag: AtomicBool,
    /// Guards the wake-up of sleepers (the flag is also set under it, so none misses it).
    lock: Mutex<()>,
    wake: Condvar,
}

impl Shutdown {
    /// A signal not yet triggered.
    pub fn new() -> Self {
        Self::default()
    }

    /// Asks every thread holding a clone to stop, and wakes those sleeping.
    pub fn trigger(&self) {
        let _guard = self.0.lock.lock().unwrap_or_else(PoisonError::into_inner);
        self.0.flag.store(true, Ordering::Relaxed);
        self.0.wake.notify_all();
    }

    /// Whether a stop was asked for.
    pub fn is_triggered(&self) -> bool {
        self.0.flag.load(Ordering::Relaxed)
    }

    /// Sleeps until `until` or until the signal is triggered; returns whether it was.
    pub fn sleep_until(&self, until: Instant) -> bool {
        let mut guard = self.0.lock.lock().unwrap_or_else(PoisonError::into_inner);
        loop {
            if self.is_triggered() {
                return true;
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return false;
            }
            guard = self
                .0
                .wake
                .wait_timeout(guard, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_sleep_runs_to_its_deadline_unless_triggered() {
        let s = Shutdown::new();
        let start = Instant::now();
        assert!(!s.sleep_until(start + Duration::from_millis(20)));
        assert!(start.elapsed() >= Duration::from_millis(20));
    }

    #[test]
    fn a_trigger_wakes_a_sleeper_long_before_its_deadline() {
        let s = Shutdown::new();
        let ready = std::sync::Arc::new(std::sync::Barrier::new(2));
        let (tx, rx) = std::sync::mpsc::channel();
        {
            let (s, ready) = (s.clone(), std::sync::Arc::clone(&ready));
            std::thread::spawn(move || {
                ready.wait();
                let _ = tx.send(s.sleep_until(Instant::now() + Duration::from_secs(120)));
            });
        }
        // The sleeper is about to sleep (or sleeping) when the trigger comes; it must answer
        // long before its two-minute deadline, and the wait for it is bounded.
        ready.wait();
        s.trigger();
        let woke = rx
            .recv_timeout(Duration::from_secs(30))
            .expect("the sleeper woke");
        assert!(woke, "the sleep ended by the trigger, not its deadline");
        assert!(s.is_triggered());
    }
}
