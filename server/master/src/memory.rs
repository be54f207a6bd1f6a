//! Keeping the resident set where sessions leave it: one malloc arena, and freed memory
//! handed back to the system once sessions end.
//!
//! glibc's malloc gives each thread that allocates while another holds the lock an arena of
//! its own (up to 8 per core), and returns memory to the kernel only when the top of a heap
//! is free. A session frees its peer connection, encoder and frame buffers from several
//! threads, so after churn the resident set stays near its peak although nothing is live:
//! the soak test measured 87 MB → 151 MB after 500 sessions. Two measures:
//!
//! - [`trim`]: once sessions have ended, the master calls `malloc_trim(0)` (which also
//!   releases free pages inside each arena), at most once per [`TRIM_EVERY`], on the
//!   blocking pool.
//! - [`use_one_arena`]: the `nephele` binary asks for a single arena before any thread
//!   starts. With trimming alone the settled size after 500 sessions was 0.94–1.22× of its
//!   baseline run to run (which arenas a process happens to grow, and where long-lived
//!   objects land in them); with one arena, 1.040–1.044 in six runs, baseline
//!   36 MB instead of 41–47, peak 104 MB instead of 139 (`tests/soak.rs`). Rendering and
//!   encoding allocate little per frame and each thread keeps its small-chunk cache, so the
//!   shared lock costs nothing measurable here (`bench render`, `bench stream`: within
//!   run-to-run noise). An operator's own `GLIBC_TUNABLES=glibc.malloc.arena_max=N` wins.
//!
//! (Tried: mimalloc stays flat over the churn but peaks at 450 MB while loading the default
//! scenes, against 270 MB here.) Other allocators and platforms: nothing to do.

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

/// Asks glibc's malloc for one arena shared by all threads (see the module notes), unless
/// `GLIBC_TUNABLES` already sets `arena_max`. Call first thing in `main`, before any thread
/// is started: arenas that exist stay. Returns whether the setting was applied.
#[allow(unsafe_code)] // one FFI call into glibc
pub fn use_one_arena() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        if std::env::var("GLIBC_TUNABLES").is_ok_and(|t| t.contains("arena_max")) {
            return false;
        }
        // SAFETY: mallopt only sets malloc's parameters under its own lock; called from main
        // before other threads exist.
        unsafe { libc::mallopt(libc::M_ARENA_MAX, 1) == 1 }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    false
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

/// Bytes malloc has handed out and not had back (small chunks in the arenas plus mmapped
/// blocks; glibc's `mallinfo2`): the live heap, without the free memory the allocator keeps.
/// `/metrics` shows it as `nephele_heap_in_use_bytes`, so a leak (this grows) can be told
/// from fragmentation (only the resident set grows).
#[allow(unsafe_code)] // one FFI call into glibc
pub fn heap_in_use() -> Option<u64> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 takes malloc's own locks and returns a plain struct.
        let info = unsafe { libc::mallinfo2() };
        Some((info.uordblks + info.hblkhd) as u64)
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    None
}
