//! Real networks, on one machine: every session's media over one UDP port, and a client that
//! may use only TURN relay candidates streaming through a real coturn (Debian's
//! `turnserver`, started per test on free loopback ports) with the credential signaling
//! minted for its session, or failing in words when the secret is wrong.

use std::{net::UdpSocket, sync::Arc, time::Duration};

use nephele_client::{ClientNet, ClientOptions, Receive, StreamClient, replay::Trace};
use nephele_core::CoreConfig;
use nephele_e2e::{Coturn, core_config, fixture_scene};
use nephele_farm::catalog::Catalog;
use nephele_master::{MasterConfig, compositor::ComposeChoice, encoder::DEFAULT_BITS_PER_PIXEL, web};
use nephele_protocol::ice::{IceConfig, TurnAuth};
use nephele_renderer::{FastCpuBackend, RenderSettings};
use nephele_rtc::{RtcConfig, UdpPorts};
use nephele_signaling::{HubConfig, Mode};

fn opts(url: &str, width: u32, height: u32, receive: Receive) -> ClientOptions {
    ClientOptions { signal_url: url.into(), scene: "trio".into(), mode: Mode::Viewer, width, height, fps: 25, token: None, receive, quilt: None, depth: false }
}

/// A UDP port free a moment ago (the server binds it next).
fn free_udp_port() -> u16 {
    UdpSocket::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

async fn start(core: CoreConfig, rtc: RtcConfig, hub: HubConfig) -> web::LocalServer {
    let catalog = Arc::new(Catalog::load(&[fixture_scene()], &FastCpuBackend, RenderSettings::default()).expect("the scene loads"));
    let cfg = MasterConfig { name: "field".into(), token: None, rtc, core, workers: 1, compose: ComposeChoice::Cpu, bits_per_pixel: DEFAULT_BITS_PER_PIXEL, nats: None };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    web::spawn_local_with(listener, catalog, cfg, hub).await.expect("the server starts")
}

/// Sends `poses` poses 40 ms apart and returns the frames received.
async fn stream(client: &mut StreamClient, poses: u32, width: u32, height: u32) -> usize {
    let trace = Trace::builtin("orbit").unwrap();
    let mut frames = 0;
    for seq in 1..=poses {
        client.send_pose(&trace.pose_message(seq, width, height)).await.unwrap();
        tokio::time::sleep(Duration::from_millis(40)).await;
        while client.frames.try_recv().is_ok() {
            frames += 1;
        }
    }
    let drain = tokio::time::Instant::now() + Duration::from_millis(500);
    while let Ok(Some(_)) = tokio::time::timeout_at(drain, client.frames.recv()).await {
        frames += 1;
    }
    frames
}

/// Thirty people behind one NAT (one address) open the page within two seconds, at the
/// default per-address limits: every one of them streams, every session over the server's
/// one UDP port.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_sessions_from_one_address_share_one_udp_port() {
    nephele_e2e::log_from_env();
    let port = free_udp_port();
    let rtc = RtcConfig { udp: UdpPorts::Mux(port), ..RtcConfig::loopback() };
    let server = start(core_config(30), rtc, HubConfig::default()).await;
    let url = server.signal_url();
    let started = std::time::Instant::now();
    let joins = (0..30).map(|k| {
        let o = opts(&url, 64, 48, if k == 0 { Receive::Decode } else { Receive::AccessUnits });
        tokio::spawn(async move {
            // All thirty within two seconds.
            tokio::time::sleep(Duration::from_millis(k * 60)).await;
            let mut c = StreamClient::connect(&o).await.unwrap_or_else(|e| panic!("client {k} connects: {e:#}"));
            let frames = stream(&mut c, 40, 64, 48).await;
            let pair = c.selected_pair().await;
            c.close().await;
            (frames, pair)
        })
    });
    let mut results = Vec::new();
    for r in joins.collect::<Vec<_>>() {
        results.push(r.await.unwrap());
    }
    for (k, (frames, pair)) in results.iter().enumerate() {
        assert!(*frames >= 10, "client {k} got {frames} frames");
        let (_, remote) = pair.as_ref().unwrap_or_else(|| panic!("client {k} has no candidate pair"));
        assert_eq!(remote.port, port, "client {k} streams from {remote:?}, not the one UDP port {port}");
    }
    println!(
        "30 sessions from one address over UDP port {port} in {:.1} s: frames per client min {}",
        started.elapsed().as_secs_f64(),
        results.iter().map(|r| r.0).min().unwrap()
    );
}

fn hub_with_turn(port: u16, secret: &str) -> HubConfig {
    let url = format!("turn:127.0.0.1:{port}?transport=udp").parse().unwrap();
    HubConfig { ice: IceConfig::new(vec![url], TurnAuth::Secret { secret: secret.into(), ttl_s: 600 }).unwrap(), ..HubConfig::default() }
}

/// A coturn sharing `turn_secret`, a server minting credentials from `minting_secret`, and
/// a relay-only client (a browser's `iceTransportPolicy: "relay"`) trying to connect.
async fn relay_only_client(turn_secret: &str, minting_secret: &str) -> (Coturn, web::LocalServer, anyhow::Result<StreamClient>) {
    nephele_e2e::log_from_env();
    let turn = Coturn::start(turn_secret);
    let server = start(core_config(2), RtcConfig::loopback(), hub_with_turn(turn.port, minting_secret)).await;
    let net = ClientNet { relay_only: true, ..ClientNet::default() };
    let client = StreamClient::connect_with(&opts(&server.signal_url(), 96, 64, Receive::Decode), &net).await;
    (turn, server, client)
}

/// The client's only candidates are on the TURN server, logged into with the credential
/// signaling minted for its session.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_relay_only_client_streams_through_turn() {
    let (_turn, _server, client) = relay_only_client("north-sea", "north-sea").await;
    let mut client = client.expect("the client connects through TURN");
    let frames = stream(&mut client, 40, 96, 64).await;
    let (local, remote) = client.selected_pair().await.expect("a candidate pair");
    println!("relayed: {frames} frames over {local:?} → {remote:?}");
    assert_eq!(local.kind, "relay", "the client's end of the pair is not a TURN relay: {local:?}");
    assert!(frames >= 20, "only {frames} frames through TURN");
    client.close().await;
}

/// A TURN secret the TURN server does not share: the relay-only client is told in words
/// that no relay candidate could be gathered (not a silent 30 s timeout).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn turn_refusing_the_credentials_is_an_error_in_words() {
    let started = std::time::Instant::now();
    let (turn, _server, client) = relay_only_client("north-sea", "wrong-secret").await;
    let text = format!("{:#}", client.err().expect("no relay, no stream"));
    assert!(text.contains("no TURN relay candidate") && text.contains(&format!("127.0.0.1:{}", turn.port)), "{text}");
    println!("refused after {:.1} s: {text}", started.elapsed().as_secs_f64());
}

/// Relay only against a server that offers no TURN server: refused in words at once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn relay_only_without_a_turn_server_is_an_error_in_words() {
    let server = start(core_config(2), RtcConfig::loopback(), HubConfig::default()).await;
    let net = ClientNet { relay_only: true, ..ClientNet::default() };
    let err = StreamClient::connect_with(&opts(&server.signal_url(), 96, 64, Receive::Decode), &net).await.err().expect("no TURN, no relay");
    assert!(format!("{err:#}").contains("relay only needs a TURN server"), "{err:#}");
}
