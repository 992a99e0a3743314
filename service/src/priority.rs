//! Thread priorities: background work (the aggregate, hyperparameter learning, batch queries)
//! runs at a higher nice value, so that on a robot's few cores the latency-critical threads —
//! Zenoh's (which answer single-point queries), ingest and the fitter — preempt it at once.

#![allow(unsafe_code)] // Allowed here, each site with its SAFETY comment; denied elsewhere.

/// How much a background thread yields.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Background {
    /// Batch queries: behind the fitter and single-point queries, ahead of the aggregate.
    Batch = 5,
    /// Work nobody waits for (aggregate inserts, hyperparameter learning).
    Idle = 10,
}

/// Lowers the calling thread's priority by `level` nice steps from where it stands (at most to
/// 19; Linux: the nice value is per thread), so that a daemon started under `nice` keeps its
/// background threads behind its own. Failure is harmless (the thread keeps its priority) and
/// logged at debug level.
pub fn lower_current_thread(level: Background) {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: getpriority and setpriority only read their integer arguments; `who = 0`
        // names the calling thread. getpriority may return -1 as a value, so errno is cleared
        // first and read after; raising the nice value needs no privilege.
        let rc = unsafe {
            *libc::__errno_location() = 0;
            let current = libc::getpriority(libc::PRIO_PROCESS, 0);
            if current == -1 && *libc::__errno_location() != 0 {
                -1
            } else {
                libc::setpriority(libc::PRIO_PROCESS, 0, (current + level as libc::c_int).min(19))
            }
        };
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
    fn only_the_calling_thread_is_lowered_relative_to_where_it_stands() {
        let nice = || {
            // SAFETY: getpriority only reads its integer arguments.
            unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
        };
        let before = nice();
        let (started, inside) = std::thread::spawn(move || {
            // A thread already niced by 3 (as under `nice -n 3`): Idle puts it 10 further.
            // SAFETY: setpriority only reads its integer arguments; raising needs no privilege.
            unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, (before + 3).min(19)) };
            let started = nice();
            lower_current_thread(Background::Idle);
            (started, nice())
        })
        .join()
        .expect("thread");
        assert_eq!(started, (before + 3).min(19));
        assert_eq!(inside, (started + 10).min(19));
        assert_eq!(nice(), before, "the spawning thread keeps its priority");
    }
}
