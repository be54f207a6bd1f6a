//! `nephele`: parse the command line and run it (`nephele::cli`).

use clap::Parser;

fn main() -> anyhow::Result<()> {
    // Before any thread starts: one malloc arena keeps the resident set steady under churn.
    nephele_master::memory::use_one_arena();
    // Warnings and our own notices by default; RUST_LOG says otherwise.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn,nephele=info"));
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    nephele::cli::run(nephele::cli::Cli::parse())
}
