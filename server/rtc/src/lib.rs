//! The WebRTC conventions both ends of a stream share: the one video format (H.264
//! constrained baseline `42e01f`, packetization mode 1, NACK/PLI/FIR feedback), how a
//! `webrtc` API object is built with it and with the process's network settings (which
//! interfaces, which UDP ports, STUN/TURN servers), how a local ICE candidate is written as
//! the `RTCIceCandidateInit` JSON that signaling relays. The master's peer and the headless
//! client both build on this crate and nothing else of each other's.
//!
//! UDP: by default each peer connection takes its own ephemeral port (`UdpPorts::Any`); a
//! range keeps them inside a firewall's opening; `UdpPorts::Mux` carries every session over
//! one socket (ICE tells sessions apart by their username fragment), so a firewall, cloud
//! security group or Kubernetes Service opens one UDP port. `webrtc` 0.17 has no ICE-TCP
//! (its gatherer leaves TCP candidates as a to-do): a client whose network allows only TCP
//! reaches the server through TURN over TCP or TLS (`turn:…?transport=tcp`, `turns:`).

use std::{
    net::{IpAddr, Ipv4Addr, SocketAddr},
    sync::Arc,
    time::Duration,
};

use anyhow::{Context, Result, bail};
pub use nephele_protocol::ice::{IceConfig, IceServer};
use serde_json::Value;
use webrtc::{
    api::{
        API, APIBuilder, interceptor_registry::register_default_interceptors, media_engine::MediaEngine,
        setting_engine::SettingEngine,
    },
    ice::{
        network_type::NetworkType,
        udp_mux::{UDPMuxDefault, UDPMuxParams},
        udp_network::{EphemeralUDP, UDPNetwork},
    },
    ice_transport::{ice_candidate::RTCIceCandidateInit, ice_server::RTCIceServer},
    interceptor::registry::Registry,
    peer_connection::{RTCPeerConnection, configuration::RTCConfiguration, policy::ice_transport_policy::RTCIceTransportPolicy},
    rtp_transceiver::{
        RTCPFeedback,
        rtp_codec::{RTCRtpCodecCapability, RTCRtpCodecParameters, RTPCodecType},
    },
};

/// The only video format we send (and the only one the test client accepts).
pub const H264_FMTP: &str = "level-asymmetry-allowed=1;packetization-mode=1;profile-level-id=42e01f";

/// Network settings for every peer connection of a process.
#[derive(Debug, Clone, Default)]
pub struct RtcConfig {
    /// Gather loopback candidates only (tests, a browser on the same machine).
    pub loopback_only: bool,
    /// Public addresses to advertise instead of the host's (server behind 1:1 NAT).
    pub public_ips: Vec<String>,
    /// Which UDP ports the peer connections use.
    pub udp: UdpPorts,
    /// STUN/TURN servers this process's own peer connections gather through.
    pub ice: IceConfig,
}

impl RtcConfig {
    /// Loopback candidates only, ephemeral ports, no ICE servers (tests, benches).
    pub fn loopback() -> Self {
        Self { loopback_only: true, ..Self::default() }
    }
}

/// The UDP ports of a process's peer connections.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum UdpPorts {
    /// An ephemeral port per connection, anywhere.
    #[default]
    Any,
    /// An ephemeral port per connection within `min..=max`.
    Range { min: u16, max: u16 },
    /// Every connection over one socket on this port (0: one the system picks).
    Mux(u16),
}

impl std::str::FromStr for UdpPorts {
    type Err = String;

    /// `N` (one muxed port) or `MIN-MAX` (a range).
    fn from_str(text: &str) -> Result<Self, String> {
        let port = |p: &str| p.trim().parse::<u16>().ok().filter(|&p| p > 0).ok_or_else(|| format!("{p:?} is not a UDP port (1..=65535)"));
        match text.split_once('-') {
            Some((a, b)) => {
                let (min, max) = (port(a)?, port(b)?);
                if min > max {
                    return Err(format!("the UDP port range {text} runs backwards"));
                }
                Ok(Self::Range { min, max })
            }
            None => Ok(Self::Mux(port(text)?)),
        }
    }
}

/// The process's `webrtc` API with its ICE servers.
pub struct RtcApi {
    pub api: API,
    ice: IceConfig,
    /// The one UDP port of [`UdpPorts::Mux`], as bound.
    pub udp_port: Option<u16>,
    /// The public IPv4 address host candidates of the muxed port are advertised with.
    advertise_ip: Option<String>,
}

impl RtcApi {
    /// A local candidate line (`candidate:… udp PRIO ADDRESS PORT typ host …`) as peers
    /// should see it: a host candidate of the muxed port carries the public address (see
    /// `--public-ip`); `None` for a copy of one already advertised (`seen` keeps them).
    pub fn advertised(&self, candidate: &str, seen: &mut std::collections::HashSet<String>) -> Option<String> {
        let Some(public) = &self.advertise_ip else { return Some(candidate.to_owned()) };
        let mut fields: Vec<&str> = candidate.split(' ').collect();
        if fields.len() < 8 || fields[6] != "typ" || fields[7] != "host" {
            return Some(candidate.to_owned());
        }
        fields[4] = public;
        let line = fields.join(" ");
        // Foundation and priority differ between the copies; address and port do not.
        seen.insert(format!("{}:{}", fields[4], fields[5])).then_some(line)
    }

    /// [`RtcApi::advertised`] applied to every `a=candidate:` line of an SDP.
    pub fn advertised_sdp(&self, sdp: &str, seen: &mut std::collections::HashSet<String>) -> String {
        if self.advertise_ip.is_none() {
            return sdp.to_owned();
        }
        let mut out = String::with_capacity(sdp.len());
        for line in sdp.split_inclusive("\r\n") {
            match line.strip_prefix("a=") {
                Some(c) if c.starts_with("candidate:") => {
                    if let Some(c) = self.advertised(c.trim_end(), seen) {
                        out.push_str("a=");
                        out.push_str(&c);
                        out.push_str("\r\n");
                    }
                }
                _ => out.push_str(line),
            }
        }
        out
    }

    /// What a master gathers with: the STUN servers only. TURN is for clients that cannot
    /// reach the master's UDP port; the master reaches their relays from its own address
    /// (a relay of its own would hold an allocation per session and send the media through
    /// TURN twice).
    pub fn master_ice_servers(&self) -> Vec<IceServer> {
        let mut servers = self.ice.servers_now("master");
        servers.retain(|s| s.urls.iter().all(|u| !u.starts_with("turn:") && !u.starts_with("turns:")));
        servers
    }

    /// A peer connection gathering through `servers`; `relay_only`: TURN relay candidates
    /// only (`iceTransportPolicy: "relay"`).
    pub async fn peer_connection(&self, servers: &[IceServer], relay_only: bool) -> Result<RTCPeerConnection> {
        let config = RTCConfiguration {
            ice_servers: servers
                .iter()
                .map(|s| RTCIceServer { urls: s.urls.clone(), username: s.username.clone().unwrap_or_default(), credential: s.credential.clone().unwrap_or_default() })
                .collect(),
            ice_transport_policy: if relay_only { RTCIceTransportPolicy::Relay } else { RTCIceTransportPolicy::All },
            ..Default::default()
        };
        self.api.new_peer_connection(config).await.context("creating a peer connection")
    }
}

/// Silence before a peer connection is `disconnected`…
pub const ICE_DISCONNECTED_AFTER: Duration = Duration::from_secs(4);
/// …and then before it is `failed` (its session ends).
pub const ICE_FAILED_AFTER: Duration = Duration::from_secs(6);

/// Builds the `webrtc` API object shared by all peers of a process (binds the one UDP
/// port of [`UdpPorts::Mux`]: call inside a tokio runtime).
pub fn build_api(cfg: &RtcConfig) -> Result<Arc<RtcApi>> {
    build_api_with(cfg, &|_| {})
}

/// [`build_api`], with `tweak` having the last word on the network settings (the test
/// client: which interfaces, an impaired socket).
pub fn build_api_with(cfg: &RtcConfig, tweak: &dyn Fn(&mut SettingEngine)) -> Result<Arc<RtcApi>> {
    let mut media = MediaEngine::default();
    media.register_codec(h264_codec(), RTPCodecType::Video).context("registering H.264")?;
    let mut registry = Registry::new();
    // After register_codec: the interceptors add feedback only to codecs already registered.
    registry = register_default_interceptors(registry, &mut media).context("registering interceptors")?;
    let mut settings = SettingEngine::default();
    settings.set_include_loopback_candidate(true);
    // A peer that vanished without closing (a killed tab or process) is given up after
    // ~10 s of silence (4 s to disconnected, 6 s more to failed) instead of webrtc's 30 s,
    // so its session and slot are freed; a 2 s network blackout stays well inside it.
    settings.set_ice_timeouts(Some(ICE_DISCONNECTED_AFTER), Some(ICE_FAILED_AFTER), Some(Duration::from_secs(1)));
    if cfg.loopback_only {
        settings.set_ip_filter(Box::new(|ip: IpAddr| ip.is_loopback()));
    }
    // Behind 1:1 NAT. On one muxed port the host candidates are advertised with the public
    // address by [`RtcApi::advertised`] instead of webrtc's 1:1 mapping: that maps every
    // local address (loopback, a container bridge, …) to the same public one, and the
    // duplicates it makes close the one socket they share (pion/ice#505, also in
    // webrtc-ice 0.17), so no session could connect.
    let muxed = matches!(cfg.udp, UdpPorts::Mux(_));
    if !cfg.public_ips.is_empty() && !muxed {
        settings.set_nat_1to1_ips(cfg.public_ips.clone(), webrtc::ice_transport::ice_candidate_type::RTCIceCandidateType::Host);
    }
    let advertise_ip = if muxed { cfg.public_ips.iter().find(|ip| ip.parse::<Ipv4Addr>().is_ok()).cloned() } else { None };
    if muxed && !cfg.public_ips.is_empty() && advertise_ip.is_none() {
        anyhow::bail!("--public-ip {}: one UDP port (--rtc-port N) is IPv4 only; give the public IPv4 address", cfg.public_ips.join(","));
    }
    let mut udp_port = None;
    match cfg.udp {
        UdpPorts::Any => {}
        UdpPorts::Range { min, max } => {
            let range = EphemeralUDP::new(min, max).map_err(|e| anyhow::anyhow!("UDP ports {min}-{max}: {e}"))?;
            settings.set_udp_network(UDPNetwork::Ephemeral(range));
        }
        UdpPorts::Mux(port) => {
            let ip = if cfg.loopback_only { IpAddr::V4(Ipv4Addr::LOCALHOST) } else { IpAddr::V4(Ipv4Addr::UNSPECIFIED) };
            let socket = bind_udp(SocketAddr::new(ip, port))?;
            udp_port = Some(socket.local_addr()?.port());
            settings.set_udp_network(UDPNetwork::Muxed(UDPMuxDefault::new(UDPMuxParams::new(socket))));
            // The socket is IPv4: candidates on IPv6 addresses would name a port nobody
            // listens on (and a client that prefers them would wait for checks that fail).
            settings.set_network_types(vec![NetworkType::Udp4]);
        }
    }
    tweak(&mut settings);
    let api = APIBuilder::new().with_media_engine(media).with_interceptor_registry(registry).with_setting_engine(settings).build();
    Ok(Arc::new(RtcApi { api, ice: cfg.ice.clone(), udp_port, advertise_ip }))
}

/// The one UDP socket of every session, with the error a person can act on.
fn bind_udp(addr: SocketAddr) -> Result<tokio::net::UdpSocket> {
    let socket = match std::net::UdpSocket::bind(addr) {
        Ok(s) => s,
        Err(e) if e.kind() == std::io::ErrorKind::AddrInUse => {
            bail!("UDP port {} is in use by another process (choose another --rtc-port, or stop that process)", addr.port())
        }
        Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => bail!("no permission to bind UDP port {} ({e})", addr.port()),
        Err(e) => return Err(e).with_context(|| format!("binding UDP {addr}")),
    };
    socket.set_nonblocking(true)?;
    tokio::net::UdpSocket::from_std(socket).context("the UDP socket needs a tokio runtime")
}

/// A local candidate as the `RTCIceCandidateInit` JSON a browser accepts. Bundled: every
/// candidate belongs to m-line 0; the crate's mid ("") matches no m-line in a browser, so
/// the mid is left out.
pub fn candidate_json(init: &RTCIceCandidateInit) -> Value {
    serde_json::json!({
        "candidate": init.candidate,
        "sdpMid": null,
        "sdpMLineIndex": init.sdp_mline_index.unwrap_or(0),
    })
}

/// The RTP clock of H.264 (RFC 6184).
pub const H264_CLOCK_HZ: u32 = 90_000;

/// H.264 constrained baseline 3.1, packetization mode 1, NACK/PLI/FIR.
pub fn h264_codec() -> RTCRtpCodecParameters {
    let fb = |typ: &str, parameter: &str| RTCPFeedback { typ: typ.into(), parameter: parameter.into() };
    RTCRtpCodecParameters {
        capability: RTCRtpCodecCapability {
            mime_type: webrtc::api::media_engine::MIME_TYPE_H264.into(),
            clock_rate: H264_CLOCK_HZ,
            channels: 0,
            sdp_fmtp_line: H264_FMTP.into(),
            rtcp_feedback: vec![fb("nack", ""), fb("nack", "pli"), fb("ccm", "fir")],
        },
        payload_type: 102,
        ..Default::default()
    }
}


#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn udp_ports_parse_as_one_port_or_a_range() {
        assert_eq!("3478".parse::<UdpPorts>(), Ok(UdpPorts::Mux(3478)));
        assert_eq!("40000-40100".parse::<UdpPorts>(), Ok(UdpPorts::Range { min: 40000, max: 40100 }));
        for bad in ["0", "70000", "x", "5-4", "-5", "1-"] {
            assert!(bad.parse::<UdpPorts>().is_err(), "{bad}");
        }
    }

    #[tokio::test]
    async fn a_port_in_use_is_refused_in_words() {
        let taken = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        let port = taken.local_addr().unwrap().port();
        let err = build_api(&RtcConfig { udp: UdpPorts::Mux(port), ..RtcConfig::loopback() }).err().expect("the port is taken");
        assert!(format!("{err:#}").contains(&format!("UDP port {port} is in use")), "{err:#}");
        let api = build_api(&RtcConfig { udp: UdpPorts::Mux(0), ..RtcConfig::loopback() }).unwrap();
        assert!(api.udp_port.is_some_and(|p| p > 0));
    }

    #[tokio::test]
    async fn on_one_port_host_candidates_carry_the_public_address_once() {
        let cfg = RtcConfig { udp: UdpPorts::Mux(0), public_ips: vec!["198.51.100.4".into()], ..RtcConfig::default() };
        let api = build_api(&cfg).unwrap();
        let mut seen = std::collections::HashSet::new();
        let lo = "candidate:1 1 udp 2130706431 127.0.0.1 3479 typ host";
        let eth = "candidate:2 1 udp 2130706175 10.0.0.5 3479 typ host";
        assert_eq!(api.advertised(lo, &mut seen).as_deref(), Some("candidate:1 1 udp 2130706431 198.51.100.4 3479 typ host"));
        assert_eq!(api.advertised(eth, &mut seen), None, "a second host candidate on the same port is a duplicate");
        let relay = "candidate:3 1 udp 16777215 203.0.113.9 49160 typ relay raddr 0.0.0.0 rport 0";
        assert_eq!(api.advertised(relay, &mut seen).as_deref(), Some(relay), "only host candidates are rewritten");
        let sdp = format!("v=0\r\na=candidate:{}\r\na=candidate:{}\r\na=end-of-candidates\r\n", &lo["candidate:".len()..], &eth["candidate:".len()..]);
        let out = api.advertised_sdp(&sdp, &mut std::collections::HashSet::new());
        assert_eq!(out, "v=0\r\na=candidate:1 1 udp 2130706431 198.51.100.4 3479 typ host\r\na=end-of-candidates\r\n");
        // The one port is IPv4: an IPv6 public address alone is refused in words.
        let err = build_api(&RtcConfig { udp: UdpPorts::Mux(0), public_ips: vec!["2001:db8::4".into()], ..RtcConfig::default() }).err().expect("refused");
        assert!(format!("{err:#}").contains("IPv4 only"), "{err:#}");
        // Without a muxed port (webrtc's own mapping applies), nothing is rewritten.
        let api = build_api(&RtcConfig { public_ips: vec!["198.51.100.4".into()], ..RtcConfig::default() }).unwrap();
        assert_eq!(api.advertised(eth, &mut std::collections::HashSet::new()).as_deref(), Some(eth));
    }
}
