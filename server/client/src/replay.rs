//! Pose traces and their replay through a real server (`nephele replay`).
//!
//! A trace is a recorded camera path: one camera-to-world matrix per 20 ms tick. The replay
//! client sends the poses on schedule, decodes what comes back, reads the answered pose
//! sequence from each access unit's SEI, and reports pose→decoded latency on its own clock,
//! fps, bitrate, the master's per-stage times, and image quality against a direct render of
//! the same pose (PSNR; in AR mode also the IoU of the keyed-out green against the
//! renderer's alpha).

use std::{
    collections::HashMap,
    path::Path,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use glam::{DVec3, Mat4, Vec3};
use nephele_renderer::{Frame, Instance, Intrinsics, PreparedAsset, RenderSettings, View, ViewRequest, views::projection_from_intrinsics};
use nephele_protocol::Mode;
use serde::{Deserialize, Serialize};

pub use nephele_renderer::render::psnr_rgb;

use super::{ClientOptions, ReceivedFrame, StreamClient};
use nephele_wire::{FrameInfo, MultiViewPose, PoseMessage, PoseView, ToViewer, Viewport, background_of};

/// A recorded camera path.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trace {
    pub name: String,
    pub description: String,
    /// Vertical field of view, degrees.
    pub fov_y_deg: f64,
    /// Time between poses, ms.
    pub period_ms: f64,
    /// Camera-to-world matrices, column-major, OpenGL camera, scene units (world up +z).
    pub poses: Vec<[f32; 16]>,
}

/// The traces shipped in `examples/traces/`, made by [`Trace::builtin`].
pub const BUILTIN_TRACES: &[&str] = &["orbit", "zoom", "shake", "head"];

impl Trace {
    /// A built-in trace by name ([`BUILTIN_TRACES`]), or a trace file.
    pub fn from_spec(spec: &str) -> Result<Self> {
        if BUILTIN_TRACES.contains(&spec) { Self::builtin(spec) } else { Self::load(std::path::Path::new(spec)) }
    }

    /// Built-in camera paths around the origin (the procedural scenes' centre):
    /// `orbit` (one turn in 5 s), `zoom` (distance 4 → 1.3, a close-up, and back),
    /// `shake` (fast ±12° jitter, as a hand-held phone), `head` (6 s of head turns at
    /// human speeds: [`head_pose`]).
    pub fn builtin(name: &str) -> Result<Self> {
        let n = 250; // 5 s at 20 ms
        let orbit = |az: f64, el: f64, dist: f64| View::orbit(DVec3::ZERO, dist, az, el, Intrinsics::from_fov_x(2, 2, 1.0)).world_from_camera.as_mat4().to_cols_array();
        let (description, poses): (&str, Vec<[f32; 16]>) = match name {
            "orbit" => ("one turn around the object at distance 4, elevation 20°", (0..n).map(|i| orbit(360.0 * i as f64 / n as f64, 20.0, 4.0)).collect()),
            "zoom" => (
                "zoom from distance 4 to a close-up at 1.3 and back, turning slowly",
                (0..n)
                    .map(|i| {
                        let s = (std::f64::consts::PI * i as f64 / (n - 1) as f64).sin();
                        orbit(30.0 + 0.2 * i as f64, 25.0, 4.0 - 2.7 * s)
                    })
                    .collect(),
            ),
            "shake" => (
                "hand-held shake: ±12° jitter at 3–7 Hz around azimuth 40°",
                (0..n)
                    .map(|i| {
                        let t = i as f64 * 0.02;
                        let tau = std::f64::consts::TAU;
                        let az = 40.0 + 8.0 * (tau * 7.0 * t).sin() + 4.0 * (tau * 3.1 * t + 1.0).sin();
                        let el = 20.0 + 6.0 * (tau * 5.3 * t + 0.5).sin();
                        orbit(az, el, 3.5 + 0.3 * (tau * 4.0 * t).sin())
                    })
                    .collect(),
            ),
            "head" => (
                "a standing viewer turning their head: yaw and pitch turns of 25–55° at 100–300°/s peak (minimum-jerk), holds between, a slow sway",
                (0..300).map(|i| head_pose(f64::from(i) * 0.02).as_mat4().to_cols_array()).collect(),
            ),
            other => bail!("unknown trace {other:?}; built-in traces: {}", BUILTIN_TRACES.join(", ")),
        };
        Ok(Self { name: name.into(), description: description.into(), fov_y_deg: 40.0, period_ms: 20.0, poses })
    }

    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading trace {}", path.display()))?;
        let trace: Self = serde_json::from_str(&text).with_context(|| format!("parsing trace {}", path.display()))?;
        if trace.poses.is_empty() || !(1.0..=1000.0).contains(&trace.period_ms) || !(1.0..=170.0).contains(&trace.fov_y_deg) {
            bail!("trace {} needs poses, period_ms in 1..=1000 and fov_y_deg in 1..=170", path.display());
        }
        Ok(trace)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("traces serialize")
    }

    /// Pinhole intrinsics for a `width`×`height` frame.
    pub fn intrinsics(&self, width: u32, height: u32) -> Intrinsics {
        let fy = 0.5 * height as f32 / (0.5 * self.fov_y_deg.to_radians() as f32).tan();
        Intrinsics { fx: fy, fy, cx: 0.5 * width as f32, cy: 0.5 * height as f32, width, height }
    }

    /// The camera at `t_ms` after the first pose: the samples on either side blended
    /// (rotation slerped, position lerped), the last one after the end.
    pub fn pose_at(&self, t_ms: f64) -> glam::DMat4 {
        let x = (t_ms / self.period_ms).max(0.0);
        let i = (x.floor() as usize).min(self.poses.len() - 1);
        let j = (i + 1).min(self.poses.len() - 1);
        let f = (x - i as f64).clamp(0.0, 1.0);
        let m = |k: usize| Mat4::from_cols_array(&self.poses[k]).as_dmat4();
        let (a, b) = (m(i), m(j));
        let qa = glam::DQuat::from_mat4(&a).normalize();
        let qb = glam::DQuat::from_mat4(&b).normalize();
        let p = a.w_axis.truncate().lerp(b.w_axis.truncate(), f);
        glam::DMat4::from_rotation_translation(qa.slerp(qb, f).normalize(), p)
    }

    /// Length of the trace, ms.
    pub fn duration_ms(&self) -> f64 {
        self.period_ms * (self.poses.len() - 1) as f64
    }

    /// Pose message `seq` for a `width`×`height` stream: the trace's pose `seq` (wrapping),
    /// stamped 20 ms apart.
    pub fn pose_message(&self, seq: u32, width: u32, height: u32) -> PoseMessage {
        PoseMessage {
            seq,
            t_client_ms: f64::from(seq) * 20.0,
            world_from_camera: Mat4::from_cols_array(&self.poses[seq as usize % self.poses.len()]),
            intrinsics: self.intrinsics(width, height),
            world_from_anchor: None,
            predicted: None,
        }
    }
}

/// The `head` trace at `t_s` seconds: a viewer 3.5 units from the object (azimuth 30°,
/// elevation 15°) turning their head about world up (yaw) and their own x axis (pitch), each
/// turn a minimum-jerk profile (peak speed 1.875 × mean; Flash & Hogan 1985), with a ±3 cm
/// lateral sway at 0.4 Hz.
pub fn head_pose(t_s: f64) -> glam::DMat4 {
    // (start s, duration s, yaw to °, pitch to °): peaks 225, 295, 117, 125, 187, 219, 156 °/s.
    const TURNS: [(f64, f64, f64, f64); 8] = [
        (0.5, 0.25, 30.0, 0.0),
        (1.15, 0.35, -25.0, 0.0),
        (1.9, 0.4, 0.0, -12.0),
        (2.7, 0.3, 20.0, -12.0),
        (3.0, 0.4, -20.0, 8.0),
        (3.9, 0.3, 15.0, 0.0),
        (4.7, 0.3, -10.0, 0.0),
        (5.5, 0.3, 0.0, 0.0),
    ];
    let (mut yaw, mut pitch) = (0.0, 0.0);
    for &(start, duration, to_yaw, to_pitch) in &TURNS {
        let tau = ((t_s - start) / duration).clamp(0.0, 1.0);
        let s = tau * tau * tau * (10.0 - 15.0 * tau + 6.0 * tau * tau);
        yaw += (to_yaw - yaw) * s;
        pitch += (to_pitch - pitch) * s;
    }
    let base = View::orbit(DVec3::ZERO, 3.5, 30.0, 15.0, Intrinsics::from_fov_x(2, 2, 1.0)).world_from_camera;
    let right = base.x_axis.truncate();
    let eye = base.w_axis.truncate() + right * (0.03 * (std::f64::consts::TAU * 0.4 * t_s).sin());
    let rotation = glam::DMat3::from_rotation_z(yaw.to_radians()) * glam::DMat3::from_mat4(base) * glam::DMat3::from_rotation_x(pitch.to_radians());
    glam::DMat4::from_cols(rotation.x_axis.extend(0.0), rotation.y_axis.extend(0.0), rotation.z_axis.extend(0.0), eye.extend(1.0))
}

/// How to replay.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    pub client: ClientOptions,
    /// AR plane anchor sent with every pose (AR mode).
    pub anchor: Option<Mat4>,
    /// Compare every n-th decoded frame with a direct render (0: none).
    pub quality_every: usize,
    /// Write the decoded frames here as PNG.
    pub save_dir: Option<std::path::PathBuf>,
    /// How long to wait for the last frames after the last pose.
    pub drain: Duration,
    /// Send the first pose at this time (several clients in lockstep), not at once.
    pub start_at: Option<Instant>,
    /// Stereo (mode `vr`): send both eyes as an `NPO2` message, side by side, each half the
    /// frame's width, eyes this far apart (scene units) along the trace camera's x axis.
    /// Frames are then not compared with a direct render (`quality_every` is ignored).
    pub stereo_baseline: Option<f32>,
}

/// Percentiles of a sample, ms.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Percentiles {
    pub p50: f64,
    pub p95: f64,
    pub p99: f64,
    pub max: f64,
    pub n: usize,
}

impl Percentiles {
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Self::default();
        }
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let at = |q: f64| v[((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)];
        Self { p50: at(0.5), p95: at(0.95), p99: at(0.99), max: v[v.len() - 1], n: v.len() }
    }
}

/// A decoded frame compared with a direct render of the pose it answers.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct QualitySample {
    pub pose_seq: u64,
    pub psnr_db: f64,
    /// AR only: IoU of the keyed object mask and the renderer's alpha mask.
    pub key_iou: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub trace: String,
    pub width: u32,
    pub height: u32,
    pub poses_sent: usize,
    pub frames_decoded: usize,
    /// Decoded frames whose SEI names a pose this client never sent (must be 0).
    pub frames_unknown_pose: usize,
    /// Decoded frames without a pose SEI (must be 0).
    pub frames_without_pose: usize,
    /// Pose sent → frame decoded, ms, on this client's clock.
    pub latency_ms: Percentiles,
    /// Pose sent → frame-info message received, ms.
    pub info_latency_ms: Percentiles,
    pub fps: f64,
    pub bitrate_kbps: f64,
    /// The master's own times from the frame-info messages.
    pub queue_ms: Percentiles,
    pub render_ms: Percentiles,
    pub convert_ms: Percentiles,
    pub encode_ms: Percentiles,
    pub send_ms: Percentiles,
    /// Multi-object and farm frames: all render tasks summed, the network hop to remote
    /// workers, depth composition, and frame start → pixels ready.
    pub render_total_ms: Percentiles,
    pub transfer_ms: Percentiles,
    pub compose_ms: Percentiles,
    pub ready_ms: Percentiles,
    /// Mean result bytes per frame that crossed the network.
    pub transfer_bytes_mean: f64,
    pub idr_frames: usize,
    /// Time between consecutive decoded frames, ms.
    pub frame_gap_ms: Percentiles,
    /// The master's render time divided among the views of each rendered frame's task, ms
    /// (mean over frames that were rendered, not reused).
    pub render_ms_per_view: f64,
    /// Mean views per render task of this client's rendered frames.
    pub mean_batch_views: f64,
    /// Frames the master reused instead of rendering (a still camera, the history table).
    pub reused_frames: usize,
    /// Mean render scale of the frames (1 = full size).
    pub mean_render_scale: f64,
    pub quality: Vec<QualitySample>,
    /// Errors the master sent on the pose channel.
    pub errors: Vec<String>,
    /// Notices the master sent (the render farm went away or came back).
    pub notices: Vec<String>,
    /// The pose each decoded frame answers, in decode order.
    pub decoded_pose_seqs: Vec<u64>,
    /// When each frame was decoded, ms after the first pose was sent.
    pub decoded_at_ms: Vec<f64>,
}

impl ReplayReport {
    pub fn min_psnr(&self) -> Option<f64> {
        self.quality.iter().map(|q| q.psnr_db).reduce(f64::min)
    }
    pub fn mean_psnr(&self) -> Option<f64> {
        (!self.quality.is_empty()).then(|| self.quality.iter().map(|q| q.psnr_db).sum::<f64>() / self.quality.len() as f64)
    }
    pub fn min_iou(&self) -> Option<f64> {
        self.quality.iter().filter_map(|q| q.key_iou).reduce(f64::min)
    }
}

impl std::fmt::Display for ReplayReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let p = |x: &Percentiles| format!("p50 {:6.1}  p95 {:6.1}  p99 {:6.1}  max {:6.1}", x.p50, x.p95, x.p99, x.max);
        writeln!(f, "trace {} at {}x{}: {} poses sent, {} frames decoded ({} IDR)", self.trace, self.width, self.height, self.poses_sent, self.frames_decoded, self.idr_frames)?;
        writeln!(f, "  pose → decoded frame ms   {}", p(&self.latency_ms))?;
        writeln!(f, "  pose → frame info ms      {}", p(&self.info_latency_ms))?;
        writeln!(f, "  master queue ms           {}", p(&self.queue_ms))?;
        writeln!(f, "  master render ms          {}", p(&self.render_ms))?;
        writeln!(f, "  master RGB→I420 ms        {}", p(&self.convert_ms))?;
        writeln!(f, "  master encode ms          {}", p(&self.encode_ms))?;
        writeln!(f, "  master send ms            {}", p(&self.send_ms))?;
        writeln!(f, "  {:.1} fps, {:.0} kbit/s", self.fps, self.bitrate_kbps)?;
        if let (Some(min), Some(mean)) = (self.min_psnr(), self.mean_psnr()) {
            writeln!(f, "  PSNR vs direct render: mean {mean:.2} dB, min {min:.2} dB over {} frames", self.quality.len())?;
        }
        if let Some(iou) = self.min_iou() {
            writeln!(f, "  AR key IoU vs renderer alpha: min {iou:.4}")?;
        }
        if self.frames_unknown_pose + self.frames_without_pose > 0 {
            writeln!(f, "  WARNING: {} frames answer no pose we sent, {} carry no pose", self.frames_unknown_pose, self.frames_without_pose)?;
        }
        for e in &self.errors {
            writeln!(f, "  master said: {e}")?;
        }
        for n in &self.notices {
            writeln!(f, "  master noted: {n}")?;
        }
        Ok(())
    }
}

/// Renders what a pose should show, for the quality comparison: `(camera, placement,
/// background) → frame` (a direct render of the served asset or composed scene).
pub type Reference<'a> = &'a (dyn Fn(View, Instance, Vec3) -> Result<Frame> + Sync);

/// A reference that renders one prepared asset.
pub fn asset_reference(prepared: &dyn PreparedAsset, settings: RenderSettings) -> impl Fn(View, Instance, Vec3) -> Result<Frame> + Sync + '_ {
    move |view, instance, background| Ok(prepared.render(&[ViewRequest { view, instance, background }], &settings)?.frames.remove(0))
}

/// Replays `trace` through the server at `opts.client.signal_url`. `reference` renders the
/// same poses directly for the quality comparison (same asset and settings as the server).
pub async fn replay(trace: &Trace, opts: &ReplayOptions, reference: Option<Reference<'_>>) -> Result<ReplayReport> {
    let mut client = StreamClient::connect(&opts.client).await?;
    let (w, h) = (opts.client.width, opts.client.height);
    let intrinsics = trace.intrinsics(w, h);
    let mut sent_at: HashMap<u64, (Instant, PoseMessage)> = HashMap::new();
    let mut frames: Vec<ReceivedFrame> = Vec::new();
    let mut infos: Vec<(FrameInfo, Instant)> = Vec::new();
    let mut errors = Vec::new();
    let mut notices = Vec::new();
    let period = Duration::from_secs_f64(trace.period_ms / 1e3);
    if let Some(at) = opts.start_at {
        tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await;
    }
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
    let mut next = 0usize;
    let mut drain_until: Option<tokio::time::Instant> = None;
    let mut signaling_open = true;
    let start = Instant::now();
    loop {
        tokio::select! {
            _ = ticker.tick(), if next < trace.poses.len() => {
                let seq = next as u32 + 1;
                let pose = PoseMessage {
                    seq,
                    t_client_ms: start.elapsed().as_secs_f64() * 1e3,
                    world_from_camera: Mat4::from_cols_array(&trace.poses[next]),
                    intrinsics,
                    world_from_anchor: opts.anchor,
                    predicted: None,
                };
                sent_at.insert(u64::from(seq), (Instant::now(), pose));
                match opts.stereo_baseline {
                    None => client.send_pose(&pose).await?,
                    Some(baseline) => client.send_bytes(stereo_pose(&pose, w, h, baseline).encode().into()).await?,
                }
                next += 1;
                if next == trace.poses.len() {
                    drain_until = Some(tokio::time::Instant::now() + opts.drain);
                }
            }
            f = client.frames.recv() => match f {
                Some(mut f) => {
                    // Keep pixels only of frames that will be compared or saved.
                    let sampled = opts.quality_every > 0 && frames.len().is_multiple_of(opts.quality_every);
                    if !sampled && opts.save_dir.is_none() {
                        f.rgba = Vec::new();
                    }
                    frames.push(f);
                }
                None => bail!("the video stream ended early"),
            },
            m = client.messages.recv() => match m {
                Some(ToViewer::Frame(info)) => infos.push((info, Instant::now())),
                Some(ToViewer::Error { code, message }) => errors.push(format!("{code}: {message}")),
                Some(ToViewer::Notice { code, message }) => notices.push(format!("{code}: {message}")),
                Some(_) => {}
                None => bail!("the pose channel closed early"),
            },
            // Signaling may go away (a restart) while the stream, peer to peer, goes on.
            s = client.signaling.recv(), if signaling_open => match s {
                Some(s) => bail!("signaling: {s:?}"),
                None => signaling_open = false,
            },
            _ = async { tokio::time::sleep_until(drain_until.expect("guarded")).await }, if drain_until.is_some() => break,
        }
    }
    client.close().await;

    let mut latency = Vec::new();
    let (mut unknown, mut without) = (0, 0);
    for f in &frames {
        match f.pose_seq.and_then(|s| sent_at.get(&s)) {
            Some((t, _)) => latency.push(f.decoded_at.duration_since(*t).as_secs_f64() * 1e3),
            None if f.pose_seq.is_some() => unknown += 1,
            None => without += 1,
        }
    }
    let info_latency: Vec<f64> = infos
        .iter()
        .filter_map(|(i, at)| sent_at.get(&u64::from(i.pose_seq)).map(|(t, _)| at.duration_since(*t).as_secs_f64() * 1e3))
        .collect();
    let span = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) if frames.len() > 1 => b.decoded_at.duration_since(a.decoded_at).as_secs_f64(),
        _ => 0.0,
    };
    let bytes: usize = frames.iter().map(|f| f.bytes).sum();
    let stat = |f: fn(&FrameInfo) -> f64| Percentiles::of(&infos.iter().map(|(i, _)| f(i)).collect::<Vec<_>>());

    if let Some(dir) = &opts.save_dir {
        std::fs::create_dir_all(dir)?;
        for (i, f) in frames.iter().enumerate().filter(|(_, f)| !f.rgba.is_empty()) {
            let frame = nephele_renderer::Frame { width: f.width, height: f.height, rgba: f.rgba.clone(), depth: vec![] };
            frame.save_png(&dir.join(format!("frame{:04}_pose{}.png", i, f.pose_seq.unwrap_or(0))))?;
        }
    }

    let rendered: Vec<&FrameInfo> = infos.iter().map(|(i, _)| i).filter(|i| !i.reused).collect();
    let mut quality = Vec::new();
    if let (Some(reference), true) = (reference, opts.quality_every > 0 && opts.stereo_baseline.is_none()) {
        let background = background_of(opts.client.mode);
        for f in frames.iter().step_by(opts.quality_every) {
            let Some((_, sent)) = f.pose_seq.and_then(|s| sent_at.get(&s)) else { continue };
            if f.rgba.is_empty() || (f.width, f.height) != (w, h) {
                continue;
            }
            // The same validation (and f32 repair) the master applied to this message.
            let (view, instance) = sent.view((w, h)).map_err(|e| anyhow::anyhow!("{e}"))?;
            let direct = reference(view, instance, background)?;
            let psnr_db = psnr_rgb(&direct.rgba, &f.rgba);
            let key_iou = (opts.client.mode == Mode::Ar).then(|| key_iou(&direct.rgba, &f.rgba));
            quality.push(QualitySample { pose_seq: f.pose_seq.unwrap_or(0), psnr_db, key_iou });
        }
    }

    Ok(ReplayReport {
        trace: trace.name.clone(),
        width: w,
        height: h,
        poses_sent: next,
        frames_decoded: frames.len(),
        frames_unknown_pose: unknown,
        frames_without_pose: without,
        latency_ms: Percentiles::of(&latency),
        info_latency_ms: Percentiles::of(&info_latency),
        fps: if span > 0.0 { (frames.len() - 1) as f64 / span } else { 0.0 },
        bitrate_kbps: if span > 0.0 { bytes as f64 * 8.0 / span / 1e3 } else { 0.0 },
        queue_ms: stat(|i| i.queue_ms),
        render_ms: stat(|i| i.times.render_ms),
        convert_ms: stat(|i| i.times.convert_ms),
        encode_ms: stat(|i| i.times.encode_ms),
        send_ms: stat(|i| i.times.send_ms),
        render_total_ms: stat(|i| i.times.render_total_ms),
        transfer_ms: stat(|i| i.times.transfer_ms),
        compose_ms: stat(|i| i.times.compose_ms),
        ready_ms: stat(|i| i.times.ready_ms),
        transfer_bytes_mean: mean(infos.iter().map(|(i, _)| i.times.transfer_bytes as f64)),
        idr_frames: infos.iter().filter(|(i, _)| i.times.idr).count(),
        frame_gap_ms: Percentiles::of(&frames.windows(2).map(|w| w[1].decoded_at.duration_since(w[0].decoded_at).as_secs_f64() * 1e3).collect::<Vec<_>>()),
        render_ms_per_view: mean(rendered.iter().map(|i| i.times.render_ms / f64::from(i.batch_views.max(1)))),
        mean_batch_views: mean(rendered.iter().map(|i| f64::from(i.batch_views))),
        reused_frames: infos.iter().filter(|(i, _)| i.reused).count(),
        mean_render_scale: mean(infos.iter().map(|(i, _)| f64::from(i.render_scale))),
        quality,
        errors,
        notices,
        decoded_pose_seqs: frames.iter().filter_map(|f| f.pose_seq).collect(),
        decoded_at_ms: frames.iter().map(|f| f.decoded_at.saturating_duration_since(start).as_secs_f64() * 1e3).collect(),
    })
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// PSNR over the RGB channels of two RGBA8 images of the same size, dB (∞ if identical).
/// Both eyes of `centre`, side by side in a `width`×`height` frame, `baseline` apart.
fn stereo_pose(centre: &PoseMessage, width: u32, height: u32, baseline: f32) -> MultiViewPose {
    let eye_w = width / 2;
    // The trace camera's focal length over √2: the object covers half as many pixels in
    // each eye as in the mono frame, so both eyes together render the same rays *and* the
    // same hits as one mono view of the same total pixels — what is left is the cost of
    // two views in one task. (At the mono focal length each eye would hold as much of the
    // object as the whole mono frame: twice the work.)
    let c = centre.intrinsics;
    let f = std::f32::consts::FRAC_1_SQRT_2;
    let k = Intrinsics { fx: c.fx * f, fy: c.fy * f, cx: 0.5 * eye_w as f32, cy: 0.5 * height as f32, width: eye_w, height };
    let clip_from_camera = projection_from_intrinsics(&k, 0.01, 1000.0);
    let views = [(-0.5f32, 0), (0.5, eye_w)]
        .into_iter()
        .map(|(side, x)| PoseView {
            world_from_camera: centre.world_from_camera * Mat4::from_translation(glam::Vec3::new(side * baseline, 0.0, 0.0)),
            clip_from_camera,
            viewport: Viewport { x, y: 0, width: eye_w, height },
        })
        .collect();
    MultiViewPose { seq: centre.seq, t_client_ms: centre.t_client_ms, frame_width: width, frame_height: height, views, world_from_anchor: centre.world_from_anchor, predicted: None }
}

/// The AR page's key, in Rust: how strongly a pixel is the green screen, 0..1. Green
/// dominance `g − max(r, b)` is 1 for pure green and ≤ 0 for anything not green-tinted.
pub fn green_key(rgb: [u8; 3]) -> f32 {
    let [r, g, b] = rgb.map(|c| f32::from(c) / 255.0);
    ((g - r.max(b)) / 0.75).clamp(0.0, 1.0)
}

/// IoU of "object" masks: the renderer's alpha ≥ ½ versus a keyed decoded pixel with
/// key ≤ ½ (a pixel is object when it is less than half green screen).
pub fn key_iou(direct_rgba: &[u8], decoded_rgba: &[u8]) -> f64 {
    let (mut inter, mut union) = (0u64, 0u64);
    for (d, v) in direct_rgba.chunks_exact(4).zip(decoded_rgba.chunks_exact(4)) {
        let truth = d[3] >= 128;
        let keyed = green_key([v[0], v[1], v[2]]) <= 0.5;
        inter += u64::from(truth && keyed);
        union += u64::from(truth || keyed);
    }
    if union == 0 { 1.0 } else { inter as f64 / union as f64 }
}
