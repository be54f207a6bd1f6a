//! Helpers shared by the end-to-end tests: the `nephele` binary of this build, the fixture
//! asset, an in-process server, child processes that die with the test.

use std::{
    path::PathBuf,
    process::{Child, Command},
    sync::Arc,
};

use nephele_core::{Admission, CoreConfig, scheduler::RenderScale};
use nephele_farm::{catalog::Catalog, worker::NatsAuth};
use nephele_master::{
    MasterConfig,
    compositor::ComposeChoice,
    driver::NatsSettings,
    encoder::DEFAULT_BITS_PER_PIXEL,
    web::{self, LocalServer},
};
use nephele_rtc::RtcConfig;
use nephele_renderer::{Backend, FastCpuBackend, RenderSettings, gpu::GpuBackend};

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

/// Runs a command to the end; panics with its output if it fails (the namespace tests'
/// network set-up).
pub fn run_ok(program: &str, args: &[&str]) {
    let out = Command::new(program).args(args).output().unwrap_or_else(|e| panic!("cannot run {program}: {e}"));
    assert!(out.status.success(), "`{program} {}` failed: {}{}", args.join(" "), String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
}

/// Fails (never skips) unless this runs as root with every `(command, its version flag,
/// Debian package)` of `tools` installed: the namespace tests need both, as CI gives them.
pub fn require_root_and(test: &str, tools: &[(&str, &str, &str)]) {
    let uid = Command::new("id").arg("-u").output().map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string()).unwrap_or_default();
    assert_eq!(uid, "0", "{test} needs root (network namespaces, veth pairs, iptables rules); run it as root, as CI does");
    for (tool, flag, package) in tools {
        let found = Command::new(tool).arg(flag).stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null()).status().is_ok();
        assert!(found, "`{tool}` is missing: install the Debian package `{package}` (tests/run and .ci/run do)");
    }
}

/// A `nephele` command of this build.
pub fn nephele() -> Command {
    Command::new(nephele_bin())
}

/// A validator from the Python environment `tests/run` installs (`NEPHELE_PY_TOOLS`, by
/// default `target/py-tools`): `kubernetes-validate`, `check-jsonschema`, `python`. Missing,
/// the test fails and says how to get it.
pub fn py_tool(name: &str) -> PathBuf {
    let dir = std::env::var_os("NEPHELE_PY_TOOLS").map_or_else(|| repo().join("target/py-tools"), PathBuf::from);
    let tool = dir.join("bin").join(name);
    assert!(
        tool.exists(),
        "{} is missing: tests/run installs it (python3 -m venv {dir} && {dir}/bin/pip install kubernetes-validate==1.37.0 check-jsonschema==0.39.0 prometheus-client==0.26.0)",
        tool.display(),
        dir = dir.display()
    );
    tool
}

/// Checks `text` with a strict OpenMetrics parser (Python's `prometheus_client`), and the
/// conventions every Nephele role keeps: names start `nephele_`, counters end `_total`, no
/// millisecond series, `nephele_build_info` for `role`. Returns the metric family names.
pub fn check_openmetrics(text: &str, role: &str) -> Vec<String> {
    let script = r#"
import sys
from prometheus_client.openmetrics.parser import text_string_to_metric_families
for family in text_string_to_metric_families(sys.stdin.read()):
    for sample in family.samples:
        print(family.name, family.type, sample.name, sorted(sample.labels.items()), sample.value)
"#;
    let mut child = Command::new(py_tool("python"))
        .args(["-c", script])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("python from the test tools");
    std::io::Write::write_all(&mut child.stdin.take().unwrap(), text.as_bytes()).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success(), "not valid OpenMetrics: {}\n{text}", String::from_utf8_lossy(&out.stderr));
    let lines = String::from_utf8(out.stdout).unwrap();
    let mut families = Vec::new();
    for line in lines.lines() {
        let mut parts = line.splitn(4, ' ');
        let (family, kind, sample) = (parts.next().unwrap(), parts.next().unwrap(), parts.next().unwrap());
        assert!(family.starts_with("nephele_"), "{family}: not a nephele_ series");
        assert!(!family.ends_with("_ms") && !family.contains("_ms_"), "{family}: milliseconds (Prometheus wants seconds)");
        if kind == "counter" {
            assert!(sample.ends_with("_total") || sample.ends_with("_created"), "counter sample {sample} does not end in _total");
        }
        if families.last() != Some(&family.to_owned()) {
            families.push(family.to_owned());
        }
    }
    let build = format!("nephele_build info nephele_build_info [('role', '{role}'), ('version', '{}')] 1", env!("CARGO_PKG_VERSION"));
    assert!(lines.lines().any(|l| l == build), "no {build:?} in\n{lines}");
    families
}

/// Kills a child process when dropped, so a failing assertion leaves no server behind.
pub struct Reap(pub Child);

impl Drop for Reap {
    fn drop(&mut self) {
        self.0.kill().ok();
        self.0.wait().ok();
    }
}

/// `node SCRIPT ARGS…` in a process group of its own, so that [`NodeGroup`] can end the
/// browser it starts along with it.
pub fn node(script: &std::path::Path) -> Command {
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new("node");
    cmd.arg(script).process_group(0);
    cmd
}

/// Ends a `node` process group (node and the Chromium it launched) when dropped, whether the
/// test passed, failed or panicked: no browser is left running.
pub struct NodeGroup(pub u32);

impl Drop for NodeGroup {
    fn drop(&mut self) {
        // `kill -KILL -PGID`: the whole group; an error only means it is gone already.
        let _ = Command::new("kill").args(["-KILL", "--", &format!("-{}", self.0)]).stderr(std::process::Stdio::null()).status();
    }
}

/// Runs `cmd` (from [`node`]) to the end and returns its output; its process group is ended
/// on the way out in any case.
pub fn node_output(mut cmd: Command) -> std::io::Result<std::process::Output> {
    let child = cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn()?;
    let _group = NodeGroup(child.id());
    child.wait_with_output()
}

/// A core configuration for tests: exact render scale, `capacity` sessions, admission open
/// (tests run side by side on two cores, so the farm they measure is slower than it is
/// alone; admission by load has its own tests on simulated time).
pub fn core_config(capacity: u32) -> CoreConfig {
    CoreConfig { capacity, render_scale: RenderScale::Fixed(1.0), admission: Admission::Open, ..Default::default() }
}

/// Signaling + a master (the fast CPU renderer `serve` uses by default, the fixture scene) +
/// pages, in this process.
pub async fn start_server(core: CoreConfig) -> (LocalServer, Arc<Catalog>) {
    start_server_with(&[fixture_scene()], core).await
}

/// [`start_server`] serving `scenes` (`name=asset` or `name=scene.json`).
pub async fn start_server_with(scenes: &[String], core: CoreConfig) -> (LocalServer, Arc<Catalog>) {
    start_server_full(scenes, core, DEFAULT_BITS_PER_PIXEL).await
}

/// [`start_server_with`] at `bits_per_pixel` of video.
pub async fn start_server_full(scenes: &[String], core: CoreConfig, bits_per_pixel: f64) -> (LocalServer, Arc<Catalog>) {
    start_master(scenes, core, bits_per_pixel, None, &FastCpuBackend, ComposeChoice::Cpu).await
}

/// [`start_server_with`] rendering on wgpu (the software adapter here) and composing
/// multi-object frames with the wgpu compositor: the path a GPU server takes.
pub async fn start_gpu_server(scenes: &[String], core: CoreConfig, bits_per_pixel: f64) -> (LocalServer, Arc<Catalog>) {
    let gpu = GpuBackend::new().expect("a wgpu adapter (tests/run installs lavapipe)");
    start_master(scenes, core, bits_per_pixel, None, &gpu, ComposeChoice::Gpu).await
}

/// A master rendering on the NATS farm at `nats` (with its token), in this process.
pub async fn start_nats_master(scenes: &[String], core: CoreConfig, nats: &NatsServer) -> (LocalServer, Arc<Catalog>) {
    let settings = NatsSettings { url: nats.url.clone(), auth: NatsAuth { token: Some(nats.token.clone()), ..Default::default() } };
    start_master(scenes, core, DEFAULT_BITS_PER_PIXEL, Some(settings), &FastCpuBackend, ComposeChoice::Cpu).await
}

async fn start_master(
    scenes: &[String],
    core: CoreConfig,
    bits_per_pixel: f64,
    nats: Option<NatsSettings>,
    backend: &dyn Backend,
    compose: ComposeChoice,
) -> (LocalServer, Arc<Catalog>) {
    let catalog = Arc::new(Catalog::load(scenes, backend, RenderSettings::default()).expect("the scenes load"));
    let cfg = MasterConfig { name: "test".into(), token: None, rtc: RtcConfig::loopback(), core, workers: 1, compose, bits_per_pixel, nats };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("a loopback port");
    (web::spawn_local(listener, Arc::clone(&catalog), cfg).await.expect("the server starts"), catalog)
}

/// A fresh directory under the system's temp dir, removed when dropped.
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("nephele-e2e-{tag}-{}-{:?}", std::process::id(), std::thread::current().id()));
        std::fs::create_dir_all(&dir).expect("a temp dir");
        Self(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        std::fs::remove_dir_all(&self.0).ok();
    }
}

/// A two-object scene of the small procedural fixtures, overlapping so that the depth
/// order flips as the camera orbits; written into `dir`, returned as `name=path`.
pub fn pair_scene(dir: &std::path::Path) -> String {
    let path = dir.join("pair.json");
    let trio = repo().join("examples/assets/trio-small.nolf");
    let text = serde_json::json!({
        "background": [0.9, 0.95, 1.0],
        "objects": [
            { "asset": trio.display().to_string(), "world_from_object": { "translation": [-0.5, 0.0, 0.0], "scale": 0.6 } },
            { "asset": "builtin:diffuse-small", "world_from_object": { "rotation": [0.0, 0.0, 0.3826834, 0.9238795], "translation": [0.6, 0.1, 0.1], "scale": 0.5 } }
        ]
    });
    std::fs::write(&path, text.to_string()).expect("writing the scene file");
    format!("pair={}", path.display())
}

/// A `nats-server` of this test on a free loopback port, requiring a token; killed when
/// dropped. Debian's `nats-server` package (tests/run installs it); a missing binary fails
/// the test in words.
pub struct NatsServer {
    child: Option<Reap>,
    pub port: u16,
    pub url: String,
    pub token: String,
}

impl NatsServer {
    pub fn start() -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0").expect("a free port").local_addr().unwrap().port();
        let mut s = Self { child: None, port, url: format!("nats://127.0.0.1:{port}"), token: format!("t{}", std::process::id()) };
        s.restart();
        s
    }

    /// Stops it (clients see the connection drop).
    pub fn stop(&mut self) {
        self.child = None;
    }

    /// Starts it again on the same port.
    pub fn restart(&mut self) {
        self.child = None;
        let child = Command::new("nats-server")
            .args(["-a", "127.0.0.1", "-p", &self.port.to_string(), "--auth", &self.token])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("nats-server is missing: install the `nats-server` package (tests/run does)");
        self.child = Some(Reap(child));
        for _ in 0..200 {
            if std::net::TcpStream::connect(("127.0.0.1", self.port)).is_ok() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(25));
        }
        panic!("nats-server did not listen on port {} within 5 s", self.port);
    }
}

/// Starts `nephele worker` on `nats` and waits until it serves (its "serves" line).
pub fn spawn_worker(nats: &NatsServer, id: &str, farm: &str, scenes: &[String]) -> Reap {
    use std::io::{BufRead, BufReader};
    let mut cmd = nephele();
    cmd.args(["worker", "--nats", &nats.url, "--farm", farm, "--id", id, "--backend", "cpu"]).env("NEPHELE_NATS_TOKEN", &nats.token);
    for s in scenes {
        cmd.args(["--scene", s]);
    }
    let mut child = cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn().expect("starting nephele worker");
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut err = child.stderr.take().unwrap();
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    if !line.contains(" serves ") {
        // Say why: the worker's own words (it has exited, or is stopped now).
        let _ = child.kill();
        let status = child.wait();
        let mut why = String::new();
        let _ = std::io::Read::read_to_string(&mut err, &mut why);
        panic!("worker {id} printed {line:?} ({status:?}); its stderr:\n{why}");
    }
    // Keep reading, so the worker never writes into a closed pipe.
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    std::thread::spawn(move || std::io::copy(&mut err, &mut std::io::sink()));
    Reap(child)
}

/// Polls `condition` every 10 ms until it holds (`true`) or `limit` passes (`false`): how
/// tests wait on a state the server reports (its metrics), not on a guessed sleep.
pub async fn wait_until(limit: std::time::Duration, mut condition: impl FnMut() -> bool) -> bool {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        if condition() {
            return true;
        }
        if tokio::time::Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
}

/// Logs of the code under test on stderr when `RUST_LOG` is set (`--nocapture` shows them).
pub fn log_from_env() {
    if let Ok(filter) = tracing_subscriber::EnvFilter::try_from_default_env() {
        let _ = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).try_init();
    }
}

/// Starts `nephele serve` as `cmd` (already given its arguments), its stderr into `log`, and
/// waits (up to 120 s) for its "open http://…" line; returns it with its `host:port`.
pub fn spawn_serve(mut cmd: Command, log: &std::path::Path) -> (Reap, String) {
    use std::io::{BufRead, BufReader};
    let mut child = cmd
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(log).expect("the server's log file"))
        .spawn()
        .expect("starting nephele serve");
    let stdout = child.stdout.take().unwrap();
    let reap = Reap(child);
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut out = BufReader::new(stdout);
        let mut line = String::new();
        let _ = out.read_line(&mut line);
        let _ = tx.send(line);
        // Keep reading, so the server never writes into a closed pipe.
        let _ = std::io::copy(&mut out, &mut std::io::sink());
    });
    let line = rx.recv_timeout(std::time::Duration::from_secs(120)).expect("nephele serve printed nothing within 120 s");
    let addr = line.split("http://").nth(1).and_then(|s| s.split('/').next()).unwrap_or_else(|| panic!("nephele serve printed {line:?}")).to_string();
    (reap, addr)
}

/// Prints the last lines of a server's log file if the test fails.
pub struct ShowLogOnFailure(pub PathBuf);

impl Drop for ShowLogOnFailure {
    fn drop(&mut self) {
        if std::thread::panicking() {
            let text = std::fs::read_to_string(&self.0).unwrap_or_default();
            let lines: Vec<&str> = text.lines().collect();
            eprintln!("--- the last lines of the server's log ---");
            for l in &lines[lines.len().saturating_sub(60)..] {
                eprintln!("{l}");
            }
        }
    }
}

/// `nephele signal --listen addr` as a child; waits until it prints its address.
pub fn spawn_signal_at(addr: &str) -> Reap {
    use std::io::{BufRead, BufReader};
    let mut child = nephele().args(["signal", "--listen", addr]).stdout(std::process::Stdio::piped()).spawn().unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    assert!(line.contains("ws://"), "signal printed {line:?}");
    Reap(child)
}

/// `nephele master` for the fixture scene (`trio`), registering with signaling at `addr`
/// (CPU, render scale 1, admission open; its log discarded).
pub fn spawn_fixture_master(addr: &str) -> Reap {
    let (scene, url) = (fixture_scene(), format!("ws://{addr}/signal"));
    Reap(
        nephele()
            .args(["master", "--signal", &url, "--scene", &scene, "--backend", "cpu", "--loopback-only", "--render-scale", "1", "--admission", "open"])
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    )
}

/// A plain HTTP/1.1 GET on loopback; returns the body.
pub async fn http_get(addr: std::net::SocketAddr, path: &str) -> String {
    let (status, body) = http_request(addr, path).await;
    assert_eq!(status, 200, "GET {path}: {body}");
    body
}

/// A plain HTTP/1.1 GET on loopback; returns the status code and the body.
pub async fn http_request(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    let status = out.split(' ').nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (status, out.split_once("\r\n\r\n").map(|(_, b)| b.to_owned()).unwrap_or_default())
}

/// A coturn on loopback with TURN REST authentication (`use-auth-secret`).
pub struct Coturn {
    child: std::process::Child,
    pub port: u16,
}

impl Coturn {
    /// Starts `turnserver` with `secret` on free loopback ports; returns once it listens.
    pub fn start(secret: &str) -> Self {
        let free_udp_port = || std::net::UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let port = free_udp_port();
        let relay = free_udp_port().max(20_000);
        let child = std::process::Command::new("turnserver")
            .args(["-n", "--listening-ip", "127.0.0.1", "--relay-ip", "127.0.0.1", "--listening-port", &port.to_string()])
            .args(["--min-port", &relay.to_string(), "--max-port", &(relay + 200).to_string()])
            .args(["--realm", "nephele", "--use-auth-secret", "--static-auth-secret", secret])
            .args(["--no-tls", "--no-dtls", "--no-cli", "--allow-loopback-peers", "--log-file", "stdout", "--simple-log"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .expect("turnserver (Debian coturn; tests/run installs it)");
        // Ready when its TCP listener answers (it opens UDP and TCP on the port together).
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(std::time::Instant::now() < deadline, "turnserver did not start on port {port}");
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        Self { child, port }
    }
}

impl Drop for Coturn {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
