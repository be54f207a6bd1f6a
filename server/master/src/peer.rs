//! WebRTC behind a small interface of our own ([`MasterPeer`]), implemented with the
//! `webrtc` crate 0.17.2 (tokio-based). Only this module names `webrtc` types on the master
//! side, so moving to another stack (str0m, webrtc 0.2x) stays local.
//!
//! The master answers: the client's offer brings a recvonly video m-line and the unordered
//! `pose` data channel. We register exactly one codec, H.264 constrained baseline
//! `42e01f` in packetization mode 1 with NACK/PLI/FIR feedback, then the default
//! interceptors (NACK responder, RTCP reports). Picture-loss reports arrive through the
//! sender's RTCP reader and become [`PeerEvent::PictureLoss`].

use std::{sync::Arc, time::Duration};

use anyhow::{Context, Result};
use bytes::Bytes;
use serde_json::Value;
use tokio::sync::{Mutex, mpsc};
use webrtc::{
    data_channel::{RTCDataChannel, data_channel_message::DataChannelMessage},
    ice_transport::ice_candidate::RTCIceCandidateInit,
    media::Sample,
    peer_connection::{
        RTCPeerConnection, peer_connection_state::RTCPeerConnectionState,
        sdp::session_description::RTCSessionDescription,
    },
    rtcp::payload_feedbacks::{full_intra_request::FullIntraRequest, picture_loss_indication::PictureLossIndication},
    track::track_local::{TrackLocal, track_local_static_sample::TrackLocalStaticSample},
};

use nephele_rtc::{RtcApi, candidate_json, h264_codec};

/// Largest pose-channel message we look at; anything longer is refused unread.
pub const MAX_CHANNEL_MESSAGE: usize = nephele_limits::MAX_POSE_MESSAGE_BYTES;

/// Something that happened on a peer connection, delivered in order on one channel.
#[derive(Debug, Clone, PartialEq)]
pub enum PeerEvent {
    /// A local ICE candidate to send through signaling (`RTCIceCandidateInit` JSON).
    LocalIce(Value),
    /// The pose channel opened.
    ChannelOpen,
    /// A binary message on the pose channel.
    Binary(Bytes),
    /// A text message on the pose channel.
    Text(String),
    /// A message longer than [`MAX_CHANNEL_MESSAGE`] was dropped unread.
    Oversized(usize),
    /// RTCP PLI or FIR from the receiver.
    PictureLoss,
    /// ICE+DTLS connected.
    Connected,
    /// The connection failed or closed; the session should end.
    Closed(String),
}

/// The master's side of one client connection.
pub trait MasterPeer: Send + Sync + 'static {
    /// Applies the client's offer and returns our answer SDP.
    fn answer(&self, offer_sdp: &str) -> impl Future<Output = Result<String>> + Send;
    /// Adds one trickled candidate from the client (`RTCIceCandidateInit` JSON).
    fn add_remote_ice(&self, candidate: &Value) -> impl Future<Output = Result<()>> + Send;
    /// Sends one H.264 access unit (Annex-B) that lasts `duration`.
    fn send_video(&self, access_unit: Bytes, duration: Duration) -> impl Future<Output = Result<()>> + Send;
    /// Sends a text message on the pose channel (dropped if the channel is not open).
    fn send_text(&self, text: String) -> impl Future<Output = Result<()>> + Send;
    /// Sends a binary message on the pose channel (a frame's depth; dropped if the channel is
    /// not open).
    fn send_binary(&self, bytes: Bytes) -> impl Future<Output = Result<()>> + Send;
    fn close(&self) -> impl Future<Output = ()> + Send;
}

/// [`MasterPeer`] on the `webrtc` crate.
pub struct WebrtcPeer {
    pc: Arc<RTCPeerConnection>,
    rtc: Arc<RtcApi>,
    advertised: Arc<std::sync::Mutex<std::collections::HashSet<String>>>,
    track: Arc<TrackLocalStaticSample>,
    channel: Arc<Mutex<Option<Arc<RTCDataChannel>>>>,
}

impl WebrtcPeer {
    /// A new peer connection with its H.264 track, gathering through the process's STUN
    /// servers ([`RtcApi::master_ice_servers`]); events go to `events`.
    pub async fn new(rtc: &Arc<RtcApi>, events: mpsc::Sender<PeerEvent>) -> Result<Self> {
        let pc = Arc::new(rtc.peer_connection(&rtc.master_ice_servers(), false).await?);
        // Candidates as peers should see them (the public address on a muxed port), once.
        let advertised: Arc<std::sync::Mutex<std::collections::HashSet<String>>> = Arc::default();
        let track = Arc::new(TrackLocalStaticSample::new(h264_codec().capability, "video".into(), "nephele".into()));
        let sender = pc.add_track(Arc::clone(&track) as Arc<dyn TrackLocal + Send + Sync>).await.context("adding the video track")?;

        // RTCP from the receiver: PLI/FIR ask for an IDR. The loop also drives the
        // interceptors (NACK responder), so it must run for the connection's life.
        let tx = events.clone();
        tokio::spawn(async move {
            while let Ok((packets, _)) = sender.read_rtcp().await {
                let loss = packets.iter().any(|p| {
                    let any = p.as_any();
                    any.downcast_ref::<PictureLossIndication>().is_some() || any.downcast_ref::<FullIntraRequest>().is_some()
                });
                if loss && tx.try_send(PeerEvent::PictureLoss).is_err() {
                    tracing::debug!("event queue full; PLI dropped");
                }
            }
        });

        let tx = events.clone();
        let (rtc_c, seen_c) = (Arc::clone(rtc), Arc::clone(&advertised));
        pc.on_ice_candidate(Box::new(move |candidate| {
            let (tx, rtc, seen) = (tx.clone(), Arc::clone(&rtc_c), Arc::clone(&seen_c));
            Box::pin(async move {
                let Some(c) = candidate else { return };
                match c.to_json() {
                    Ok(mut init) => {
                        let line = rtc.advertised(&init.candidate, &mut seen.lock().unwrap_or_else(|e| e.into_inner()));
                        let Some(line) = line else { return };
                        init.candidate = line;
                        let _ = tx.send(PeerEvent::LocalIce(candidate_json(&init))).await;
                    }
                    Err(e) => tracing::warn!("cannot serialise a local candidate: {e}"),
                }
            })
        }));

        let tx = events.clone();
        pc.on_peer_connection_state_change(Box::new(move |state| {
            let tx = tx.clone();
            Box::pin(async move {
                let event = match state {
                    RTCPeerConnectionState::Connected => Some(PeerEvent::Connected),
                    RTCPeerConnectionState::Failed => Some(PeerEvent::Closed("peer connection failed".into())),
                    RTCPeerConnectionState::Closed => Some(PeerEvent::Closed("peer connection closed".into())),
                    _ => None,
                };
                if let Some(e) = event {
                    let _ = tx.send(e).await;
                }
            })
        }));

        let channel = Arc::new(Mutex::new(None));
        let slot = Arc::clone(&channel);
        pc.on_data_channel(Box::new(move |dc: Arc<RTCDataChannel>| {
            let (tx, slot) = (events.clone(), Arc::clone(&slot));
            Box::pin(async move {
                if dc.label() != "pose" {
                    tracing::debug!(label = dc.label(), "ignoring an unknown data channel");
                    return;
                }
                let open_tx = tx.clone();
                dc.on_open(Box::new(move || {
                    Box::pin(async move {
                        let _ = open_tx.send(PeerEvent::ChannelOpen).await;
                    })
                }));
                // Without its pose channel a session is dead weight: end it (and free its
                // slot) instead of streaming a frozen camera. webrtc-rs takes an empty
                // message as the end of the stream and closes the channel.
                let close_tx = tx.clone();
                dc.on_close(Box::new(move || {
                    let tx = close_tx.clone();
                    Box::pin(async move {
                        let why = "the pose channel closed (an empty or final message ends it)".to_string();
                        let _ = tx.send(PeerEvent::Closed(why)).await;
                    })
                }));
                dc.on_message(Box::new(move |msg: DataChannelMessage| {
                    let event = if msg.data.len() > MAX_CHANNEL_MESSAGE {
                        PeerEvent::Oversized(msg.data.len())
                    } else if msg.is_string {
                        PeerEvent::Text(String::from_utf8_lossy(&msg.data).into_owned())
                    } else {
                        PeerEvent::Binary(msg.data)
                    };
                    // Poses arrive every 20 ms; if the session cannot keep up, dropping is
                    // what an unreliable channel means anyway.
                    let _ = tx.try_send(event);
                    Box::pin(async {})
                }));
                *slot.lock().await = Some(dc);
            })
        }));
        Ok(Self { pc, rtc: Arc::clone(rtc), advertised, track, channel })
    }
}

impl MasterPeer for WebrtcPeer {
    async fn answer(&self, offer_sdp: &str) -> Result<String> {
        let offer = RTCSessionDescription::offer(offer_sdp.to_owned()).context("the offer is not valid SDP")?;
        self.pc.set_remote_description(offer).await.context("cannot apply the offer")?;
        let answer = self.pc.create_answer(None).await.context("cannot create an answer")?;
        self.pc.set_local_description(answer).await.context("cannot apply our answer")?;
        let local = self.pc.local_description().await.context("no local description after set_local_description")?;
        Ok(self.rtc.advertised_sdp(&local.sdp, &mut self.advertised.lock().unwrap_or_else(|e| e.into_inner())))
    }

    async fn add_remote_ice(&self, candidate: &Value) -> Result<()> {
        let init: RTCIceCandidateInit = serde_json::from_value(candidate.clone()).context("the ICE candidate is not an RTCIceCandidateInit")?;
        if init.candidate.is_empty() {
            return Ok(()); // end-of-candidates
        }
        self.pc.add_ice_candidate(init).await.context("cannot add the ICE candidate")
    }

    async fn send_video(&self, access_unit: Bytes, duration: Duration) -> Result<()> {
        let sample = Sample { data: access_unit, duration, ..Default::default() };
        self.track.write_sample(&sample).await.context("writing an H.264 sample")
    }

    async fn send_text(&self, text: String) -> Result<()> {
        let dc = self.channel.lock().await.clone();
        if let Some(dc) = dc {
            dc.send_text(text).await.context("sending on the pose channel")?;
        }
        Ok(())
    }

    async fn send_binary(&self, bytes: Bytes) -> Result<()> {
        let dc = self.channel.lock().await.clone();
        if let Some(dc) = dc {
            dc.send(&bytes).await.context("sending on the pose channel")?;
        }
        Ok(())
    }

    async fn close(&self) {
        if let Err(e) = self.pc.close().await {
            tracing::debug!("closing a peer connection: {e}");
        }
    }
}
