//! Nephele's `nephele` binary and its three products, one room each:
//!
//! - [`master`]: the master node — a sans-IO core (sessions, admission, scheduler, frame
//!   rules) with its edge drivers (WebRTC peers, signaling link, encoder threads, render
//!   workers);
//! - [`worker`]: the render worker of the NATS farm (`nephele worker`) and the protocol its
//!   masters speak with it;
//! - [`client`]: the headless streaming client and pose replay, which share only the wire
//!   protocol ([`wire`]) with the master;
//! - [`cli`]: the subcommands (serve, render, train, eval, bench, …) and their tools.
//!
//! Beside them: [`catalog`] (the scenes a process serves), [`assets`] (loading assets and
//! choosing a backend), [`web`] (the HTTP side of `nephele serve`).

pub mod assets;
pub mod catalog;
pub mod cli;
pub mod client;
pub mod master;
pub mod web;
pub mod wire;
pub mod worker;
