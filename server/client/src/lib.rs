//! A real streaming client in Rust: joins through signaling, offers a recvonly H.264 video
//! m-line and the unordered `pose` channel (like the browser page), reassembles RTP into
//! access units in sequence order (waiting briefly for NACK retransmissions; after a loss
//! it drops P frames and sends a PLI until an IDR comes: [`reassembly`]), and decodes them
//! with OpenH264 on its own thread.
//! Used by `nephele replay`, `nephele bench stream|users` and the end-to-end tests. It
//! shares only the wire protocol (`nephele-wire`, `nephele-rtc`) with the master.

use std::{
    sync::{
        Arc,
        atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering},
    },
    time::{Duration, Instant},
};

use anyhow::{Context, Result, anyhow, bail};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use nephele_protocol::{JoinSpec, Mode, ToClient, ToSignal};
use openh264::{decoder::Decoder, formats::YUVSource};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message;
use webrtc::{
    data_channel::{RTCDataChannel, data_channel_init::RTCDataChannelInit, data_channel_message::DataChannelMessage},
    api::setting_engine::SettingEngine,
    ice_transport::ice_candidate::RTCIceCandidateInit,
    peer_connection::{RTCPeerConnection, sdp::session_description::RTCSessionDescription},
    rtcp::payload_feedbacks::picture_loss_indication::PictureLossIndication,
    rtp_transceiver::{
        RTCRtpTransceiverInit, rtp_codec::RTPCodecType, rtp_transceiver_direction::RTCRtpTransceiverDirection,
    },
};

use nephele_rtc::{RtcConfig, build_api_with, candidate_json};
use nephele_wire::{
    PoseMessage, ToViewer,
    depth::{DepthError, DepthFrame},
    sei::parse_pose_seq,
};

pub mod delay;
pub mod glass;
pub mod reassembly;
pub mod replay;

pub use reassembly::ReceiveCounts;
use reassembly::{ReceiveStats, Reassembler, Unit};

/// How the client's peer meets the network. [`Default`] (what [`StreamClient::connect`]
/// uses): loopback candidates only, sockets of the `webrtc` crate's own.
#[derive(Clone, Default)]
pub struct ClientNet {
    /// Gather candidates on every interface, not only loopback (a server on another host
    /// or in another network namespace).
    pub any_interface: bool,
    /// Applied last to the peer's network settings (tests: which addresses, one impaired
    /// socket through `SettingEngine::set_udp_network`).
    #[allow(clippy::type_complexity)]
    pub settings: Option<Arc<dyn Fn(&mut SettingEngine) + Send + Sync>>,
    /// The signaling websocket's source address (tests and `bench abuse`: clients from
    /// different loopback addresses, 127.0.0.0/8); `None`: the system's choice.
    pub source_ip: Option<std::net::IpAddr>,
    /// Gather TURN relay candidates only (a browser's `iceTransportPolicy: "relay"`), using
    /// the ICE servers signaling hands out in `joined`.
    pub relay_only: bool,
}

/// One end of an ICE candidate pair: its type (`host`, `srflx`, `prflx`, `relay`) and
/// address.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PairEnd {
    pub kind: String,
    pub ip: String,
    pub port: u16,
}

/// What to ask signaling for.
#[derive(Debug, Clone)]
pub struct ClientOptions {
    /// e.g. ws://127.0.0.1:8080/signal
    pub signal_url: String,
    pub scene: String,
    pub mode: Mode,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub token: Option<String>,
    /// How much of each picture to take in.
    pub receive: Receive,
    /// Mode `quilt`: the layout to ask for (`None`: the master's default, 5×9 over 40°).
    pub quilt: Option<nephele_protocol::QuiltSpec>,
    /// Ask for each frame's depth ([`StreamClient::depth`]), for reprojection.
    pub depth: bool,
}

/// How far the client takes each access unit it reassembles.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Receive {
    /// Decode and keep the RGBA pixels (PSNR, saved frames).
    Pixels,
    /// Decode, drop the pixels: what a viewer pays, without this client's copy.
    Decode,
    /// Count complete access units and read their SEI, no decode: a load generator whose
    /// own decoding would take the cores from the server it measures (benches with many
    /// clients on one machine). Its frames have `decoded_at == arrived_at`.
    AccessUnits,
}

/// One received video frame (decoded unless [`Receive::AccessUnits`]).
#[derive(Debug, Clone)]
pub struct ReceivedFrame {
    /// Pose sequence from the access unit's SEI, if it had one.
    pub pose_seq: Option<u64>,
    /// When the last RTP packet of the access unit arrived.
    pub arrived_at: Instant,
    /// When decoding finished (with [`Receive::AccessUnits`]: when it arrived).
    pub decoded_at: Instant,
    pub bytes: usize,
    pub width: u32,
    pub height: u32,
    /// RGBA8, `width`×`height` (empty unless [`Receive::Pixels`]).
    pub rgba: Vec<u8>,
    /// The access unit was an IDR.
    pub idr: bool,
}

/// A connected client; receive from `frames` and `messages`.
pub struct StreamClient {
    pc: Arc<RTCPeerConnection>,
    channel: Arc<RTCDataChannel>,
    pub frames: mpsc::UnboundedReceiver<ReceivedFrame>,
    pub messages: mpsc::UnboundedReceiver<ToViewer>,
    /// Each frame's depth, when [`ClientOptions::depth`] asked for it; a message that does
    /// not parse comes as its error (the frame is then shown unwarped).
    pub depth: mpsc::UnboundedReceiver<Result<DepthFrame, DepthError>>,
    /// The `session` message the master sent when the channel opened.
    pub session: ToViewer,
    /// Signaling messages after the connection was set up (`ended`, errors).
    pub signaling: mpsc::UnboundedReceiver<ToClient>,
    ws_out: mpsc::UnboundedSender<ToSignal>,
    video_ssrc: Arc<AtomicU32>,
    stats: Arc<ReceiveStats>,
    /// When [`StreamClient::send_pose_paced`] last sent, and how many it held back.
    last_paced: std::sync::Mutex<Option<Instant>>,
    poses_held_back: AtomicU64,
    /// [`StreamClient::close`] ran (so dropping has nothing left to close).
    closed: AtomicBool,
}

/// Unacknowledged pose-channel bytes up to which [`StreamClient::send_pose_paced`] sends
/// every pose (three poses).
pub const POSE_BACKLOG_FREE: usize = 312;
/// The `webrtc` crate's SCTP congestion window after a retransmission timeout (one MTU of
/// 1228 bytes): DATA beyond it waits for the next timeout, which backs off from 1 s.
pub const SCTP_WINDOW_AFTER_TIMEOUT: usize = 1228;
/// Above [`POSE_BACKLOG_FREE`], [`StreamClient::send_pose_paced`] sends one pose this often.
pub const POSE_PROBE_EVERY: Duration = Duration::from_millis(300);

impl StreamClient {
    /// Joins, negotiates and waits (up to 30 s) for the pose channel and the session message.
    pub async fn connect(opts: &ClientOptions) -> Result<Self> {
        Self::connect_with(opts, &ClientNet::default()).await
    }

    /// [`StreamClient::connect`] through the network `net`.
    pub async fn connect_with(opts: &ClientOptions, net: &ClientNet) -> Result<Self> {
        tokio::time::timeout(Duration::from_secs(30), Self::connect_inner(opts, net)).await.context("timed out connecting (30 s)")?
    }

    async fn connect_inner(opts: &ClientOptions, net: &ClientNet) -> Result<Self> {
        let (ws, _) = match net.source_ip {
            None => tokio_tungstenite::connect_async(&opts.signal_url).await,
            Some(ip) => tokio_tungstenite::client_async(&opts.signal_url, tokio_tungstenite::MaybeTlsStream::Plain(connect_from(ip, &opts.signal_url).await?)).await,
        }
        .with_context(|| format!("connecting to {}", opts.signal_url))?;
        let (mut ws_tx, mut ws_rx) = ws.split();
        let spec = JoinSpec { scene: opts.scene.clone(), mode: opts.mode, width: opts.width, height: opts.height, fps: opts.fps, quilt: opts.quilt, depth: opts.depth };
        let join = ToSignal::Join { spec, token: opts.token.clone() };
        ws_tx.send(Message::text(serde_json::to_string(&join)?)).await?;
        let ice_servers = match next_signal(&mut ws_rx).await? {
            ToClient::Joined { ice_servers, .. } => ice_servers,
            ToClient::Error { code, message } => bail!("signaling refused the join ({code:?}): {message}"),
            other => bail!("unexpected signaling message before joined: {other:?}"),
        };

        if net.relay_only && !ice_servers.iter().flat_map(|s| &s.urls).any(|u| u.starts_with("turn:") || u.starts_with("turns:")) {
            bail!("relay only needs a TURN server, and signaling offered none (the server has no turn: --ice-server)");
        }
        let tweak = |s: &mut SettingEngine| {
            if let Some(f) = &net.settings {
                f(s);
            }
        };
        let api = build_api_with(&RtcConfig { loopback_only: !net.any_interface, ..RtcConfig::default() }, &tweak)?;
        let pc = Arc::new(api.peer_connection(&ice_servers, net.relay_only).await?);
        pc.add_transceiver_from_kind(
            RTPCodecType::Video,
            Some(RTCRtpTransceiverInit { direction: RTCRtpTransceiverDirection::Recvonly, send_encodings: vec![] }),
        )
        .await?;
        let init = RTCDataChannelInit { ordered: Some(false), max_retransmits: Some(0), ..Default::default() };
        let channel = pc.create_data_channel("pose", Some(init)).await?;

        let (ws_out, mut ws_out_rx) = mpsc::unbounded_channel::<ToSignal>();
        let ice_tx = ws_out.clone();
        // How many candidates gathering found, reported when it completes: none at all
        // (relay only, and TURN unreachable or refusing the credentials) cannot connect.
        let (gathered_tx, mut gathered) = mpsc::unbounded_channel::<usize>();
        let found = Arc::new(AtomicU64::new(0));
        pc.on_ice_candidate(Box::new(move |c| {
            let (tx, gathered_tx, found) = (ice_tx.clone(), gathered_tx.clone(), Arc::clone(&found));
            Box::pin(async move {
                match c.map(|c| c.to_json()) {
                    Some(Ok(init)) => {
                        found.fetch_add(1, Ordering::Relaxed);
                        let _ = tx.send(ToSignal::Ice { session: None, candidate: candidate_json(&init) });
                    }
                    Some(Err(_)) => {}
                    None => {
                        let _ = gathered_tx.send(found.load(Ordering::Relaxed) as usize);
                    }
                }
            })
        }));

        let (frame_tx, frames) = mpsc::unbounded_channel();
        let receive = opts.receive;
        let (w, h) = (opts.width, opts.height);
        let video_ssrc = Arc::new(AtomicU32::new(0));
        let ssrc_slot = Arc::clone(&video_ssrc);
        let stats = Arc::new(ReceiveStats::default());
        let (pli_tx, pli_rx) = mpsc::unbounded_channel::<()>();
        tokio::spawn(send_plis(Arc::downgrade(&pc), Arc::clone(&video_ssrc), Arc::clone(&stats), pli_rx));
        let track_stats = Arc::clone(&stats);
        pc.on_track(Box::new(move |track, _, _| {
            let (frame_tx, pli_tx, stats) = (frame_tx.clone(), pli_tx.clone(), Arc::clone(&track_stats));
            ssrc_slot.store(track.ssrc(), Ordering::Relaxed);
            Box::pin(async move {
                let (au_tx, au_rx) = std::sync::mpsc::channel::<Unit>();
                let (fail_tx, fail_rx) = mpsc::unbounded_channel::<()>();
                let decode_stats = Arc::clone(&stats);
                std::thread::spawn(move || decode_loop(au_rx, frame_tx, fail_tx, decode_stats, receive, w, h));
                // One task only reads (a read is not cancelled half-way), the other orders.
                let (packet_tx, packet_rx) = mpsc::unbounded_channel();
                tokio::spawn(async move {
                    while let Ok((packet, _)) = track.read_rtp().await {
                        if packet_tx.send((packet, Instant::now())).is_err() {
                            break;
                        }
                    }
                });
                let reassembler = Reassembler::new(reassembly::DEFAULT_WAIT, stats);
                tokio::spawn(reassemble(packet_rx, fail_rx, au_tx, pli_tx, reassembler));
            })
        }));

        let (msg_tx, mut messages) = mpsc::unbounded_channel();
        let (depth_tx, depth) = mpsc::unbounded_channel();
        channel.on_message(Box::new(move |m: DataChannelMessage| {
            if !m.is_string {
                let _ = depth_tx.send(DepthFrame::decode(&m.data));
            } else {
                match serde_json::from_slice::<ToViewer>(&m.data) {
                    Ok(msg) => {
                        let _ = msg_tx.send(msg);
                    }
                    Err(e) => tracing::warn!("unreadable message from the master: {e}"),
                }
            }
            Box::pin(async {})
        }));

        let offer = pc.create_offer(None).await?;
        pc.set_local_description(offer).await?;
        let sdp = pc.local_description().await.context("no local description")?.sdp;
        ws_tx.send(Message::text(serde_json::to_string(&ToSignal::Offer { sdp })?)).await?;

        // From here a task owns the websocket: it applies the answer and candidates and
        // forwards everything else.
        // It holds the peer weakly (the peer's callbacks do not hold the task), and when the
        // client is closed or dropped (its sender gone) it closes the websocket properly.
        let (sig_tx, mut signaling) = mpsc::unbounded_channel();
        let weak_pc = Arc::downgrade(&pc);
        tokio::spawn(async move {
            loop {
                tokio::select! {
                    out = ws_out_rx.recv() => {
                        let Some(out) = out else {
                            let _ = ws_tx.close().await;
                            break;
                        };
                        let Ok(text) = serde_json::to_string(&out) else { continue };
                        if ws_tx.send(Message::text(text)).await.is_err() { break }
                    }
                    msg = next_signal(&mut ws_rx) => match msg {
                        Ok(ToClient::Answer { sdp }) => {
                            let Some(pc2) = weak_pc.upgrade() else { break };
                            let applied = match RTCSessionDescription::answer(sdp) {
                                Ok(answer) => pc2.set_remote_description(answer).await.map_err(|e| anyhow!(e)),
                                Err(e) => Err(anyhow!(e)),
                            };
                            if let Err(e) = applied {
                                let _ = sig_tx.send(ToClient::Error { code: nephele_protocol::ErrorCode::BadRequest, message: format!("bad answer: {e}") });
                            }
                        }
                        Ok(ToClient::Ice { candidate }) => {
                            let Some(pc2) = weak_pc.upgrade() else { break };
                            if let Ok(init) = serde_json::from_value::<RTCIceCandidateInit>(candidate)
                                && !init.candidate.is_empty()
                                && let Err(e) = pc2.add_ice_candidate(init).await
                            {
                                tracing::debug!("bad candidate from the master: {e}");
                            }
                        }
                        Ok(other) => { let _ = sig_tx.send(other); }
                        Err(_) => break,
                    },
                }
            }
        });

        // Wait for the master's session message (sent when the channel opens).
        let session = loop {
            tokio::select! {
                m = messages.recv() => match m {
                    Some(m @ ToViewer::Session { .. }) => break m,
                    Some(_) => continue,
                    None => bail!("the pose channel closed before the session started"),
                },
                s = signaling.recv() => match s {
                    Some(ToClient::Error { code, message }) => bail!("signaling error ({code:?}): {message}"),
                    Some(ToClient::Ended { reason }) => bail!("the master ended the session: {reason}"),
                    Some(_) => continue,
                    None => bail!("signaling closed"),
                },
                Some(0) = gathered.recv() => {
                    let servers: Vec<&str> = ice_servers.iter().flat_map(|s| s.urls.iter().map(String::as_str)).collect();
                    if net.relay_only {
                        bail!("no TURN relay candidate was gathered: the TURN server ({}) is unreachable or refused the credentials", servers.join(", "));
                    }
                    bail!("no ICE candidate was gathered (no usable network interface)");
                }
            }
        };
        Ok(Self { pc, channel, frames, messages, depth, session, signaling, ws_out, video_ssrc, stats, last_paced: std::sync::Mutex::new(None), poses_held_back: AtomicU64::new(0), closed: AtomicBool::new(false) })
    }

    pub async fn send_pose(&self, pose: &PoseMessage) -> Result<()> {
        self.send_bytes(Bytes::from(pose.encode())).await
    }

    /// Sends a pose unless it would only queue behind unacknowledged ones; returns whether it
    /// went out. Poses are latest-wins and never retransmitted, so a backlog is worth nothing,
    /// and on a path that went dark it is harmful: the pose channel's SCTP keeps the lost
    /// messages in flight until a timeout that backs off from 1 s (2 s, 4 s, ...), and when
    /// they fill its congestion window nothing new leaves until then, so the stream would
    /// stay frozen for seconds after the path is back. Here the backlog stays below what
    /// that window lets through: every pose while at most [`POSE_BACKLOG_FREE`] bytes are
    /// unacknowledged, otherwise one every [`POSE_PROBE_EVERY`] while they fit in
    /// [`SCTP_WINDOW_AFTER_TIMEOUT`]. The first of those to arrive after an outage is
    /// acknowledged at once (it leaves a gap), which clears the lost ones (FORWARD-TSN).
    pub async fn send_pose_paced(&self, pose: &PoseMessage) -> Result<bool> {
        let bytes = pose.encode();
        let backlog = self.channel.buffered_amount().await + bytes.len();
        let now = Instant::now();
        let send = {
            let mut last = self.last_paced.lock().unwrap_or_else(|e| e.into_inner());
            let send = backlog <= POSE_BACKLOG_FREE || (backlog <= SCTP_WINDOW_AFTER_TIMEOUT && last.is_none_or(|t| now - t >= POSE_PROBE_EVERY));
            if send {
                *last = Some(now);
            }
            send
        };
        if !send {
            self.poses_held_back.fetch_add(1, Ordering::Relaxed);
            return Ok(false);
        }
        self.send_bytes(Bytes::from(bytes)).await?;
        Ok(true)
    }

    /// Poses [`StreamClient::send_pose_paced`] held back so far.
    pub fn poses_held_back(&self) -> u64 {
        self.poses_held_back.load(Ordering::Relaxed)
    }

    /// Sends arbitrary bytes on the pose channel (tests of bad input).
    pub async fn send_bytes(&self, bytes: Bytes) -> Result<()> {
        self.channel.send(&bytes).await.context("pose channel send")?;
        Ok(())
    }

    pub async fn send_text(&self, text: &str) -> Result<()> {
        self.channel.send_text(text.to_owned()).await.context("pose channel send")?;
        Ok(())
    }

    /// Asks the master for an IDR, as a receiver does after packet loss.
    pub async fn send_pli(&self) -> Result<()> {
        let ssrc = self.video_ssrc.load(Ordering::Relaxed);
        self.pc.write_rtcp(&[Box::new(PictureLossIndication { sender_ssrc: 0, media_ssrc: ssrc })]).await?;
        self.stats.count_pli();
        Ok(())
    }

    /// Bytes sent on the pose channel and not acknowledged yet (SCTP's buffered amount).
    pub async fn pose_backlog(&self) -> usize {
        self.channel.buffered_amount().await
    }

    /// The ICE candidate pair carrying the stream (local end, remote end), once ICE has
    /// nominated one: the candidates' types say whether it is direct or relayed.
    pub async fn selected_pair(&self) -> Option<(PairEnd, PairEnd)> {
        use webrtc::stats::StatsReportType as S;
        let reports = self.pc.get_stats().await.reports;
        let end = |id: &str| match reports.get(id) {
            Some(S::LocalCandidate(c) | S::RemoteCandidate(c)) => Some(PairEnd { kind: c.candidate_type.to_string(), ip: c.ip.clone(), port: c.port }),
            _ => None,
        };
        reports
            .values()
            .filter_map(|r| match r {
                S::CandidatePair(p) if p.nominated => Some(p),
                _ => None,
            })
            .max_by_key(|p| p.bytes_received)
            .and_then(|p| Some((end(&p.local_candidate_id)?, end(&p.remote_candidate_id)?)))
    }

    /// What the receive path has counted so far (packets late, lost, IDRs, PLIs sent, ...).
    pub fn receive_stats(&self) -> ReceiveCounts {
        self.stats.snapshot()
    }

    /// Leaves: tells signaling, closes the peer connection, then the signaling websocket
    /// (with a close frame). Dropping a client does the same without the `leave`.
    pub async fn close(self) {
        let _ = self.ws_out.send(ToSignal::Leave {});
        tokio::time::sleep(Duration::from_millis(50)).await;
        self.closed.store(true, Ordering::Relaxed);
        let _ = self.pc.close().await;
    }
}

impl Drop for StreamClient {
    fn drop(&mut self) {
        // The websocket task ends when `ws_out` goes with this struct; the peer connection's
        // own tasks would keep it alive (answering ICE, so the master never lets it go).
        if !self.closed.load(Ordering::Relaxed)
            && let Ok(rt) = tokio::runtime::Handle::try_current()
        {
            let pc = Arc::clone(&self.pc);
            rt.spawn(async move {
                let _ = pc.close().await;
            });
        }
    }
}

/// A TCP connection to the host of the `ws://` URL `url`, from the address `source`.
pub async fn connect_from(source: std::net::IpAddr, url: &str) -> Result<tokio::net::TcpStream> {
    use tokio_tungstenite::tungstenite::client::IntoClientRequest;
    let request = url.into_client_request().with_context(|| format!("not a websocket URL: {url}"))?;
    let uri = request.uri();
    anyhow::ensure!(uri.scheme_str() == Some("ws"), "a source address needs a ws:// URL, not {url}");
    let host = uri.host().context("the URL has no host")?.trim_matches(['[', ']']);
    let target = tokio::net::lookup_host((host, uri.port_u16().unwrap_or(80))).await?.next().with_context(|| format!("{host} has no address"))?;
    let socket = if target.is_ipv4() { tokio::net::TcpSocket::new_v4()? } else { tokio::net::TcpSocket::new_v6()? };
    socket.bind(std::net::SocketAddr::new(source, 0)).with_context(|| format!("binding to {source}"))?;
    Ok(socket.connect(target).await?)
}

async fn next_signal<S>(rx: &mut S) -> Result<ToClient>
where
    S: futures_util::Stream<Item = Result<Message, tokio_tungstenite::tungstenite::Error>> + Unpin,
{
    loop {
        match rx.next().await {
            None => bail!("signaling closed the connection"),
            Some(Err(e)) => bail!("signaling connection: {e}"),
            Some(Ok(Message::Text(t))) => return serde_json::from_str(&t).with_context(|| format!("unreadable signaling message {t}")),
            Some(Ok(Message::Close(_))) => bail!("signaling closed the connection"),
            Some(Ok(_)) => continue,
        }
    }
}

/// Orders the track's packets into access units for the decoder; asks for PLIs when a
/// picture is lost (a hole given up, or the decoder refused an access unit).
async fn reassemble(
    mut packets: mpsc::UnboundedReceiver<(webrtc::rtp::packet::Packet, Instant)>,
    mut failures: mpsc::UnboundedReceiver<()>,
    aus: std::sync::mpsc::Sender<Unit>,
    pli: mpsc::UnboundedSender<()>,
    mut r: Reassembler,
) {
    loop {
        let deadline = r.deadline();
        tokio::select! {
            p = packets.recv() => match p {
                Some((p, at)) => r.push(p.header.sequence_number, p.header.timestamp, p.header.marker, p.payload, at),
                None => return,
            },
            Some(()) = failures.recv() => r.request_idr(Instant::now()),
            _ = tokio::time::sleep_until(tokio::time::Instant::from_std(deadline.unwrap_or_else(Instant::now))), if deadline.is_some() => {}
        }
        let now = Instant::now();
        while let Some(unit) = r.pop(now) {
            if aus.send(unit).is_err() {
                return;
            }
        }
        if r.take_pli(now) {
            let _ = pli.send(());
        }
    }
}

/// Writes the PLIs [`reassemble`] asks for (it spaces them out).
async fn send_plis(pc: std::sync::Weak<RTCPeerConnection>, ssrc: Arc<AtomicU32>, stats: Arc<ReceiveStats>, mut wanted: mpsc::UnboundedReceiver<()>) {
    while wanted.recv().await.is_some() {
        let Some(pc) = pc.upgrade() else { return };
        let pli = PictureLossIndication { sender_ssrc: 0, media_ssrc: ssrc.load(Ordering::Relaxed) };
        match pc.write_rtcp(&[Box::new(pli)]).await {
            Ok(_) => {
                stats.count_pli();
                tracing::debug!("picture lost: PLI sent");
            }
            Err(e) => tracing::debug!("cannot send a PLI: {e}"),
        }
    }
}

/// Decoder thread: access units in, RGBA frames out (cropped to the session size).
fn decode_loop(
    aus: std::sync::mpsc::Receiver<Unit>,
    out: mpsc::UnboundedSender<ReceivedFrame>,
    failures: mpsc::UnboundedSender<()>,
    stats: Arc<ReceiveStats>,
    receive: Receive,
    width: u32,
    height: u32,
) {
    if receive == Receive::AccessUnits {
        for Unit { annex_b: au, arrived_at, idr } in aus {
            let frame = ReceivedFrame { pose_seq: parse_pose_seq(&au), arrived_at, decoded_at: arrived_at, bytes: au.len(), width, height, rgba: Vec::new(), idr };
            if out.send(frame).is_err() {
                return;
            }
        }
        return;
    }
    let keep_pixels = receive == Receive::Pixels;
    let mut decoder = match Decoder::new() {
        Ok(d) => d,
        Err(e) => {
            tracing::error!("cannot create the H.264 decoder: {e}");
            return;
        }
    };
    let mut full = Vec::new();
    // After a refused access unit, P frames already queued are skipped up to the next IDR.
    let mut broken = false;
    for Unit { annex_b: au, arrived_at, idr } in aus {
        if broken && !idr {
            continue;
        }
        broken = false;
        let pose_seq = parse_pose_seq(&au);
        let decoded = match decoder.decode(&au) {
            Ok(Some(yuv)) => yuv,
            Ok(None) => continue,
            Err(e) => {
                tracing::debug!("undecodable access unit: {e}");
                stats.count_decode_error();
                broken = true;
                let _ = failures.send(());
                continue;
            }
        };
        // Decoded now: the copy to RGBA below is this client's, for PSNR and saved frames (a
        // browser shows the YUV picture as it is), so it is not part of the frame's latency.
        let decoded_at = Instant::now();
        let (dw, dh) = decoded.dimensions();
        let mut rgba = Vec::new();
        if keep_pixels {
            full.resize(dw * dh * 4, 0);
            decoded.write_rgba8(&mut full);
            let (w, h) = ((width as usize).min(dw), (height as usize).min(dh));
            rgba.reserve(w * h * 4);
            for row in full.chunks_exact(dw * 4).take(h) {
                rgba.extend_from_slice(&row[..w * 4]);
            }
        }
        let frame = ReceivedFrame {
            pose_seq,
            arrived_at,
            decoded_at,
            bytes: au.len(),
            width: width.min(dw as u32),
            height: height.min(dh as u32),
            rgba,
            idr,
        };
        if out.send(frame).is_err() {
            return;
        }
    }
}
