//! The hub on simulated time: joins, routing, limits, heartbeats and failures, one
//! behaviour per test, no sockets.

use super::*;
use serde_json::{Value, json};

const TIMEOUT: Duration = Duration::from_secs(15);

fn hub_with(token: Option<&str>) -> (Hub, Instant) {
    let cfg = HubConfig {
        token: token.map(str::to_owned),
        heartbeat_timeout: TIMEOUT,
        max_message_bytes: 1024,
        ..HubConfig::default()
    };
    (Hub::new(cfg), Instant::now())
}

fn send(hub: &mut Hub, conn: u64, msg: Value, now: Instant) -> Vec<Outgoing> {
    hub.handle_text(ConnId(conn), &msg.to_string(), now)
}

/// Outgoing messages as `(to, json)` for easy matching.
fn json_of(out: &[Outgoing]) -> Vec<(u64, Value)> {
    out.iter()
        .map(|o| (o.to.0, serde_json::from_str(&o.msg.to_json()).unwrap()))
        .collect()
}

fn error_code(out: &[Outgoing]) -> (u64, String, String) {
    let [(to, v)] = json_of(out).try_into().unwrap();
    assert_eq!(v["type"], "error", "{v}");
    (
        to,
        v["code"].as_str().unwrap().to_owned(),
        v["message"].as_str().unwrap().to_owned(),
    )
}

fn add_master(hub: &mut Hub, conn: u64, name: &str, capacity: u32, now: Instant) {
    hub.connect(ConnId(conn), now);
    let out = send(
        hub,
        conn,
        json!({"type":"register","name":name,"capacity":capacity,"scenes":["cubes","A-z_9"]}),
        now,
    );
    assert_eq!(
        json_of(&out),
        vec![(conn, json!({"type":"registered","master":name}))]
    );
}

fn join_json() -> Value {
    json!({"type":"join","scene":"cubes","mode":"viewer","width":1280,"height":720,"fps":60})
}

/// Connect and join; returns (session, master conn).
fn add_client(hub: &mut Hub, conn: u64, now: Instant) -> (String, u64) {
    hub.connect(ConnId(conn), now);
    let out = json_of(&send(hub, conn, join_json(), now));
    assert_eq!(out.len(), 2, "{out:?}");
    let session = out[0].1["session"].as_str().unwrap().to_owned();
    assert_eq!(out[0].0, conn);
    assert_eq!(out[0].1["type"], "joined");
    assert_eq!(
        out[1].1,
        json!({"type":"join","session":session,"scene":"cubes","mode":"viewer","width":1280,"height":720,"fps":60})
    );
    (session, out[1].0)
}

fn master_sessions(hub: &Hub) -> Vec<(String, u32)> {
    hub.stats()
        .masters
        .into_iter()
        .map(|m| (m.master, m.sessions))
        .collect()
}

#[test]
fn pairs_by_free_rays_then_reports_full() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "b", 2, t0);
    add_master(&mut hub, 2, "a", 4, t0);
    // Before any heartbeat both have unbounded room: fewer sessions, then the smaller id.
    let picked: Vec<u64> = (10..12).map(|c| add_client(&mut hub, c, t0).1).collect();
    assert_eq!(picked, vec![2, 1]);
    // Heartbeats give the room; each join takes its pixel rate (1280×720×60 = 55.3 M/s).
    send(&mut hub, 1, json!({"type":"heartbeat","sessions":1,"free_rays_per_s":200e6}), t0);
    send(&mut hub, 2, json!({"type":"heartbeat","sessions":1,"free_rays_per_s":120e6}), t0);
    // b 200 → 144.7 → 89.4 (b full at 2 sessions: only a is left, 120 → 64.7 → 9.4).
    let picked: Vec<u64> = (12..15).map(|c| add_client(&mut hub, c, t0).1).collect();
    assert_eq!(picked, vec![1, 2, 2]);
    let stats = hub.stats();
    assert!((stats.masters[0].free_rays_per_s.unwrap() - (120e6 - 2.0 * 1280.0 * 720.0 * 60.0)).abs() < 1.0);
    assert_eq!(
        master_sessions(&hub),
        vec![("a".into(), 3), ("b".into(), 2)]
    );
    // A saturated master gets no joins even with a free slot.
    send(&mut hub, 2, json!({"type":"heartbeat","sessions":3,"free_rays_per_s":1e9,"saturated":true}), t0);
    hub.connect(ConnId(20), t0);
    let (to, code, message) = error_code(&send(&mut hub, 20, join_json(), t0));
    assert_eq!((to, code.as_str()), (20, "no_capacity"));
    assert_eq!(message, "all 2 masters serving scene \"cubes\" are busy: 1 report users behind their frame rates, 1 have every session slot taken; try again later");
    send(&mut hub, 2, json!({"type":"heartbeat","sessions":3,"free_rays_per_s":1e9,"saturated":false}), t0);
    assert_eq!(add_client(&mut hub, 21, t0).1, 2);
}

#[test]
fn a_scene_nobody_serves_is_refused_at_once_in_words() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, t0);
    hub.connect(ConnId(2), t0);
    let mut join = join_json();
    join["scene"] = json!("lego");
    let (to, code, message) = error_code(&send(&mut hub, 2, join, t0));
    assert_eq!((to, code.as_str()), (2, "unknown_scene"));
    assert_eq!(message, "no master serves scene \"lego\"; scenes on offer: A-z_9, cubes");
    assert_eq!(master_sessions(&hub), vec![("m".into(), 0)]);
    // The master heard nothing; the client may join a served scene.
    assert_eq!(add_client(&mut hub, 2, t0).1, 1);
    // A master listing a bad scene name is refused.
    hub.connect(ConnId(3), t0);
    let bad = json!({"type":"register","name":"x","capacity":1,"scenes":["../x"]});
    assert_eq!(error_code(&send(&mut hub, 3, bad, t0)).1, "bad_request");
}

#[test]
fn no_master_means_no_capacity() {
    let (mut hub, t0) = hub_with(None);
    hub.connect(ConnId(1), t0);
    let (_, code, message) = error_code(&send(&mut hub, 1, join_json(), t0));
    assert_eq!(code, "no_capacity");
    assert!(message.contains("no master is registered"), "{message}");
}

#[test]
fn token_is_required_when_configured() {
    let (mut hub, t0) = hub_with(Some("s3cret"));
    hub.cfg.master_token = Some("m4ster".into());
    hub.connect(ConnId(1), t0);
    let out = send(
        &mut hub,
        1,
        json!({"type":"register","name":"m","capacity":1,"scenes":["cubes"]}),
        t0,
    );
    assert_eq!(error_code(&out).1, "unauthorized");
    assert!(out[0].close);
    let out = send(
        &mut hub,
        1,
        json!({"type":"register","name":"m","capacity":1,"scenes":["cubes"],"token":"s3cre"}),
        t0,
    );
    assert_eq!(error_code(&out).1, "unauthorized");
    // The clients' token never registers a master.
    let out = send(
        &mut hub,
        1,
        json!({"type":"register","name":"m","capacity":1,"scenes":["cubes"],"token":"s3cret"}),
        t0,
    );
    assert_eq!(error_code(&out).1, "unauthorized");
    let out = send(
        &mut hub,
        1,
        json!({"type":"register","name":"m","capacity":1,"scenes":["cubes"],"token":"m4ster"}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(1, json!({"type":"registered","master":"m"}))]
    );

    hub.connect(ConnId(2), t0);
    assert_eq!(
        error_code(&send(&mut hub, 2, join_json(), t0)).1,
        "unauthorized"
    );
    let mut join = join_json();
    join["token"] = json!("m4ster");
    assert_eq!(error_code(&send(&mut hub, 2, join.clone(), t0)).1, "unauthorized", "the masters' token does not join");
    join["token"] = json!("s3cret");
    assert_eq!(json_of(&send(&mut hub, 2, join, t0))[0].1["type"], "joined");
    assert!(secrets_match("abc", "abc") && !secrets_match("abd", "abc") && !secrets_match("ab", "abc"));
}

#[test]
fn malformed_and_oversize_messages_hurt_only_their_sender() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, t0);
    let (session, _) = add_client(&mut hub, 2, t0);
    for bad in [
        "{not json",
        "[]",
        r#"{"type":"dance"}"#,
        r#"{"type":"join","scene":"x"}"#,
        "",
    ] {
        let out = hub.handle_text(ConnId(2), bad, t0);
        let (to, code, _) = error_code(&out);
        assert_eq!(
            (to, code.as_str(), out[0].close),
            (2, "bad_message", false),
            "{bad}"
        );
    }
    let big = json!({"type":"offer","sdp":"x".repeat(2000)}).to_string();
    let (to, code, message) = error_code(&hub.handle_text(ConnId(2), &big, t0));
    assert_eq!((to, code.as_str()), (2, "too_large"));
    assert!(message.contains("limit is 1024 bytes"), "{message}");
    // Masters get errors in the same shape.
    let (to, code, _) = error_code(&hub.handle_text(ConnId(1), "nope", t0));
    assert_eq!((to, code.as_str()), (1, "bad_message"));
    // The session still works.
    let out = send(&mut hub, 2, json!({"type":"offer","sdp":"v=0"}), t0);
    assert_eq!(
        json_of(&out),
        vec![(1, json!({"type":"offer","session":session,"sdp":"v=0"}))]
    );
}

#[test]
fn absurd_joins_are_bad_requests() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, t0);
    hub.connect(ConnId(2), t0);
    let cases = [
        ("width", json!(0)),
        ("width", json!(3841)),
        ("width", json!(7680)),
        ("height", json!(4321)),
        ("fps", json!(0)),
        ("fps", json!(240)),
        ("scene", json!("")),
        ("scene", json!("../etc")),
        ("scene", json!("x".repeat(65))),
    ];
    for (field, value) in cases {
        let mut join = join_json();
        join[field] = value.clone();
        assert_eq!(
            error_code(&send(&mut hub, 2, join, t0)).1,
            "bad_request",
            "{field}={value}"
        );
    }
    let mut odd = join_json();
    odd["width"] = json!(3840);
    odd["height"] = json!(1);
    odd["fps"] = json!(120);
    odd["scene"] = json!("A-z_9");
    assert_eq!(json_of(&send(&mut hub, 2, odd, t0))[0].1["type"], "joined");
    assert_eq!(
        error_code(&send(&mut hub, 2, join_json(), t0)).1,
        "bad_request",
        "second join"
    );
    assert_eq!(master_sessions(&hub), vec![("m".into(), 1)]);
}

#[test]
fn messages_must_suit_the_role() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, t0);
    let (session, _) = add_client(&mut hub, 2, t0);
    let answer = json!({"type":"answer","session":session,"sdp":"v=0"});
    assert_eq!(
        error_code(&send(&mut hub, 2, answer.clone(), t0)).1,
        "wrong_role"
    );
    assert_eq!(
        error_code(&send(
            &mut hub,
            2,
            json!({"type":"register","name":"x","capacity":1,"scenes":["cubes"]}),
            t0
        ))
        .1,
        "wrong_role"
    );
    assert_eq!(
        error_code(&send(&mut hub, 1, json!({"type":"offer","sdp":"v=0"}), t0)).1,
        "wrong_role"
    );
    assert_eq!(
        error_code(&send(&mut hub, 1, join_json(), t0)).1,
        "wrong_role"
    );
    assert_eq!(
        error_code(&send(&mut hub, 1, json!({"type":"ice","candidate":{}}), t0)).1,
        "bad_request"
    );

    hub.connect(ConnId(3), t0);
    assert_eq!(
        error_code(&send(&mut hub, 3, json!({"type":"offer","sdp":"v=0"}), t0)).1,
        "not_joined"
    );
    assert_eq!(error_code(&send(&mut hub, 3, answer, t0)).1, "not_joined");
    // After leaving, session messages need a new join.
    send(&mut hub, 2, json!({"type":"leave"}), t0);
    assert_eq!(
        error_code(&send(&mut hub, 2, json!({"type":"ice","candidate":{}}), t0)).1,
        "not_joined"
    );
}

#[test]
fn relays_offer_answer_and_ice_by_session() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m1", 1, t0);
    add_master(&mut hub, 2, "m2", 1, t0);
    let (s10, m10) = add_client(&mut hub, 10, t0);
    let (s11, m11) = add_client(&mut hub, 11, t0);
    assert_eq!((m10, m11), (1, 2));
    let cand = json!({"candidate":"candidate:1 1 udp 2113937151 10.0.0.2 5000 typ host","sdpMid":"0","sdpMLineIndex":0});

    let out = send(&mut hub, 11, json!({"type":"offer","sdp":"offer11"}), t0);
    assert_eq!(
        json_of(&out),
        vec![(2, json!({"type":"offer","session":s11,"sdp":"offer11"}))]
    );
    let out = send(&mut hub, 10, json!({"type":"ice","candidate":cand}), t0);
    assert_eq!(
        json_of(&out),
        vec![(1, json!({"type":"ice","session":s10,"candidate":cand}))]
    );
    let out = send(
        &mut hub,
        1,
        json!({"type":"answer","session":s10,"sdp":"answer10"}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(10, json!({"type":"answer","sdp":"answer10"}))]
    );
    let out = send(
        &mut hub,
        2,
        json!({"type":"ice","session":s11,"candidate":cand}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(11, json!({"type":"ice","candidate":cand}))]
    );
    // A master cannot address another master's session, nor an unknown one.
    assert!(
        send(
            &mut hub,
            2,
            json!({"type":"answer","session":s10,"sdp":"x"}),
            t0
        )
        .is_empty()
    );
    assert!(
        send(
            &mut hub,
            2,
            json!({"type":"end","session":s10,"reason":"x"}),
            t0
        )
        .is_empty()
    );
    assert!(
        send(
            &mut hub,
            2,
            json!({"type":"answer","session":"s999","sdp":"x"}),
            t0
        )
        .is_empty()
    );
}

#[test]
fn session_counts_follow_leave_end_reject_disconnect_and_heartbeats() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 10, t0);
    let sessions: Vec<String> = (10..15).map(|c| add_client(&mut hub, c, t0).0).collect();
    assert_eq!(master_sessions(&hub), vec![("m".into(), 5)]);

    let out = send(&mut hub, 10, json!({"type":"leave"}), t0);
    assert_eq!(
        json_of(&out),
        vec![(1, json!({"type":"leave","session":sessions[0]}))]
    );
    let out = hub.disconnect(ConnId(11), t0);
    assert_eq!(
        json_of(&out),
        vec![(1, json!({"type":"leave","session":sessions[1]}))]
    );
    let out = send(
        &mut hub,
        1,
        json!({"type":"reject","session":sessions[2],"reason":"unknown scene"}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(
            12,
            json!({"type":"error","code":"rejected","message":"unknown scene"})
        )]
    );
    let out = send(
        &mut hub,
        1,
        json!({"type":"end","session":sessions[3],"reason":"shutting down"}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(13, json!({"type":"ended","reason":"shutting down"}))]
    );
    assert_eq!(master_sessions(&hub), vec![("m".into(), 1)]);
    assert_eq!(hub.stats().sessions, 1);
    // Ended clients may join again.
    add_client(&mut hub, 13, t0);
    assert_eq!(master_sessions(&hub), vec![("m".into(), 2)]);
    // The master's own count wins when it is higher...
    assert!(send(&mut hub, 1, json!({"type":"heartbeat","sessions":7}), t0).is_empty());
    assert_eq!(master_sessions(&hub), vec![("m".into(), 7)]);
    // ...but a stale heartbeat (sent before the latest joins reached the master)
    // cannot free capacity that paired sessions still hold.
    assert!(send(&mut hub, 1, json!({"type":"heartbeat","sessions":0}), t0).is_empty());
    assert_eq!(master_sessions(&hub), vec![("m".into(), 2)]);
}

#[test]
fn silent_master_is_dropped_and_its_clients_told() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "quiet", 4, t0);
    add_master(&mut hub, 2, "chatty", 4, t0);
    let (_, m) = add_client(&mut hub, 10, t0);
    assert_eq!(m, 2, "chatty < quiet");
    add_client(&mut hub, 11, t0);
    add_client(&mut hub, 12, t0);

    let t10 = t0 + Duration::from_secs(10);
    send(&mut hub, 2, json!({"type":"heartbeat","sessions":2}), t10);
    assert!(
        hub.tick(t0 + TIMEOUT).is_empty(),
        "exactly at the timeout is still alive"
    );
    let out = hub.tick(t0 + TIMEOUT + Duration::from_millis(1));
    let mut got = json_of(&out);
    got.sort_by_key(|(to, _)| *to);
    assert_eq!(got.len(), 2, "{got:?}");
    assert_eq!((got[0].0, &got[0].1["code"]), (1, &json!("master_lost")));
    assert!(out.iter().find(|o| o.to == ConnId(1)).unwrap().close);
    assert_eq!((got[1].0, &got[1].1["code"]), (11, &json!("master_lost")));
    assert_eq!(master_sessions(&hub), vec![("chatty".into(), 2)]);

    let out = hub.tick(t10 + TIMEOUT + Duration::from_millis(1));
    let mut lost: Vec<u64> = out.iter().map(|o| o.to.0).collect();
    lost.sort();
    assert_eq!(lost, vec![2, 10, 12]);
    assert_eq!(
        hub.stats(),
        HubStats {
            masters: vec![],
            clients: 3,
            sessions: 0,
            connections: 0,
            connections_refused: 0,
            connections_evicted: 0,
            sessions_started: 3,
            refused: Default::default(),
        }
    );
}

#[test]
fn refusals_are_counted_by_their_wire_code() {
    let (mut hub, t0) = hub_with(Some("secret"));
    hub.connect(ConnId(1), t0);
    hub.connect(ConnId(2), t0);
    let mut out = Vec::new();
    for text in ["not json", "{\"type\":\"nonsense\"}"] {
        out.extend(hub.handle_text(ConnId(1), text, t0));
    }
    // A join without the token: unauthorized.
    out.extend(send(&mut hub, 2, join_json(), t0));
    let mut expected = std::collections::BTreeMap::new();
    for (_, msg) in json_of(&out) {
        *expected.entry(msg["code"].as_str().unwrap().to_owned()).or_insert(0u64) += 1;
    }
    assert_eq!(expected.get("bad_message"), Some(&2), "{expected:?}");
    assert_eq!(expected.get("unauthorized"), Some(&1), "{expected:?}");
    assert_eq!(hub.stats().refused, expected);
}

#[test]
fn error_codes_name_themselves_as_they_travel() {
    use crate::ErrorCode::*;
    for code in [BadMessage, TooLarge, Unauthorized, NoCapacity, BadRequest, MasterLost, UnknownScene, Rejected, WrongRole, NotJoined, RateLimited] {
        assert_eq!(json!(code), json!(code.as_str()));
    }
}

#[test]
fn master_disconnect_loses_its_sessions_only() {
    let (mut hub, t0) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, t0);
    hub.connect(ConnId(2), t0);
    let out = send(
        &mut hub,
        2,
        json!({"type":"register","name":"m","capacity":4,"scenes":["cubes"]}),
        t0,
    );
    assert_eq!(
        json_of(&out),
        vec![(2, json!({"type":"registered","master":"m-2"}))]
    );
    assert_eq!(
        master_sessions(&hub),
        vec![("m".into(), 0), ("m-2".into(), 0)]
    );
    add_client(&mut hub, 10, t0);
    add_client(&mut hub, 11, t0);
    let out = json_of(&hub.disconnect(ConnId(1), t0));
    assert_eq!(
        out,
        vec![(
            10,
            json!({"type":"error","code":"master_lost","message":"master m disconnected"})
        )]
    );
    assert_eq!(
        error_code(&send(&mut hub, 10, json!({"type":"offer","sdp":"v=0"}), t0)).1,
        "not_joined"
    );
    assert_eq!(
        json_of(&send(&mut hub, 11, json!({"type":"offer","sdp":"v=0"}), t0))[0].0,
        2
    );
}

#[test]
fn joins_still_connecting_are_capped_per_address() {
    let (mut hub, now) = hub_with(None);
    hub.cfg.limits.max_pending_joins_per_address = 2;
    add_master(&mut hub, 1, "m1", 100, now);
    let (home, away): (IpAddr, IpAddr) = ("10.0.0.7".parse().unwrap(), "10.0.0.8".parse().unwrap());
    let mut sessions = Vec::new();
    for conn in 10..12 {
        hub.connect_from(ConnId(conn), home, now);
        let out = json_of(&send(&mut hub, conn, join_json(), now));
        sessions.push(out[0].1["session"].as_str().unwrap().to_owned());
    }
    // A third join from the same address waits for one of the two to connect…
    hub.connect_from(ConnId(12), home, now);
    let (to, code, message) = error_code(&send(&mut hub, 12, join_json(), now));
    assert_eq!((to, code.as_str()), (12, "rate_limited"), "{message}");
    assert!(message.contains("limit 2"), "{message}");
    // …while another address is not held up…
    hub.connect_from(ConnId(13), away, now);
    assert_eq!(json_of(&send(&mut hub, 13, join_json(), now)).len(), 2);
    // …and once the master says one connected, the address may join again (the
    // refused connection was not closed).
    assert!(send(&mut hub, 1, json!({"type":"connected","session":sessions[0]}), now).is_empty());
    assert_eq!(json_of(&send(&mut hub, 12, join_json(), now)).len(), 2);
}

/// Found with `bench abuse`: a 4K join → pose → leave loop from one address, each
/// session admitted and left at once, took 40% of a bystander's frames on a server with
/// admission open. New sessions per address now come from a token bucket.
#[test]
fn new_sessions_per_address_are_throttled() {
    let (mut hub, now) = hub_with(None);
    (hub.cfg.limits.join_burst_per_address, hub.cfg.limits.joins_per_address_per_minute) = (3, 30);
    add_master(&mut hub, 1, "m1", 100, now);
    let (home, away): (IpAddr, IpAddr) = ("10.0.0.7".parse().unwrap(), "10.0.0.8".parse().unwrap());
    hub.connect_from(ConnId(10), home, now);
    // A burst of three join → leave cycles on one connection…
    for _ in 0..3 {
        assert_eq!(json_of(&send(&mut hub, 10, join_json(), now)).len(), 2);
        assert_eq!(json_of(&send(&mut hub, 10, json!({"type":"leave"}), now)).len(), 1);
    }
    // …then the fourth is refused, on this connection or a new one from the address,
    // and the connection stays open.
    let (to, code, message) = error_code(&send(&mut hub, 10, join_json(), now));
    assert_eq!((to, code.as_str()), (10, "rate_limited"), "{message}");
    assert!(message.contains("30 per minute") && message.contains("try again in 2 s"), "{message}");
    hub.connect_from(ConnId(11), home, now);
    assert_eq!(error_code(&send(&mut hub, 11, join_json(), now)).1, "rate_limited");
    // Another address is not held up.
    hub.connect_from(ConnId(12), away, now);
    assert_eq!(json_of(&send(&mut hub, 12, join_json(), now)).len(), 2);
    // One session's worth comes back after 2 s (30 per minute), and only one.
    let later = now + Duration::from_secs(2);
    assert_eq!(json_of(&send(&mut hub, 11, join_json(), later)).len(), 2);
    assert_eq!(error_code(&send(&mut hub, 10, join_json(), later)).1, "rate_limited");
    // A refused join costs nothing: no master for the scene, no token taken.
    let much_later = later + Duration::from_secs(60);
    hub.connect_from(ConnId(13), home, much_later);
    let unknown = json!({"type":"join","scene":"nowhere","mode":"viewer","width":64,"height":64,"fps":30});
    for _ in 0..5 {
        assert_eq!(error_code(&send(&mut hub, 13, unknown.clone(), much_later)).1, "unknown_scene");
    }
    assert_eq!(json_of(&send(&mut hub, 13, join_json(), much_later)).len(), 2);
    // Addresses whose allowance is full again are forgotten.
    hub.tick(much_later + Duration::from_secs(60));
    assert!(hub.join_allowance.is_empty());
}

#[test]
fn a_connected_session_outlives_its_clients_signaling_connection() {
    let (mut hub, now) = hub_with(None);
    add_master(&mut hub, 1, "m1", 4, now);
    let (connected, _) = add_client(&mut hub, 10, now);
    let (_connecting, _) = add_client(&mut hub, 11, now);
    assert!(send(&mut hub, 1, json!({"type":"connected","session":connected}), now).is_empty());
    // Its video is up: the master keeps the session (no `leave`), the slot stays taken.
    assert!(hub.disconnect(ConnId(10), now).is_empty());
    assert_eq!(master_sessions(&hub), vec![("m1".into(), 2)]);
    // Still connecting: the join is abandoned and the master hears `leave`.
    let out = json_of(&hub.disconnect(ConnId(11), now));
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].1["type"], "leave");
}

/// `joined` carries the deployment's STUN server and a TURN credential minted for the
/// session, never the secret; without ICE servers it has no `ice_servers` at all.
#[test]
fn joined_hands_each_client_its_own_turn_credential() {
    use nephele_protocol::ice::{IceConfig, TurnAuth, turn_rest_credentials};
    let (mut hub, now) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, now);
    hub.connect(ConnId(2), now);
    let plain = json_of(&send(&mut hub, 2, join_json(), now));
    assert!(plain[0].1.get("ice_servers").is_none(), "{plain:?}");

    let urls = ["stun:stun.example.org", "turn:turn.example.org:3478?transport=udp"].map(|u| u.parse().unwrap()).to_vec();
    let ice = IceConfig::new(urls, TurnAuth::Secret { secret: "shh-secret".into(), ttl_s: 3600 }).unwrap();
    let mut hub = Hub::new(HubConfig { ice, ..HubConfig::default() });
    add_master(&mut hub, 1, "m", 4, now);
    let mut creds = Vec::new();
    for conn in [2, 3] {
        hub.connect(ConnId(conn), now);
        let out = json_of(&send(&mut hub, conn, join_json(), now));
        let joined = &out[0].1;
        assert!(!joined.to_string().contains("shh-secret"), "{joined}");
        let servers = joined["ice_servers"].as_array().unwrap();
        assert_eq!(servers[0], json!({"urls":["stun:stun.example.org"]}));
        let (user, pass) = (servers[1]["username"].as_str().unwrap(), servers[1]["credential"].as_str().unwrap());
        let session = joined["session"].as_str().unwrap();
        let (expiry, id) = user.split_once(':').unwrap();
        assert_eq!(id, format!("nephele-{session}"));
        let expiry: u64 = expiry.parse().unwrap();
        let unix_now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs();
        assert!((unix_now + 3590..=unix_now + 3610).contains(&expiry), "{user}");
        assert_eq!(turn_rest_credentials("shh-secret", expiry, id).1, pass);
        creds.push(pass.to_owned());
    }
    assert_ne!(creds[0], creds[1]);
}

/// A draining hub refuses joins in words and counts the sessions still connecting.
#[test]
fn a_draining_hub_refuses_joins() {
    let (mut hub, now) = hub_with(None);
    add_master(&mut hub, 1, "m", 4, now);
    add_client(&mut hub, 2, now);
    assert_eq!(hub.connecting(), 1);
    hub.drain();
    hub.connect(ConnId(3), now);
    let (to, code, message) = error_code(&send(&mut hub, 3, join_json(), now));
    assert_eq!((to, code.as_str()), (3, "no_capacity"));
    assert!(message.contains("shutting down"), "{message}");
}
