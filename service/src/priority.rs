//! Thread priorities: background work (the aggregate, hyperparameter learning, batch queries)
//! runs at a higher nice value, so that on a robot's few cores the latency-critical threads —
//! Zenoh's (which answer single-point queries), ingest and the fitter — preempt it at once.

/// How much a background thread yields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Background {
    /// Batch queries: behind the fitter and single-point queries, ahead of the aggregate.
    Batch = 5,
    /// Work nobody waits for (aggregate inserts, hyperparameter learning).
    Idle = 10,
}

/// Lowers the calling thread's priority to `level` (Linux: the nice value is per thread).
/// Failure is harmless (the thread keeps its priority) and logged at debug level.
pub fn lower_current_thread(level: Background) {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: setpriority only reads its integer arguments; `who = 0` names the calling
        // thread, and raising the nice value needs no privilege.
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, level as libc::c_int) };
        if rc != 0 {
            tracing::debug!(error = %std::io::Error::last_os_error(), "cannot lower the thread priority");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = level;
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn only_the_calling_thread_is_lowered() {
        let nice = || {
            // SAFETY: getpriority only reads its integer arguments.
            unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
        };
        let before = nice();
        let inside = std::thread::spawn(move || {
            lower_current_thread(Background::Idle);
            nice()
        })
        .join()
        .expect("thread");
        assert_eq!(inside, (before + 10).min(19));
        assert_eq!(nice(), before, "the spawning thread keeps its priority");
    }
}
