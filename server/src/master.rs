//! The master node: registers with signaling, and for every paired client runs one session
//! task: a WebRTC peer ([`crate::rtc`]), the sans-IO [`Session`] rules, and the frame path
//! pose → render (farm) → RGBA→I420 → H.264 → RTP, with frame info back on the pose channel.
//!
//! Isolation: each session is its own task; a bad message, a failed render or even a
//! panicking frame ends at most that session, with a reason sent to its client.

use std::{
    collections::HashMap,
    sync::Arc,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use glam::Vec3;
use nephele_renderer::ViewRequest;
use nephele_signaling::{Mode, ToMaster, ToSignal};
use serde_json::Value;
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message;

use crate::{
    encode::{EncoderConfig, FrameEncoder},
    farm::{Farm, SceneEntry},
    rtc::{MasterPeer, PeerEvent, RtcConfig, WebrtcPeer, build_api},
    session::{FrameJob, FrameTimes, RenderScale, Session},
    wire::{FrameInfo, ToViewer},
};

/// Largest frame a session may ask for, in pixels (4K UHD).
pub const MAX_STREAM_PIXELS: u64 = 3840 * 2160;
/// Background behind the object in viewer mode (linear RGB).
pub const VIEWER_BACKGROUND: Vec3 = Vec3::ONE;
/// AR mode renders over pure green, keyed out by the client.
pub const AR_BACKGROUND: Vec3 = Vec3::new(0.0, 1.0, 0.0);
const HEARTBEAT_EVERY: Duration = Duration::from_secs(5);

#[derive(Debug, Clone)]
pub struct MasterConfig {
    pub name: String,
    pub capacity: u32,
    pub token: Option<String>,
    pub rtc: RtcConfig,
    /// Fixed or dynamic render resolution (the speed/accuracy knob).
    pub render_scale: RenderScale,
}

/// Messages from the signaling loop to one session task.
#[derive(Debug)]
enum Command {
    Offer(String),
    Ice(Value),
    Leave,
}

/// What a session asks of the signaling loop.
type ToSignalTx = mpsc::UnboundedSender<ToSignal>;

/// Connects to `signal_url` (ws://host:port/signal), registers, and serves sessions until
/// the process stops; reconnects with back-off if signaling goes away.
pub async fn run(signal_url: String, cfg: MasterConfig, farm: Arc<Farm>) -> Result<()> {
    let api = build_api(&cfg.rtc)?;
    let mut backoff = Duration::from_millis(500);
    loop {
        match connect_once(&signal_url, &cfg, &farm, &api).await {
            Ok(()) => tracing::warn!("signaling closed the connection; reconnecting"),
            Err(e) => tracing::warn!("signaling connection: {e:#}"),
        }
        tokio::time::sleep(backoff).await;
        backoff = (backoff * 2).min(Duration::from_secs(10));
    }
}

async fn connect_once(url: &str, cfg: &MasterConfig, farm: &Arc<Farm>, api: &Arc<webrtc::api::API>) -> Result<()> {
    let (ws, _) = tokio_tungstenite::connect_async(url).await.with_context(|| format!("connecting to {url}"))?;
    let (mut ws_tx, mut ws_rx) = ws.split();
    let register = ToSignal::Register { name: cfg.name.clone(), capacity: cfg.capacity, token: cfg.token.clone() };
    ws_tx.send(Message::text(serde_json::to_string(&register)?)).await?;

    let (out_tx, mut out_rx) = mpsc::unbounded_channel::<ToSignal>();
    let mut sessions: HashMap<String, mpsc::UnboundedSender<Command>> = HashMap::new();
    let (gone_tx, mut gone_rx) = mpsc::unbounded_channel::<(String, String)>();
    let mut heartbeat = tokio::time::interval(HEARTBEAT_EVERY);
    loop {
        tokio::select! {
            msg = ws_rx.next() => {
                let text = match msg {
                    None => return Ok(()),
                    Some(Err(e)) => return Err(e.into()),
                    Some(Ok(Message::Text(t))) => t,
                    Some(Ok(Message::Close(_))) => return Ok(()),
                    Some(Ok(_)) => continue,
                };
                let msg: ToMaster = match serde_json::from_str(&text) {
                    Ok(m) => m,
                    Err(e) => { tracing::warn!("unreadable message from signaling: {e}"); continue }
                };
                match msg {
                    ToMaster::Registered { master } => tracing::info!(%master, "registered with signaling"),
                    ToMaster::Join { session, scene, mode, width, height, fps } => {
                        match check_join(farm, &scene, mode, width, height) {
                            Err(reason) => { let _ = out_tx.send(ToSignal::Reject { session, reason }); }
                            Ok(entry) => {
                                let (cmd_tx, cmd_rx) = mpsc::unbounded_channel();
                                sessions.insert(session.clone(), cmd_tx);
                                let ctx = SessionCtx { id: session, entry, farm: Arc::clone(farm), mode, width, height, fps, render_scale: cfg.render_scale, to_signal: out_tx.clone() };
                                let (api, gone) = (Arc::clone(api), gone_tx.clone());
                                tokio::spawn(async move {
                                    let id = ctx.id.clone();
                                    // The session body runs in its own task so that a panic
                                    // inside it ends this session only.
                                    let outcome = tokio::spawn(run_session(ctx, api, cmd_rx)).await;
                                    let reason = match outcome {
                                        Ok(Ok(reason)) => reason,
                                        Ok(Err(e)) => format!("session error: {e:#}"),
                                        Err(e) => format!("internal error in the session ({e})"),
                                    };
                                    tracing::info!(session = %id, %reason, "session ended");
                                    let _ = gone.send((id, reason));
                                });
                            }
                        }
                    }
                    ToMaster::Offer { session, sdp } => forward(&sessions, &session, Command::Offer(sdp)),
                    ToMaster::Ice { session, candidate } => forward(&sessions, &session, Command::Ice(candidate)),
                    ToMaster::Leave { session } => {
                        forward(&sessions, &session, Command::Leave);
                        sessions.remove(&session);
                    }
                    ToMaster::Error { code, message } => {
                        tracing::warn!(?code, %message, "signaling refused a message");
                        if matches!(code, nephele_signaling::ErrorCode::Unauthorized) {
                            bail!("signaling refused our token: {message}");
                        }
                    }
                }
            }
            Some(out) = out_rx.recv() => {
                ws_tx.send(Message::text(serde_json::to_string(&out)?)).await?;
            }
            Some((session, reason)) = gone_rx.recv() => {
                // A session the client already left (removed on `leave`) needs no `end`.
                if sessions.remove(&session).is_some() {
                    ws_tx.send(Message::text(serde_json::to_string(&ToSignal::End { session, reason })?)).await?;
                }
            }
            _ = heartbeat.tick() => {
                let hb = ToSignal::Heartbeat { sessions: sessions.len() as u32 };
                ws_tx.send(Message::text(serde_json::to_string(&hb)?)).await?;
            }
        }
    }
}

fn forward(sessions: &HashMap<String, mpsc::UnboundedSender<Command>>, id: &str, cmd: Command) {
    match sessions.get(id) {
        Some(tx) => {
            let _ = tx.send(cmd);
        }
        None => tracing::debug!(session = id, "message for an unknown session"),
    }
}

/// Refuses what this master cannot serve, in words the user will see.
fn check_join(farm: &Farm, scene: &str, mode: Mode, width: u32, height: u32) -> Result<Arc<SceneEntry>, String> {
    if !matches!(mode, Mode::Viewer | Mode::Ar) {
        return Err(format!("mode {mode:?} is not served yet (viewer and ar are)"));
    }
    if width == 0 || height == 0 || u64::from(width) * u64::from(height) > MAX_STREAM_PIXELS {
        return Err(format!("frame size {width}x{height} is outside 1x1..3840x2160 pixels"));
    }
    farm.scenes.get(scene).cloned().ok_or_else(|| format!("unknown scene {scene:?}; this master has: {}", farm.names().join(", ")))
}

struct SessionCtx {
    id: String,
    entry: Arc<SceneEntry>,
    farm: Arc<Farm>,
    mode: Mode,
    width: u32,
    height: u32,
    fps: u32,
    render_scale: RenderScale,
    to_signal: ToSignalTx,
}

/// The result of one frame's blocking work, with the encoder handed back.
struct FrameResult {
    encoder: FrameEncoder,
    rgba: Vec<u8>,
    outcome: Result<(Bytes, FrameTimes)>,
}

/// One session: returns why it ended.
async fn run_session(ctx: SessionCtx, api: Arc<webrtc::api::API>, mut commands: mpsc::UnboundedReceiver<Command>) -> Result<String> {
    let (ev_tx, mut events) = mpsc::channel::<PeerEvent>(256);
    let peer = WebrtcPeer::new(&api, ev_tx).await?;
    let result = session_loop(&ctx, &peer, &mut commands, &mut events).await;
    peer.close().await;
    result
}

async fn session_loop(
    ctx: &SessionCtx,
    peer: &impl MasterPeer,
    commands: &mut mpsc::UnboundedReceiver<Command>,
    events: &mut mpsc::Receiver<PeerEvent>,
) -> Result<String> {
    let session_start = Instant::now();
    let mut session = Session::with_scale(ctx.width, ctx.height, ctx.fps, ctx.render_scale);
    let mut encoder = Some(FrameEncoder::new(EncoderConfig::new(ctx.width, ctx.height, ctx.fps)).context("creating the encoder")?);
    let mut last_rgba: Vec<u8> = Vec::new();
    let mut in_flight: Option<tokio::task::JoinHandle<FrameResult>> = None;
    let mut current_job: Option<FrameJob> = None;
    let mut last_sent: Option<Instant> = None;
    let frame_period = Duration::from_secs_f64(1.0 / f64::from(ctx.fps.max(1)));
    let background = if ctx.mode == Mode::Ar { AR_BACKGROUND } else { VIEWER_BACKGROUND };
    let connect_deadline = tokio::time::sleep(Duration::from_secs(30));
    tokio::pin!(connect_deadline);
    let mut connected = false;

    loop {
        // Start a frame if the rules allow one.
        if in_flight.is_none()
            && let Some(job) = session.poll_frame(Instant::now())
        {
            let mut enc = encoder.take().expect("the encoder is home when no frame is in flight");
            if job.idr {
                enc.force_idr();
            }
            let entry = Arc::clone(&ctx.entry);
            let settings = ctx.farm.settings;
            let reuse = job.same_as_previous.then(|| std::mem::take(&mut last_rgba));
            let (w, h) = (ctx.width, ctx.height);
            in_flight = Some(tokio::task::spawn_blocking(move || {
                render_and_encode(entry, settings, job, background, enc, reuse, w, h, session_start)
            }));
            current_job = Some(job);
        }
        let wakeup = session.next_wakeup().map(tokio::time::Instant::from_std);
        tokio::select! {
            done = async { in_flight.as_mut().expect("guarded").await }, if in_flight.is_some() => {
                in_flight = None;
                let job = current_job.take().expect("a job is in flight");
                let result = done.map_err(|e| anyhow::anyhow!("frame task failed: {e}"))?;
                encoder = Some(result.encoder);
                last_rgba = result.rgba;
                match result.outcome {
                    Ok((au, mut times)) => {
                        let now = Instant::now();
                        let duration = last_sent.map_or(frame_period, |t| now.duration_since(t));
                        last_sent = Some(now);
                        peer.send_video(au, duration).await?;
                        times.send_ms = now.elapsed().as_secs_f64() * 1e3;
                        if let Some(info) = session.frame_done(times) {
                            send_json(peer, &ToViewer::Frame(info)).await;
                            log_frame(&ctx.id, &info);
                        }
                    }
                    Err(e) => {
                        session.frame_failed();
                        tracing::warn!(session = %ctx.id, frame = job.frame, "frame failed: {e:#}");
                        send_json(peer, &ToViewer::Error { code: "frame_failed".into(), message: format!("{e:#}") }).await;
                    }
                }
            }
            cmd = commands.recv() => match cmd {
                None | Some(Command::Leave) => return Ok("the client left".into()),
                Some(Command::Offer(sdp)) => match peer.answer(&sdp).await {
                    Ok(answer) => { let _ = ctx.to_signal.send(ToSignal::Answer { session: ctx.id.clone(), sdp: answer }); }
                    Err(e) => return Ok(format!("bad offer: {e:#}")),
                },
                Some(Command::Ice(c)) => if let Err(e) = peer.add_remote_ice(&c).await {
                    tracing::debug!(session = %ctx.id, "ignoring a bad ICE candidate: {e:#}");
                },
            },
            ev = events.recv() => match ev {
                None => return Ok("peer connection gone".into()),
                Some(PeerEvent::LocalIce(candidate)) => {
                    let _ = ctx.to_signal.send(ToSignal::Ice { session: Some(ctx.id.clone()), candidate });
                }
                Some(PeerEvent::Connected) => {
                    connected = true;
                    tracing::info!(session = %ctx.id, "peer connected");
                    // Anything sent before the track was bound is lost: start with an IDR.
                    session.on_picture_loss(Instant::now());
                }
                Some(PeerEvent::ChannelOpen) => {
                    let b = ctx.entry.center;
                    let hello = ToViewer::Session {
                        scene: ctx.entry.name.clone(), mode: ctx.mode, center: b.to_array(), radius: ctx.entry.radius,
                        up: [0.0, 0.0, 1.0], width: ctx.width, height: ctx.height, fps: ctx.fps,
                    };
                    send_json(peer, &hello).await;
                }
                Some(PeerEvent::Binary(bytes)) => {
                    if let Err(e) = session.on_pose(&bytes, Instant::now()) {
                        send_json(peer, &ToViewer::Error { code: "bad_pose".into(), message: e.to_string() }).await;
                    }
                }
                Some(PeerEvent::Text(text)) => {
                    let shown: String = text.chars().take(40).collect();
                    send_json(peer, &ToViewer::Error { code: "bad_pose".into(), message: format!("pose messages are binary; got text {shown:?}") }).await;
                }
                Some(PeerEvent::Oversized(len)) => {
                    send_json(peer, &ToViewer::Error { code: "bad_pose".into(), message: format!("message of {len} bytes refused (limit {})", crate::rtc::MAX_CHANNEL_MESSAGE) }).await;
                }
                Some(PeerEvent::PictureLoss) => { session.on_picture_loss(Instant::now()); }
                Some(PeerEvent::Closed(reason)) => return Ok(reason),
            },
            _ = async { tokio::time::sleep_until(wakeup.expect("guarded")).await }, if wakeup.is_some() => {}
            _ = &mut connect_deadline, if !connected => return Ok("the peer did not connect within 30 s".into()),
        }
    }
}

async fn send_json(peer: &impl MasterPeer, msg: &ToViewer) {
    if let Err(e) = peer.send_text(msg.to_json()).await {
        tracing::debug!("pose channel send failed: {e:#}");
    }
}

fn log_frame(session: &str, info: &FrameInfo) {
    tracing::debug!(
        session, frame = info.frame, pose = info.pose_seq, render_ms = info.times.render_ms, encode_ms = info.times.encode_ms,
        bytes = info.times.bytes, idr = info.times.idr, "frame sent"
    );
}

/// Blocking: render the job's view (or reuse the previous pixels), convert and encode.
#[allow(clippy::too_many_arguments)]
fn render_and_encode(
    entry: Arc<SceneEntry>,
    settings: nephele_renderer::RenderSettings,
    job: FrameJob,
    background: Vec3,
    mut encoder: FrameEncoder,
    reuse: Option<Vec<u8>>,
    width: u32,
    height: u32,
    session_start: Instant,
) -> FrameResult {
    let started = Instant::now();
    let rendered: Result<Vec<u8>> = match reuse {
        Some(rgba) if rgba.len() == (width * height * 4) as usize => Ok(rgba),
        _ => {
            let mut view = job.pose.view;
            if job.render_scale < 1.0 {
                view.intrinsics = view.intrinsics.scaled(job.render_scale);
            }
            let request = ViewRequest { view, instance: job.pose.instance, background };
            entry
                .prepared
                .render(&[request], &settings)
                .map(|mut out| {
                    let f = out.frames.swap_remove(0);
                    if (f.width, f.height) == (width, height) { f.rgba } else { upscale_bilinear(&f.rgba, f.width, f.height, width, height) }
                })
                .map_err(|e| anyhow::anyhow!("render: {e}"))
        }
    };
    let render_ms = started.elapsed().as_secs_f64() * 1e3;
    let rgba = match rendered {
        Ok(rgba) => rgba,
        Err(e) => return FrameResult { encoder, rgba: Vec::new(), outcome: Err(e) },
    };
    let t_ms = job.started_at.duration_since(session_start).as_millis() as u64;
    let outcome = encoder
        .encode_at(&rgba, width, height, u64::from(job.pose.seq), t_ms)
        .map(|f| {
            let times = FrameTimes { render_ms, convert_ms: f.convert_ms, encode_ms: f.encode_ms, send_ms: 0.0, bytes: f.annex_b.len(), idr: f.is_idr };
            (Bytes::from(f.annex_b), times)
        })
        .map_err(|e| anyhow::anyhow!("encode: {e}"));
    FrameResult { encoder, rgba, outcome }
}

/// Bilinear resize of RGBA8 from `sw`×`sh` to `dw`×`dh`, pixel centres aligned.
pub fn upscale_bilinear(src: &[u8], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<u8> {
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    // Source coordinate and weight of each destination column/row.
    let taps = |d: usize, s: usize| -> Vec<(usize, usize, f32)> {
        (0..d)
            .map(|i| {
                let x = ((i as f32 + 0.5) * s as f32 / d as f32 - 0.5).clamp(0.0, (s - 1) as f32);
                let x0 = x as usize;
                (x0, (x0 + 1).min(s - 1), x - x0 as f32)
            })
            .collect()
    };
    let (cols, rows) = (taps(dw, sw), taps(dh, sh));
    let mut out = vec![0u8; dw * dh * 4];
    for (y, &(y0, y1, fy)) in rows.iter().enumerate() {
        let (r0, r1) = (&src[y0 * sw * 4..(y0 + 1) * sw * 4], &src[y1 * sw * 4..(y1 + 1) * sw * 4]);
        let row = &mut out[y * dw * 4..(y + 1) * dw * 4];
        for (px, &(x0, x1, fx)) in row.chunks_exact_mut(4).zip(&cols) {
            for c in 0..4 {
                let top = f32::from(r0[x0 * 4 + c]) * (1.0 - fx) + f32::from(r0[x1 * 4 + c]) * fx;
                let bottom = f32::from(r1[x0 * 4 + c]) * (1.0 - fx) + f32::from(r1[x1 * 4 + c]) * fx;
                px[c] = (top * (1.0 - fy) + bottom * fy).round() as u8;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::upscale_bilinear;

    #[test]
    fn upscaling_keeps_flat_colour_and_interpolates_between_pixels() {
        let flat = [10u8, 200, 30, 255].repeat(3 * 2);
        assert_eq!(upscale_bilinear(&flat, 3, 2, 7, 5), [10u8, 200, 30, 255].repeat(7 * 5));
        // 2×1 black|white → 4×1: centres at 0.25 and 0.75 of the way.
        let src = [0, 0, 0, 255, 255, 255, 255, 255];
        let out = upscale_bilinear(&src, 2, 1, 4, 1);
        let reds: Vec<u8> = out.chunks(4).map(|p| p[0]).collect();
        assert_eq!(reds, vec![0, 64, 191, 255]);
        // Same size is the identity.
        assert_eq!(upscale_bilinear(&src, 2, 1, 2, 1), src.to_vec());
    }
}
