//! The checkpoint thread: writes the published aggregate whenever it changed, at most once per
//! interval; the daemon writes once more after the aggregate thread has stopped.

use crate::checkpoint::writer::Writer;
use crate::priority::{lower_current_thread, Background};
use crate::shutdown::Shutdown;
use crate::state::DaemonState;
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Starts the checkpoint thread; it stops when `shutdown` is triggered.
pub(super) fn spawn(
    writer: Arc<Mutex<Writer>>,
    state: Arc<DaemonState>,
    interval: Duration,
    shutdown: Shutdown,
) -> std::io::Result<JoinHandle<()>> {
    std::thread::Builder::new()
        .name("rangegp-checkpoint".into())
        .spawn(move || {
            lower_current_thread(Background::Idle);
            while !shutdown.sleep_until(Instant::now() + interval) {
                writer
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .write_if_changed(&state);
            }
        })
}
