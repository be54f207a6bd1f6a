//! How every long-running role stops: the first SIGTERM or SIGINT starts a drain (the role
//! stops taking work, tells its clients in words, lets work in flight finish up to
//! `--drain-seconds`, and exits 0); a second one stops at once (exit status 1).
//! `nephele health URL` asks a role's `/healthz` or `/readyz` (for container health checks).

use std::{sync::OnceLock, time::Duration};

use tokio::signal::unix::{SignalKind, signal};

static JSON_LOGS: OnceLock<bool> = OnceLock::new();

/// From now on [`say`] writes JSON lines (`--log-format json`).
pub fn use_json_logs(json: bool) {
    let _ = JSON_LOGS.set(json);
}

/// A notice of a long-running role on stderr ("preparing…", "draining", "stopped"): plain
/// words, or under `--log-format json` one JSON object per line like the tracing logs'.
pub fn say(level: &str, message: &str) {
    match (JSON_LOGS.get().copied().unwrap_or(false), level) {
        (true, "warn") => tracing::warn!(target: "nephele", "{message}"),
        (true, _) => tracing::info!(target: "nephele", "{message}"),
        (false, "warn") => eprintln!("warning: {message}"),
        (false, _) => eprintln!("{message}"),
    }
}

/// `--drain-seconds`, shared by `serve`, `master`, `signal` and `worker`.
#[derive(clap::Args, Debug, Clone)]
pub struct DrainArgs {
    /// On SIGTERM or SIGINT, wait at most this long for work in flight (render tasks,
    /// sessions still connecting, the last messages to signaling) before exiting.
    #[arg(long, default_value_t = 10.0, value_parser = parse_drain_seconds)]
    pub drain_seconds: f64,
}

impl DrainArgs {
    pub fn deadline(&self) -> Duration {
        Duration::from_secs_f64(self.drain_seconds)
    }
}

fn parse_drain_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if (0.0..=3600.0).contains(&s) => Ok(s),
        _ => Err(format!("{text:?} is not a number of seconds in 0..=3600")),
    }
}

/// Resolves at the first SIGTERM or SIGINT (saying so on stderr); from then on a second
/// one ends the process at once. Call inside the tokio runtime.
pub async fn stop_signal(role: &'static str) {
    let (mut term, mut int) = match (signal(SignalKind::terminate()), signal(SignalKind::interrupt())) {
        (Ok(t), Ok(i)) => (t, i),
        (Err(e), _) | (_, Err(e)) => {
            say("warn", &format!("cannot listen for SIGTERM/SIGINT ({e}); {role} stops only when killed"));
            return std::future::pending().await;
        }
    };
    let name = tokio::select! {
        _ = term.recv() => "SIGTERM",
        _ = int.recv() => "SIGINT",
    };
    say("info", &format!("{name}: {role} is draining (a second signal stops it at once)"));
    tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => {},
            _ = int.recv() => {},
        }
        say("warn", &format!("second signal: {role} stops now without draining"));
        std::process::exit(1);
    });
}

#[derive(clap::Args, Debug, Clone)]
pub struct HealthArgs {
    /// What to ask: `http://HOST:PORT/healthz` (alive) or `/readyz` (can serve).
    #[arg(env = "NEPHELE_HEALTH_URL", default_value = "http://127.0.0.1:8080/readyz")]
    pub url: String,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 3.0)]
    pub timeout: f64,
}

/// `nephele health`: GET the URL; success on a 2xx answer, otherwise an error naming what
/// came back (the readiness reasons, say).
pub fn health(args: &HealthArgs) -> anyhow::Result<()> {
    use anyhow::{Context, bail};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let rest = args.url.strip_prefix("http://").with_context(|| format!("{:?}: only http:// URLs are asked (health endpoints listen inside the pod or container)", args.url))?;
    let (host_port, path) = rest.split_once('/').map_or((rest, "/".to_owned()), |(h, p)| (h, format!("/{p}")));
    let limit = Duration::from_secs_f64(args.timeout.clamp(0.1, 60.0));
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let ask = async {
        let mut stream = tokio::net::TcpStream::connect(host_port).await.with_context(|| format!("connecting to {host_port}"))?;
        let request = format!("GET {path} HTTP/1.1\r\nHost: {host_port}\r\nConnection: close\r\n\r\n");
        stream.write_all(request.as_bytes()).await?;
        let mut answer = Vec::new();
        stream.take(64 * 1024).read_to_end(&mut answer).await?;
        anyhow::Ok(String::from_utf8_lossy(&answer).into_owned())
    };
    let answer = match rt.block_on(async { tokio::time::timeout(limit, ask).await }) {
        Ok(answer) => answer?,
        Err(_) => bail!("{} did not answer within {limit:?}", args.url),
    };
    let status: u16 = answer.split_whitespace().nth(1).and_then(|s| s.parse().ok()).with_context(|| format!("{} answered something that is not HTTP", args.url))?;
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b).trim();
    if (200..300).contains(&status) {
        println!("{status} {body}");
        Ok(())
    } else {
        bail!("{} answered {status}: {body}", args.url)
    }
}
