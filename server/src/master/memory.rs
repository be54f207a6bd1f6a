//! Handing memory that ended sessions freed back to the system.
//!
//! glibc's malloc keeps freed memory in its arenas (one per thread that allocated, up to
//! 8 per core) and returns it to the kernel only when the top of a heap is free. A session
//! frees its peer connection, encoder and frame buffers from several threads, so after
//! churn the resident set stays near its peak although nothing is live: the soak test
//! measured 87 MB → 151 MB after 500 sessions. So once sessions have ended, the master calls
//! `malloc_trim(0)` (which also releases free pages inside each arena), at most once per
//! [`TRIM_EVERY`], on the blocking pool: the soak then settles at its working set (~45 MB;
//! 0.94–1.22× its baseline after 200 warm-up sessions, run to run; `tests/soak.rs`). (Tried:
//! mimalloc stays flat over the churn but peaks at 450 MB while loading the default scenes,
//! against 270 MB here; two arenas instead of glibc's default did not help.) Other
//! allocators and platforms: nothing to do.

use std::{
    sync::atomic::{AtomicU64, Ordering},
    time::Duration,
};

/// How often the trimmer looks; a session's teardown (ICE agent, DTLS, SCTP tasks) ends
/// some seconds after the session does, so an end is trimmed for twice.
pub const TRIM_EVERY: Duration = Duration::from_secs(5);

static SESSIONS_ENDED: AtomicU64 = AtomicU64::new(0);

/// Tells the trimmer that a session's memory is being freed.
pub fn session_ended() {
    SESSIONS_ENDED.fetch_add(1, Ordering::Relaxed);
}

/// Starts the trimmer on the current tokio runtime (once per process is enough; more
/// are harmless).
pub fn spawn_trimmer() {
    tokio::spawn(async {
        let mut ticks = tokio::time::interval(TRIM_EVERY);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let (mut seen, mut pending) = (SESSIONS_ENDED.load(Ordering::Relaxed), 0u8);
        loop {
            ticks.tick().await;
            let ended = SESSIONS_ENDED.load(Ordering::Relaxed);
            if ended != seen {
                (seen, pending) = (ended, 2);
            }
            if pending > 0 {
                pending -= 1;
                let _ = tokio::task::spawn_blocking(trim).await;
            }
        }
    });
}

/// Returns free heap pages to the kernel; returns whether any were released.
#[allow(unsafe_code)] // one FFI call into glibc
pub fn trim() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only takes malloc's own locks; it is safe to call from any
        // thread at any time.
        let released = unsafe { libc::malloc_trim(0) } == 1;
        tracing::debug!(released, "malloc_trim");
        released
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    false
}
