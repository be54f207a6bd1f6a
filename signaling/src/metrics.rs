//! Prometheus exposition as every Nephele role serves it (`GET /metrics`): OpenMetrics text
//! with its content type, `nephele_build_info{version, role}`, and signaling's own series,
//! read from the hub when scraped (so a session that ended leaves no series behind).
//!
//! Conventions (Prometheus's naming guide): base units (seconds, bytes) in the name,
//! counters end in `_total`, every name starts `nephele_`.

use axum::{
    http::header::CONTENT_TYPE,
    response::{IntoResponse, Response},
};
use prometheus_client::{
    collector::Collector,
    encoding::{DescriptorEncoder, EncodeMetric, text::encode},
    metrics::{counter::ConstCounter, gauge::ConstGauge, info::Info},
    registry::Registry,
};

use crate::SignalState;

/// The OpenMetrics 1.0 text content type.
pub const OPENMETRICS_CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// A registry with the `nephele_` prefix and `nephele_build_info` for `role` (master,
/// signal, serve, worker).
pub fn registry(role: &'static str) -> Registry {
    let mut registry = Registry::with_prefix("nephele");
    let labels = vec![("version", env!("CARGO_PKG_VERSION")), ("role", role)];
    registry.register("build", "The running build: crate version and the process's role", Info::new(labels));
    registry
}

/// `registry` as OpenMetrics text.
pub fn encode_text(registry: &Registry) -> String {
    let mut out = String::new();
    // Writing into a String cannot fail.
    encode(&mut out, registry).expect("metrics encode into a String");
    out
}

/// An OpenMetrics answer.
pub fn response(text: String) -> Response {
    ([(CONTENT_TYPE, OPENMETRICS_CONTENT_TYPE)], text).into_response()
}

/// Signaling's series, read from its state at every scrape.
pub struct SignalCollector(pub SignalState);

impl std::fmt::Debug for SignalCollector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SignalCollector")
    }
}

impl Collector for SignalCollector {
    fn encode(&self, mut encoder: DescriptorEncoder<'_>) -> Result<(), std::fmt::Error> {
        let stats = self.0.stats();
        let gauges = [
            ("signal_masters", "Masters registered with signaling", stats.masters.len()),
            ("signal_clients", "Client connections holding a session", stats.clients),
            ("signal_sessions", "Sessions paired with a master", stats.sessions),
            ("signal_sessions_connecting", "Sessions paired whose WebRTC connection has not started yet", self.0.connecting()),
            ("signal_connections", "Open HTTP and websocket connections", stats.connections),
        ];
        for (name, help, value) in gauges {
            let gauge = ConstGauge::new(i64::try_from(value).unwrap_or(i64::MAX));
            gauge.encode(encoder.encode_descriptor(name, help, None, gauge.metric_type())?)?;
        }
        let counters = [
            ("signal_sessions_started", "Sessions paired since start", stats.sessions_started),
            ("signal_connections_refused", "Connections closed at accept because a cap was reached", stats.connections_refused),
            ("signal_connections_evicted", "Connections without a role closed to make room for newer ones", stats.connections_evicted),
        ];
        for (name, help, value) in counters {
            let counter = ConstCounter::new(value);
            counter.encode(encoder.encode_descriptor(name, help, None, counter.metric_type())?)?;
        }
        let mut family = encoder.encode_descriptor("signal_refused", "Messages refused, by the error code their sender got", None, prometheus_client::metrics::MetricType::Counter)?;
        for (code, count) in &stats.refused {
            let labels = [("code", code.as_str())];
            ConstCounter::new(*count).encode(family.encode_family(&labels)?)?;
        }
        Ok(())
    }
}

/// Registers signaling's series for `state` in `registry`.
pub fn register_signaling(registry: &mut Registry, state: &SignalState) {
    registry.register_collector(Box::new(SignalCollector(state.clone())));
}
