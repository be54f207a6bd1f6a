//! How every long-running role stops: the first SIGTERM or SIGINT starts a drain (the role
//! stops taking work, tells its clients in words, lets work in flight finish up to
//! `--drain-seconds`, and exits 0); a second one stops at once (exit status 1).

use std::time::Duration;

use tokio::signal::unix::{SignalKind, signal};

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
            eprintln!("warning: cannot listen for SIGTERM/SIGINT ({e}); {role} stops only when killed");
            return std::future::pending().await;
        }
    };
    let name = tokio::select! {
        _ = term.recv() => "SIGTERM",
        _ = int.recv() => "SIGINT",
    };
    eprintln!("{name}: {role} is draining (a second signal stops it at once)");
    tokio::spawn(async move {
        tokio::select! {
            _ = term.recv() => {},
            _ = int.recv() => {},
        }
        eprintln!("second signal: {role} stops now without draining");
        std::process::exit(1);
    });
}
