//! Helpers shared by the end-to-end tests: the `nephele` binary of this build, the fixture
//! asset, an in-process server, child processes that die with the test.

use std::{
    path::PathBuf,
    process::{Child, Command},
    sync::Arc,
};

use nephele::{
    catalog::Catalog,
    master::{
        MasterConfig,
        core::{Admission, CoreConfig, scheduler::RenderScale},
    },
    web::{self, LocalServer},
    wire::media::RtcConfig,
};
use nephele_renderer::{CpuBackend, RenderSettings};

/// The repository root.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `trio=<the small procedural trio fixture>`.
pub fn fixture_scene() -> String {
    format!("trio={}", repo().join("examples/assets/trio-small.nolf").display())
}

/// The `nephele` binary built alongside these tests (same profile, same target directory).
pub fn nephele_bin() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    // target/<profile>/deps/<test> → target/<profile>/nephele
    let dir = exe.parent().and_then(|d| d.parent()).expect("a target directory");
    let bin = dir.join(format!("nephele{}", std::env::consts::EXE_SUFFIX));
    assert!(bin.exists(), "{} is missing: `cargo test --workspace` builds it (or run `cargo build` with the same profile)", bin.display());
    bin
}

/// A `nephele` command of this build.
pub fn nephele() -> Command {
    Command::new(nephele_bin())
}

/// Kills a child process when dropped, so a failing assertion leaves no server behind.
pub struct Reap(pub Child);

impl Drop for Reap {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// A core configuration for tests: exact render scale, `capacity` sessions, admission open
/// (tests run side by side on two cores, so the farm they measure is slower than it is
/// alone; admission by load has its own tests on simulated time).
pub fn core_config(capacity: u32) -> CoreConfig {
    CoreConfig { capacity, render_scale: RenderScale::Fixed(1.0), admission: Admission::Open, ..Default::default() }
}

/// Signaling + a master (CPU backend, the fixture scene) + pages, in this process.
pub async fn start_server(core: CoreConfig) -> (LocalServer, Arc<Catalog>) {
    let catalog = Arc::new(Catalog::load(&[fixture_scene()], &CpuBackend, RenderSettings::default()).expect("fixture asset"));
    let cfg = MasterConfig { name: "test".into(), token: None, rtc: RtcConfig { loopback_only: true, public_ips: vec![] }, core, workers: 1 };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("a loopback port");
    (web::spawn_local(listener, Arc::clone(&catalog), cfg).await.expect("the server starts"), catalog)
}
