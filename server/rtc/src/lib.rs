//! The WebRTC conventions both ends of a stream share: the one video format (H.264
//! constrained baseline `42e01f`, packetization mode 1, NACK/PLI/FIR feedback), how a
//! `webrtc` API object is built with it, how a local ICE candidate is written as the
//! `RTCIceCandidateInit` JSON that signaling relays. The master's peer and the headless client
//! both build on this crate and nothing else of each other's.

use std::{net::IpAddr, sync::Arc, time::Duration};

use anyhow::{Context, Result};
use serde_json::Value;
use webrtc::{
    api::{
        API, APIBuilder, interceptor_registry::register_default_interceptors, media_engine::MediaEngine,
        setting_engine::SettingEngine,
    },
    ice_transport::ice_candidate::RTCIceCandidateInit,
    interceptor::registry::Registry,
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
}

/// Silence before a peer connection is `disconnected`…
pub const ICE_DISCONNECTED_AFTER: Duration = Duration::from_secs(4);
/// …and then before it is `failed` (its session ends).
pub const ICE_FAILED_AFTER: Duration = Duration::from_secs(6);

/// Builds the `webrtc` API object shared by all peers of a process.
pub fn build_api(cfg: &RtcConfig) -> Result<Arc<API>> {
    build_api_with(cfg, &|_| {})
}

/// [`build_api`], with `tweak` having the last word on the network settings (the test
/// client: which interfaces, an impaired socket).
pub fn build_api_with(cfg: &RtcConfig, tweak: &dyn Fn(&mut SettingEngine)) -> Result<Arc<API>> {
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
    if !cfg.public_ips.is_empty() {
        settings.set_nat_1to1_ips(cfg.public_ips.clone(), webrtc::ice_transport::ice_candidate_type::RTCIceCandidateType::Host);
    }
    tweak(&mut settings);
    Ok(Arc::new(
        APIBuilder::new().with_media_engine(media).with_interceptor_registry(registry).with_setting_engine(settings).build(),
    ))
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

/// H.264 constrained baseline 3.1, packetization mode 1, NACK/PLI/FIR.
/// The RTP clock of H.264 (RFC 6184).
pub const H264_CLOCK_HZ: u32 = 90_000;

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

