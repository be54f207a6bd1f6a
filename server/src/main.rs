//! `nephele`: parse the command line and run it (`nephele::cli`).

use clap::Parser;

/// Where our own notices come from (every crate of the workspace but the renderer's and
/// signaling's, which speak at warn).
const LOG_FILTER: &str = "warn,nephele=info,nephele_core=info,nephele_master=info,nephele_farm=info,nephele_client=info,nephele_bench=info";

fn main() -> anyhow::Result<()> {
    // Before any thread starts: one malloc arena keeps the resident set steady under churn.
    nephele_master::memory::use_one_arena();
    quiet_vulkan_loader();
    forget_empty_settings();
    let cli = nephele::cli::Cli::parse();
    // Warnings and our own notices by default; RUST_LOG says otherwise.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(LOG_FILTER));
    let logs = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    nephele::cli::lifecycle::use_json_logs(cli.log_format == nephele::cli::LogFormat::Json);
    match cli.log_format {
        nephele::cli::LogFormat::Text => logs.init(),
        nephele::cli::LogFormat::Json => logs.json().flatten_event(true).with_current_span(false).init(),
    }
    nephele::cli::run(cli)
}

/// An empty `NEPHELE_…` variable means "not set" (as a compose file's `${VAR:-}` or an
/// optional Kubernetes key leaves it), not an empty value for its flag to refuse.
#[allow(unsafe_code)]
fn forget_empty_settings() {
    let empty: Vec<std::ffi::OsString> = std::env::vars_os().filter(|(k, v)| k.to_string_lossy().starts_with("NEPHELE_") && v.is_empty()).map(|(k, _)| k).collect();
    for key in empty {
        // SAFETY: called first thing in `main`, before any other thread exists.
        unsafe { std::env::remove_var(key) };
    }
}

/// On a headless machine (no login session) `XDG_RUNTIME_DIR` is unset, and probing Vulkan
/// adapters makes the Wayland client library print "error: XDG_RUNTIME_DIR is invalid or not
/// set in the environment." twice — words that are not ours and mean nothing here. Give the
/// process a private runtime directory (mode 0700, as the XDG spec asks) before any thread
/// starts.
#[allow(unsafe_code)]
fn quiet_vulkan_loader() {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    if std::env::var_os("XDG_RUNTIME_DIR").is_some() {
        return;
    }
    let uid = std::fs::metadata("/proc/self").map(|m| m.uid()).unwrap_or(0);
    let dir = std::env::temp_dir().join(format!("nephele-runtime-{uid}"));
    let _ = std::fs::DirBuilder::new().mode(0o700).create(&dir);
    let private = std::fs::metadata(&dir).is_ok_and(|m| m.is_dir() && m.uid() == uid && m.permissions().mode() & 0o077 == 0);
    if private {
        // SAFETY: called first thing in `main`, before any other thread exists, so nothing
        // reads the environment while it changes.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", &dir) };
    }
}
