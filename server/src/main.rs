//! `nephele`: parse the command line and run it (`nephele::cli`).

use clap::Parser;

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::from_default_env()).with_writer(std::io::stderr).init();
    nephele::cli::run(nephele::cli::Cli::parse())
}
