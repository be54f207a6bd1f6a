//! Real websockets on 127.0.0.1: a fake master and browser-like clients talk to the
//! signaling server through `/signal`, and `/status` reports the load.

use std::net::SocketAddr;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use nephele_signaling::{HubConfig, serve};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream, connect_async};

type Ws = WebSocketStream<MaybeTlsStream<TcpStream>>;

async fn start() -> SocketAddr {
    start_with(HubConfig {
        max_message_bytes: 4096,
        ..HubConfig::default()
    })
    .await
}

async fn start_with(cfg: HubConfig) -> SocketAddr {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(serve(listener, cfg));
    addr
}

async fn connect(addr: SocketAddr) -> Ws {
    connect_async(format!("ws://{addr}/signal"))
        .await
        .unwrap()
        .0
}

async fn send(ws: &mut Ws, msg: Value) {
    ws.send(Message::text(msg.to_string())).await.unwrap();
}

async fn recv(ws: &mut Ws) -> Value {
    loop {
        let msg = tokio::time::timeout(Duration::from_secs(5), ws.next())
            .await
            .expect("timed out")
            .unwrap()
            .unwrap();
        if let Message::Text(text) = msg {
            return serde_json::from_str(text.as_str()).unwrap();
        }
    }
}

async fn join(addr: SocketAddr, master: &mut Ws) -> (Ws, String) {
    let mut client = connect(addr).await;
    send(
        &mut client,
        json!({"type":"join","scene":"cubes","mode":"vr","width":1920,"height":1080,"fps":72}),
    )
    .await;
    let joined = recv(&mut client).await;
    assert_eq!(joined["type"], "joined", "{joined}");
    assert_eq!(joined["master"], "farm-1");
    let session = joined["session"].as_str().unwrap().to_owned();
    assert_eq!(
        recv(master).await,
        json!({"type":"join","session":session,"scene":"cubes","mode":"vr","width":1920,"height":1080,"fps":72})
    );
    (client, session)
}

/// Offer → answer and ICE both ways for one session.
async fn round_trip(client: &mut Ws, master: &mut Ws, session: &str) {
    let sdp = format!("v=0 offer for {session}");
    send(client, json!({"type":"offer","sdp":sdp})).await;
    assert_eq!(
        recv(master).await,
        json!({"type":"offer","session":session,"sdp":sdp})
    );
    send(
        master,
        json!({"type":"answer","session":session,"sdp":"v=0 answer"}),
    )
    .await;
    assert_eq!(
        recv(client).await,
        json!({"type":"answer","sdp":"v=0 answer"})
    );
    let cand = json!({"candidate":"candidate:0 1 UDP 2122252543 192.168.1.5 50000 typ host","sdpMid":"0","sdpMLineIndex":0});
    send(client, json!({"type":"ice","candidate":cand})).await;
    assert_eq!(
        recv(master).await,
        json!({"type":"ice","session":session,"candidate":cand})
    );
    send(
        master,
        json!({"type":"ice","session":session,"candidate":cand}),
    )
    .await;
    assert_eq!(recv(client).await, json!({"type":"ice","candidate":cand}));
}

async fn http_get(addr: SocketAddr, path: &str) -> Value {
    let mut tcp = TcpStream::connect(addr).await.unwrap();
    tcp.write_all(
        format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes(),
    )
    .await
    .unwrap();
    let mut response = String::new();
    tcp.read_to_string(&mut response).await.unwrap();
    assert!(response.starts_with("HTTP/1.1 200"), "{response}");
    serde_json::from_str(response.split("\r\n\r\n").nth(1).unwrap()).unwrap()
}

#[tokio::test]
async fn signaling_over_real_websockets() {
    let addr = start().await;
    let mut master = connect(addr).await;
    send(
        &mut master,
        json!({"type":"register","name":"farm-1","capacity":4,"scenes":["cubes"]}),
    )
    .await;
    assert_eq!(
        recv(&mut master).await,
        json!({"type":"registered","master":"farm-1"})
    );

    let (mut first, s1) = join(addr, &mut master).await;
    round_trip(&mut first, &mut master, &s1).await;

    // Garbage and oversize messages get an error; the session keeps working.
    first
        .send(Message::text("{\"type\": \"offer\", "))
        .await
        .unwrap();
    assert_eq!(recv(&mut first).await["code"], "bad_message");
    send(&mut first, json!({"type":"offer","sdp":"x".repeat(5000)})).await;
    assert_eq!(recv(&mut first).await["code"], "too_large");
    round_trip(&mut first, &mut master, &s1).await;

    // A second client is unaffected by the first one's garbage.
    let (mut second, s2) = join(addr, &mut master).await;
    first.send(Message::text("garbage")).await.unwrap();
    assert_eq!(recv(&mut first).await["code"], "bad_message");
    round_trip(&mut second, &mut master, &s2).await;
    round_trip(&mut first, &mut master, &s1).await;

    let status = http_get(addr, "/status").await;
    assert_eq!(
        status,
        // Three websockets, and this GET's own connection.
        json!({"masters":[{"master":"farm-1","capacity":4,"sessions":2,"scenes":["cubes"],"free_rays_per_s":null,"saturated":false}],"clients":2,"sessions":2,"connections":4,"connections_refused":0,"connections_evicted":0,"sessions_started":2,"refused":{"bad_message":2,"too_large":1}})
    );

    // A client that goes away frees its slot and the master hears `leave`.
    first.close(None).await.unwrap();
    assert_eq!(
        recv(&mut master).await,
        json!({"type":"leave","session":s1})
    );
    // The master ending a session reaches its client.
    send(
        &mut master,
        json!({"type":"end","session":s2,"reason":"bye"}),
    )
    .await;
    assert_eq!(
        recv(&mut second).await,
        json!({"type":"ended","reason":"bye"})
    );

    // A master that disconnects is reported to its clients.
    let (mut third, _) = join(addr, &mut master).await;
    master.close(None).await.unwrap();
    let lost = recv(&mut third).await;
    assert_eq!(
        (lost["type"].as_str(), lost["code"].as_str()),
        (Some("error"), Some("master_lost")),
        "{lost}"
    );
    send(
        &mut third,
        json!({"type":"join","scene":"cubes","mode":"ar","width":640,"height":480,"fps":30}),
    )
    .await;
    assert_eq!(recv(&mut third).await["code"], "no_capacity");
}

#[tokio::test]
async fn silent_master_times_out() {
    let addr = start_with(HubConfig {
        heartbeat_timeout: Duration::from_millis(500),
        ..HubConfig::default()
    })
    .await;
    let mut master = connect(addr).await;
    send(
        &mut master,
        json!({"type":"register","name":"farm-1","capacity":1,"scenes":["cubes"]}),
    )
    .await;
    assert_eq!(recv(&mut master).await["type"], "registered");
    let (mut client, _) = join(addr, &mut master).await;
    // Heartbeats keep the master alive past the timeout...
    for _ in 0..8 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        send(&mut master, json!({"type":"heartbeat","sessions":1})).await;
    }
    assert_eq!(http_get(addr, "/status").await["masters"][0]["sessions"], 1);
    // ...and silence drops it: the master is told and closed, the client hears `master_lost`.
    assert_eq!(recv(&mut master).await["code"], "master_lost");
    assert!(matches!(
        master.next().await,
        Some(Ok(Message::Close(_))) | None
    ));
    assert_eq!(recv(&mut client).await["code"], "master_lost");
    assert_eq!(http_get(addr, "/status").await["masters"], json!([]));
}

/// A client flooding ICE at its master (which is not reading) is cut off with
/// `rate_limited`; the master keeps its connection and its other sessions. Before the
/// allowance, ~100 messages filled the master's queue and signaling dropped the *master*.
#[tokio::test]
async fn a_relay_flood_drops_the_flooder_not_the_master() {
    let addr = start().await;
    let mut master = connect(addr).await;
    send(&mut master, json!({"type":"register","name":"farm-1","capacity":4,"scenes":["cubes"]})).await;
    assert_eq!(recv(&mut master).await["type"], "registered");
    let (mut bystander, s1) = join(addr, &mut master).await;
    let (mut flooder, _) = join(addr, &mut master).await;
    let cand = json!({"candidate":"candidate:0 1 UDP 2122252543 10.0.0.1 50000 typ host","sdpMid":"0","sdpMLineIndex":0});
    // The master reads nothing while 200 candidates are sent.
    let mut refused = None;
    for _ in 0..200 {
        if flooder.send(Message::text(json!({"type":"ice","candidate":cand}).to_string())).await.is_err() {
            break;
        }
    }
    while let Ok(Some(Ok(msg))) = tokio::time::timeout(Duration::from_secs(2), flooder.next()).await {
        if let Message::Text(text) = msg {
            let v: Value = serde_json::from_str(text.as_str()).unwrap();
            if v["type"] == "error" {
                refused = Some(v);
            }
        }
    }
    let refused = refused.expect("the flooder was told why");
    assert_eq!(refused["code"], "rate_limited", "{refused}");
    // The master drains what was relayed (at most the burst) and still serves the bystander.
    let mut relayed = 0;
    loop {
        let m = recv(&mut master).await;
        if m["type"] == "leave" {
            break;
        }
        assert_eq!(m["type"], "ice", "{m}");
        relayed += 1;
    }
    assert!(relayed <= 40, "{relayed} candidates relayed");
    round_trip(&mut bystander, &mut master, &s1).await;
    assert_eq!(http_get(addr, "/status").await["masters"][0]["sessions"], 1);
}

/// With an operator token, `/status` needs it (`Authorization: Bearer …`); masters need
/// the masters' token and the clients' token does not register one.
#[tokio::test]
async fn status_and_registration_need_their_own_secrets() {
    let addr = start_with(HubConfig { token: Some("viewer".into()), master_token: Some("master".into()), operator_token: Some("operator".into()), ..HubConfig::default() }).await;
    let get = |auth: Option<&'static str>| async move {
        let mut tcp = TcpStream::connect(addr).await.unwrap();
        let header = auth.map_or(String::new(), |a| format!("Authorization: Bearer {a}\r\n"));
        tcp.write_all(format!("GET /status HTTP/1.1\r\nHost: x\r\n{header}Connection: close\r\n\r\n").as_bytes()).await.unwrap();
        let mut response = String::new();
        tcp.read_to_string(&mut response).await.unwrap();
        response
    };
    assert!(get(None).await.starts_with("HTTP/1.1 401"));
    assert!(get(Some("viewer")).await.starts_with("HTTP/1.1 401"));
    assert!(get(Some("operator")).await.starts_with("HTTP/1.1 200"));
    let mut rogue = connect(addr).await;
    send(&mut rogue, json!({"type":"register","name":"rogue","capacity":99,"scenes":["cubes"],"token":"viewer"})).await;
    assert_eq!(recv(&mut rogue).await["code"], "unauthorized");
    let mut master = connect(addr).await;
    send(&mut master, json!({"type":"register","name":"farm-1","capacity":1,"scenes":["cubes"],"token":"master"})).await;
    assert_eq!(recv(&mut master).await["type"], "registered");
}

/// A client that closes the websocket gets the close handshake answered (a clean close,
/// not 1006 "abnormal closure").
#[tokio::test]
async fn the_close_handshake_is_answered() {
    use tokio_tungstenite::tungstenite::protocol::{CloseFrame, frame::coding::CloseCode};
    let addr = start().await;
    let mut client = connect(addr).await;
    client.send(Message::Close(Some(CloseFrame { code: CloseCode::Normal, reason: "bye".into() }))).await.unwrap();
    let reply = tokio::time::timeout(Duration::from_secs(5), client.next()).await.expect("no reply to close");
    match reply {
        Some(Ok(Message::Close(Some(frame)))) => assert_eq!(frame.code, CloseCode::Normal),
        other => panic!("expected a close frame back, got {other:?}"),
    }
}

/// Connection caps: sockets past the per-address cap (and past the total cap) are closed
/// on accept; a closed socket frees its place.
#[tokio::test]
async fn connections_past_the_caps_are_closed_at_once() {
    let limits = nephele_limits::ConnLimits { max_connections_per_address: 3, ..Default::default() };
    let addr = start_with(HubConfig { limits, ..HubConfig::default() }).await;
    let mut open = Vec::new();
    for _ in 0..3 {
        open.push(connect(addr).await);
    }
    assert!(connect_async(format!("ws://{addr}/signal")).await.is_err(), "a fourth socket from one address was accepted");
    drop(open.pop());
    // The server notices the close on its next read; then the place is free.
    let mut again = None;
    for _ in 0..50 {
        if let Ok((ws, _)) = connect_async(format!("ws://{addr}/signal")).await {
            again = Some(ws);
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(again.is_some(), "a closed socket did not free its place");

    // At the total cap, sockets that hold a role are never pushed out: with two masters
    // registered, a third socket is closed at once.
    let limits = nephele_limits::ConnLimits { max_connections: 2, ..Default::default() };
    let addr = start_with(HubConfig { limits, ..HubConfig::default() }).await;
    let (mut a, mut b) = (connect(addr).await, connect(addr).await);
    for (ws, name) in [(&mut a, "farm-1"), (&mut b, "farm-2")] {
        send(ws, json!({"type":"register","name":name,"capacity":4,"scenes":["cubes"]})).await;
        assert_eq!(recv(ws).await["type"], "registered");
    }
    assert!(connect_async(format!("ws://{addr}/signal")).await.is_err(), "a third socket past the total cap was accepted");
}

/// Closes within 5 s: the server's close frame, or the socket's end.
async fn closed_by_server(ws: &mut Ws) -> bool {
    tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            match ws.next().await {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => return,
                Some(Ok(_)) => continue,
            }
        }
    })
    .await
    .is_ok()
}

/// Sockets that never join fill the total cap (from many addresses, each under its own
/// cap): a newcomer still gets in, the oldest idle socket is closed for it, and a master
/// and a client in a session are never the ones closed.
#[tokio::test]
async fn idle_sockets_at_the_total_cap_make_room_for_a_newcomer() {
    let limits = nephele_limits::ConnLimits { max_connections: 6, hello_timeout_ms: 60_000, ..Default::default() };
    let addr = start_with(HubConfig { limits, ..HubConfig::default() }).await;
    let mut master = connect(addr).await;
    send(&mut master, json!({"type":"register","name":"farm-1","capacity":4,"scenes":["cubes"]})).await;
    assert_eq!(recv(&mut master).await["type"], "registered");
    let (mut client, session) = join(addr, &mut master).await;
    let mut idle = Vec::new();
    for _ in 0..4 {
        idle.push(connect(addr).await);
        tokio::time::sleep(Duration::from_millis(20)).await; // admission order = age
    }
    // The cap is full (6). Three newcomers: each pushes out the oldest idle socket.
    let mut newcomers = Vec::new();
    for (n, oldest) in idle.iter_mut().take(3).enumerate() {
        let ws = connect_async(format!("ws://{addr}/signal")).await;
        assert!(ws.is_ok(), "newcomer {n} was refused at the total cap though idle sockets were open");
        newcomers.push(ws.unwrap().0);
        assert!(closed_by_server(oldest).await, "idle socket {n} (the oldest left) was not closed for newcomer {n}");
    }
    // One more newcomer joins (pushing out the last idle socket) and is paired; the master
    // and the first client still work.
    let (mut second, s2) = join(addr, &mut master).await;
    assert!(closed_by_server(&mut idle[3]).await, "the last idle socket was not closed for the joining newcomer");
    round_trip(&mut client, &mut master, &session).await;
    round_trip(&mut second, &mut master, &s2).await;
    let status = http_get(addr, "/status").await;
    assert!(status["connections_evicted"].as_u64().unwrap() >= 3, "{status}");
    assert_eq!(status["sessions"], 2, "{status}");
}

/// Headers that never finish, and websockets that never speak, are closed.
#[tokio::test]
async fn slow_headers_and_silent_websockets_are_closed() {
    let limits = nephele_limits::ConnLimits { header_timeout_ms: 300, hello_timeout_ms: 300, ..Default::default() };
    let addr = start_with(HubConfig { limits, ..HubConfig::default() }).await;
    // Slowloris: half a request, then nothing.
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(b"GET /status HTTP/1.1\r\nHost: x\r\n").await.unwrap();
    let mut buf = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(5), s.read_to_end(&mut buf)).await;
    assert!(read.is_ok(), "a request with unfinished headers was kept open for 5 s");
    // A websocket that never sends `join` or `register`.
    let mut ws = connect(addr).await;
    let end = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            match ws.next().await {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => break,
                Some(Ok(_)) => continue,
            }
        }
    })
    .await;
    assert!(end.is_ok(), "a silent websocket was kept open for 5 s");
}
