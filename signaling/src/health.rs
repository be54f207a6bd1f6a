//! Health as a load balancer or an orchestrator asks for it: `GET /healthz` answers 200
//! while the process serves HTTP (liveness); `GET /readyz` answers 200 only while every
//! named check holds and the process is not draining, and otherwise 503 with the reasons
//! in words (readiness). Each role names its own checks (a master: registered with
//! signaling, render workers up; a worker: NATS connected) and turns readiness off the
//! moment it starts to drain, so traffic stops before it exits.

use std::{
    collections::BTreeMap,
    sync::{Arc, Mutex},
};

use axum::{Router, http::StatusCode, routing::get};

/// A process's readiness: checks that do not hold, and whether it drains.
#[derive(Clone, Default)]
pub struct Health(Arc<Mutex<State>>);

#[derive(Default)]
struct State {
    failing: BTreeMap<&'static str, String>,
    draining: bool,
}

impl Health {
    /// A health with `checks` failing until they are [`Health::pass`]ed (what is not up yet).
    pub fn starting(checks: &[(&'static str, &str)]) -> Self {
        let health = Self::default();
        for (check, why) in checks {
            health.fail(check, why);
        }
        health
    }

    /// `check` holds now.
    pub fn pass(&self, check: &'static str) {
        self.lock().failing.remove(check);
    }

    /// `check` does not hold, because `why`.
    pub fn fail(&self, check: &'static str, why: &str) {
        self.lock().failing.insert(check, why.to_owned());
    }

    /// From now on not ready: the process is stopping.
    pub fn drain(&self) {
        self.lock().draining = true;
    }

    pub fn is_draining(&self) -> bool {
        self.lock().draining
    }

    /// `Ok` when ready; otherwise every reason, one per line.
    pub fn readiness(&self) -> Result<(), String> {
        let s = self.lock();
        let mut why: Vec<String> = s.failing.iter().map(|(check, why)| format!("{check}: {why}")).collect();
        if s.draining {
            why.insert(0, "draining: the process is shutting down".into());
        }
        if why.is_empty() { Ok(()) } else { Err(why.join("\n")) }
    }

    /// `GET /healthz` and `GET /readyz`, to merge into a role's router.
    pub fn routes<S: Clone + Send + Sync + 'static>(&self) -> Router<S> {
        let health = self.clone();
        Router::new().route("/healthz", get(|| async { "ok\n" })).route(
            "/readyz",
            get(move || {
                let answer = match health.readiness() {
                    Ok(()) => (StatusCode::OK, "ready\n".to_owned()),
                    Err(why) => (StatusCode::SERVICE_UNAVAILABLE, format!("{why}\n")),
                };
                std::future::ready(answer)
            }),
        )
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ready_only_when_every_check_holds_and_not_draining() {
        let h = Health::starting(&[("signaling", "not registered yet"), ("workers", "none calibrated")]);
        assert_eq!(h.readiness(), Err("signaling: not registered yet\nworkers: none calibrated".into()));
        h.pass("signaling");
        h.pass("workers");
        assert_eq!(h.readiness(), Ok(()));
        h.fail("signaling", "connection lost");
        assert!(h.readiness().unwrap_err().contains("connection lost"));
        h.pass("signaling");
        h.drain();
        assert!(h.is_draining());
        assert!(h.readiness().unwrap_err().starts_with("draining"));
    }
}
