//! H.264 encoder stage of the master node: one rendered RGBA8 frame in, one Annex-B access
//! unit out, ready for `TrackLocalStaticSample::write_sample`.
//!
//! Pipeline (docs/architecture.md §5 "Encoder"):
//! 1. RGBA8 → I420 with the `yuv` crate, BT.601 limited range — the matrix and range the
//!    OpenH264 decoder (`write_rgba8`) assumes and that we also signal in the SPS VUI.
//!    Odd sizes are padded to even (last column/row replicated): I420 and OpenH264 need
//!    even sizes, so the coded size is the padded size. The planes are reused every frame.
//! 2. OpenH264, tuned for interactive streaming rather than its defaults: constrained
//!    baseline (IPPP, no B-frames, no lookahead, so a frame leaves as soon as it is
//!    encoded), `CameraVideoRealTime`, rate control `Bitrate`, frame skipping OFF (an
//!    unchanged view must still produce a frame: the client measures latency per pose),
//!    max frame rate set, and a long intra period only as a safety net — IDRs are sent on
//!    demand ([`FrameEncoder::force_idr`] on join and PLI/FIR); OpenH264 puts SPS/PPS in
//!    front of every IDR, so any IDR is a clean entry point. Complexity `Low`: ~15% less
//!    encode time than `Medium` for ~0.1 dB PSNR here. With skipping off OpenH264 warns that
//!    it cannot hold the bitrate strictly; a hard frame overshoots instead of being dropped.
//! 3. The pose sequence the frame answers is carried in an SEI `user_data_unregistered`
//!    NAL (type 6, payload type 5: our 16-byte UUID, then the sequence as big-endian u64),
//!    placed after SPS/PPS and before the first slice, with emulation prevention bytes.
//!    RTP payloaders pass SEI through, so the client can compute pose-to-photon latency on
//!    its own clock ([`crate::wire::sei`]).

use std::time::Instant;

use openh264::encoder::{
    BitRate, Complexity, Encoder, EncoderConfig as H264Config, FrameRate, FrameType,
    IntraFramePeriod, Profile, RateControlMode, UsageType, VuiConfig,
};
use openh264::formats::YUVSource;
use openh264::{OpenH264API, Timestamp};
use yuv::{
    BufferStoreMut, YuvConversionMode, YuvPlanarImageMut, YuvRange, YuvStandardMatrix,
    rgba_to_yuv420,
};

use nephele_wire::sei::write_pose_sei;

#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("invalid encoder config: {0}")]
    InvalidConfig(String),
    #[error("frame size {actual:?} differs from the configured {expected:?}")]
    FrameSize {
        expected: (u32, u32),
        actual: (u32, u32),
    },
    #[error("RGBA buffer has {actual} bytes, expected {expected}")]
    BufferSize { expected: usize, actual: usize },
    #[error("RGBA to I420 conversion failed: {0}")]
    Convert(#[from] yuv::YuvError),
    #[error("OpenH264: {0}")]
    OpenH264(#[from] openh264::Error),
    #[error("encoder produced no picture (frame type {0})")]
    NoPicture(String),
}

/// OpenH264 encodes at most this many slice partitions at once.
pub const MAX_ENCODER_THREADS: u16 = 4;

/// Encoder threads by default: one more than the machine's cores (at most
/// [`MAX_ENCODER_THREADS`]). OpenH264 gives each thread an equal band of macroblock rows; an
/// object's rows cost more than the background's, so with one band per core one core idles
/// while the other finishes. With a band more than the cores the spare band fills that gap:
/// on 2 cores, lego, 3 threads took 0.54–0.92 of the time of 2 at 640×480 and 0.64–0.85 at
/// 1280×720 (seven runs), the same bytes and PSNR (`nephele bench encode --threads 2,3,4`).
pub fn default_encoder_threads() -> u16 {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores + 1).min(usize::from(MAX_ENCODER_THREADS)) as u16
}

/// Checks an encoder thread count: 1..=[`MAX_ENCODER_THREADS`].
pub fn check_encoder_threads(threads: u16) -> Result<(), String> {
    (1..=MAX_ENCODER_THREADS).contains(&threads).then_some(()).ok_or_else(|| format!("{threads} encoder threads: OpenH264 takes 1..={MAX_ENCODER_THREADS}"))
}

/// Largest slice NAL, bytes: fits one RTP packet (MTU 1500 minus IP/UDP/SRTP/RTP headers).
pub const MAX_SLICE_BYTES: u32 = 1200;

/// Bits per pixel per frame a stream gets by default (0.15: 2.3 Mbit/s at 640×480, 50 fps).
pub const DEFAULT_BITS_PER_PIXEL: f64 = 0.15;

/// Checks a `--bits-per-pixel` setting: 0.01..=10.
pub fn check_bits_per_pixel(bits_per_pixel: f64) -> Result<(), String> {
    (0.01..=10.0).contains(&bits_per_pixel).then_some(()).ok_or_else(|| format!("--bits-per-pixel {bits_per_pixel} should be in 0.01..=10"))
}

/// What to encode. `width`/`height` are the rendered (unpadded) size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncoderConfig {
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub bitrate_bps: u32,
    /// Safety-net IDR period; IDRs normally come from [`FrameEncoder::force_idr`].
    pub intra_period_frames: u32,
    /// OpenH264's threads, 1..=[`MAX_ENCODER_THREADS`] ([`default_encoder_threads`]).
    pub threads: u16,
}

impl EncoderConfig {
    /// [`DEFAULT_BITS_PER_PIXEL`] per frame, clamped to 300 kbps..20 Mbps; an IDR every 10 s.
    pub fn new(width: u32, height: u32, fps: u32) -> Self {
        Self::with_bits_per_pixel(width, height, fps, DEFAULT_BITS_PER_PIXEL)
    }

    /// `bits_per_pixel` per frame (the quality/bandwidth knob), clamped to 300 kbps..20 Mbps.
    pub fn with_bits_per_pixel(width: u32, height: u32, fps: u32, bits_per_pixel: f64) -> Self {
        let bits = bits_per_pixel * f64::from(width) * f64::from(height) * f64::from(fps);
        Self {
            width,
            height,
            fps,
            bitrate_bps: bits.clamp(300_000.0, 20_000_000.0) as u32,
            intra_period_frames: fps.saturating_mul(10),
            threads: default_encoder_threads(),
        }
    }

    /// The coded size: rendered size rounded up to even.
    pub fn padded_size(&self) -> (u32, u32) {
        (
            self.width.next_multiple_of(2),
            self.height.next_multiple_of(2),
        )
    }
}

/// One access unit: `[SPS PPS] SEI slice…`, Annex-B start codes.
#[derive(Debug, Clone)]
pub struct EncodedFrame {
    pub annex_b: Vec<u8>,
    pub is_idr: bool,
    pub convert_ms: f64,
    pub encode_ms: f64,
}

/// I420 planes at the padded size, tightly packed; fed to OpenH264 as a `YUVSource`.
struct I420 {
    y: Vec<u8>,
    u: Vec<u8>,
    v: Vec<u8>,
    width: usize,
    height: usize,
}

impl YUVSource for I420 {
    fn dimensions(&self) -> (usize, usize) {
        (self.width, self.height)
    }
    fn strides(&self) -> (usize, usize, usize) {
        (self.width, self.width / 2, self.width / 2)
    }
    fn y(&self) -> &[u8] {
        &self.y
    }
    fn u(&self) -> &[u8] {
        &self.u
    }
    fn v(&self) -> &[u8] {
        &self.v
    }
}

pub struct FrameEncoder {
    cfg: EncoderConfig,
    encoder: Encoder,
    planes: I420,
    frames_encoded: u64,
    idr_pending: bool,
    /// The frames' real rate: the last frame's time, the mean interval (ms, a running
    /// average), and the rate the encoder was last told ([`Self::follow_frame_rate`]).
    last_t_ms: Option<u64>,
    interval_ms: Option<f64>,
    told_hz: f64,
}

/// OpenH264's `ENCODER_OPTION_FRAME_RATE` (`codec_app_def.h`): a float, frames per second.
const ENCODER_OPTION_FRAME_RATE: i32 = 4;

/// The share by which the real frame rate must differ from the one the encoder was told
/// before it is told again.
const FRAME_RATE_SLACK: f64 = 0.1;

impl FrameEncoder {
    pub fn new(cfg: EncoderConfig) -> Result<Self, EncodeError> {
        let (padded_w, padded_h) = cfg.padded_size();
        nephele_limits::check_stream_size(cfg.width, cfg.height)
            .and_then(|()| nephele_limits::check_fps(cfg.fps))
            .map_err(|e| EncodeError::InvalidConfig(e.to_string()))?;
        if cfg.bitrate_bps == 0 {
            return Err(EncodeError::InvalidConfig("bitrate must be positive".into()));
        }
        check_encoder_threads(cfg.threads).map_err(EncodeError::InvalidConfig)?;
        let h264 = H264Config::new()
            .usage_type(UsageType::CameraVideoRealTime)
            .profile(Profile::Baseline)
            // Budget by the frames' real times: a render-bound session sends fewer frames than
            // the nominal rate, and each may then spend more bits (+1–2 dB PSNR measured on the
            // fast "shake" trace versus RC_BITRATE_MODE).
            .rate_control_mode(RateControlMode::Timestamp)
            .bitrate(BitRate::from_bps(cfg.bitrate_bps))
            .max_frame_rate(FrameRate::from_hz(cfg.fps as f32))
            .skip_frames(false)
            .intra_frame_period(IntraFramePeriod::from_num_frames(cfg.intra_period_frames))
            .complexity(Complexity::Low)
            // Slices of at most one RTP payload keep each loss to one slice and let OpenH264
            // encode bands of them on several threads (one more than the cores by default:
            // `default_encoder_threads`).
            .num_threads(cfg.threads)
            .max_slice_len(MAX_SLICE_BYTES)
            // Background detection off: 5% less encode time on lego at 720p, the same
            // bytes (scene-change detection and adaptive quantization off gained nothing
            // more; `bench encode`, same run). Also measured at 720p on lego, encoders
            // side by side (initialised directly with each setting): slices of fixed count
            // (2 or 4) instead of ≤ 1 RTP packet, 0.97–1.03× the time; deblocking off,
            // 0.88× for −0.37 dB. Neither is taken: the first loses per-packet slices for
            // nothing, the second costs more picture than it saves time.
            .background_detection(false)
            .vui(VuiConfig::bt601());
        let encoder = Encoder::with_api_config(OpenH264API::from_source(), h264)?;
        let (w, h) = (padded_w as usize, padded_h as usize);
        let (y, u, v) = (vec![0; w * h], vec![128; w * h / 4], vec![128; w * h / 4]);
        let planes = I420 {
            y,
            u,
            v,
            width: w,
            height: h,
        };
        Ok(Self {
            cfg,
            encoder,
            planes,
            frames_encoded: 0,
            idr_pending: false,
            last_t_ms: None,
            interval_ms: None,
            told_hz: f64::from(cfg.fps),
        })
    }

    /// Tells OpenH264 the rate frames really come at (at most the configured one, a running
    /// average of their intervals), so that its rate control gives each frame its share of
    /// the bitrate. Told only the configured rate it budgets for frames that never come, even
    /// with timestamps: lego at 640×480 and render scale 1 (19–30 fps) spent 1.36–2.07 of its
    /// 2.3 Mbit/s and reached 35.22–35.61 dB against a direct render; told the real rate,
    /// 2.36–2.47 Mbit/s and 35.99–36.18 dB, at the same encode time (`bench stream`, runs
    /// alternating). At the auto scale (~49 fps) the PSNR is the same either way.
    #[allow(unsafe_code)] // one option set through OpenH264's own API
    fn follow_frame_rate(&mut self, t_ms: u64) {
        if let Some(last) = self.last_t_ms {
            let dt = t_ms.saturating_sub(last).max(1) as f64;
            self.interval_ms = Some(self.interval_ms.map_or(dt, |m| 0.875 * m + 0.125 * dt));
        }
        self.last_t_ms = Some(t_ms);
        let Some(interval) = self.interval_ms else { return };
        let hz = (1000.0 / interval).clamp(1.0, f64::from(self.cfg.fps));
        if self.frames_encoded == 0 || (hz - self.told_hz).abs() <= FRAME_RATE_SLACK * self.told_hz {
            return;
        }
        let mut option = hz as f32;
        // SAFETY: the encoder is initialised (a frame was encoded); the option takes a
        // pointer to an f32 for the duration of the call and changes only the frame rate
        // that its rate control budgets by.
        let status = unsafe { self.encoder.raw_api().set_option(ENCODER_OPTION_FRAME_RATE, (&raw mut option).cast()) };
        if status == 0 {
            self.told_hz = hz;
        } else {
            tracing::debug!(status, hz, "OpenH264 did not take a frame rate");
        }
    }

    pub fn config(&self) -> &EncoderConfig {
        &self.cfg
    }

    /// Make the next frame an IDR (with SPS/PPS): on join and on PLI/FIR.
    pub fn force_idr(&mut self) {
        self.idr_pending = true;
    }

    /// Encode one tightly packed RGBA8 frame of the configured size, tagged with `pose_seq`,
    /// timed as if frames came exactly at the configured rate.
    pub fn encode(&mut self, rgba: &[u8], width: u32, height: u32, pose_seq: u64) -> Result<EncodedFrame, EncodeError> {
        let t_ms = self.frames_encoded * 1000 / u64::from(self.cfg.fps);
        self.encode_at(rgba, width, height, pose_seq, t_ms)
    }

    /// [`Self::encode`] with the frame's real capture time in ms (from any fixed origin), so
    /// rate control spends the bitrate over the frames actually sent, not the nominal rate.
    pub fn encode_at(
        &mut self,
        rgba: &[u8],
        width: u32,
        height: u32,
        pose_seq: u64,
        t_ms: u64,
    ) -> Result<EncodedFrame, EncodeError> {
        let _span = tracing::trace_span!("encode", pose_seq).entered();
        let (cfg, actual) = (self.cfg, rgba.len());
        if (width, height) != (cfg.width, cfg.height) {
            let expected = (cfg.width, cfg.height);
            return Err(EncodeError::FrameSize {
                expected,
                actual: (width, height),
            });
        }
        let expected = width as usize * height as usize * 4;
        if actual != expected {
            return Err(EncodeError::BufferSize { expected, actual });
        }

        let t_convert = Instant::now();
        self.convert(rgba)?;
        let convert_ms = t_convert.elapsed().as_secs_f64() * 1e3;

        self.follow_frame_rate(t_ms);
        let t_encode = Instant::now();
        // Before the first frame OpenH264 is not initialised yet, and that frame is an IDR anyway.
        if std::mem::take(&mut self.idr_pending) && self.frames_encoded > 0 {
            self.encoder.force_intra_frame();
        }
        let timestamp = Timestamp::from_millis(t_ms);
        let bitstream = self.encoder.encode_at(&self.planes, timestamp)?;
        let frame_type = bitstream.frame_type();

        let mut annex_b = Vec::new();
        let mut sei_written = false;
        // Layers: SPS/PPS (IDR only), then the video layer with the slice NAL(s).
        for layer in (0..bitstream.num_layers()).filter_map(|i| bitstream.layer(i)) {
            if layer.is_video() && layer.nal_count() > 0 && !sei_written {
                write_pose_sei(&mut annex_b, pose_seq);
                sei_written = true;
            }
            (0..layer.nal_count())
                .filter_map(|i| layer.nal_unit(i))
                .for_each(|nal| annex_b.extend_from_slice(nal));
        }
        let encode_ms = t_encode.elapsed().as_secs_f64() * 1e3;
        if !sei_written {
            return Err(EncodeError::NoPicture(format!("{frame_type:?}")));
        }
        self.frames_encoded += 1;
        let is_idr = frame_type == FrameType::IDR;
        tracing::trace!(
            is_idr,
            bytes = annex_b.len(),
            convert_ms,
            encode_ms,
            "encoded frame"
        );
        Ok(EncodedFrame {
            annex_b,
            is_idr,
            convert_ms,
            encode_ms,
        })
    }

    /// RGBA → I420 into the reused planes, then replicate the last column/row into the padding.
    fn convert(&mut self, rgba: &[u8]) -> Result<(), EncodeError> {
        let (w, h) = (self.cfg.width as usize, self.cfg.height as usize);
        let p = &mut self.planes;
        let (pw, ph) = (p.width, p.height);
        let mut image = YuvPlanarImageMut {
            y_plane: BufferStoreMut::Borrowed(&mut p.y[..pw * h]), // odd h: yuv wants exactly h rows
            y_stride: pw as u32,
            u_plane: BufferStoreMut::Borrowed(&mut p.u),
            u_stride: pw as u32 / 2,
            v_plane: BufferStoreMut::Borrowed(&mut p.v),
            v_stride: pw as u32 / 2,
            width: w as u32,
            height: h as u32,
        };
        let (range, matrix) = (YuvRange::Limited, YuvStandardMatrix::Bt601);
        rgba_to_yuv420(
            &mut image,
            rgba,
            w as u32 * 4,
            range,
            matrix,
            YuvConversionMode::Balanced,
        )?;
        // Chroma planes already cover ceil(w/2) x ceil(h/2) = the padded chroma size.
        if w < pw {
            for row in p.y.chunks_exact_mut(pw).take(h) {
                row[w] = row[w - 1];
            }
        }
        if h < ph {
            p.y.copy_within((h - 1) * pw..h * pw, h * pw);
        }
        Ok(())
    }
}

/// Bilinear resize of RGBA8 from `sw`×`sh` to `dw`×`dh`, pixel centres aligned, in fixed
/// point (weights in 1/1024: within 0.75 of a level of exact). Each source row a frame needs
/// is blended across once, and each output row blends two of those down: integer arithmetic
/// over whole rows that the compiler vectorises, 8 lanes wide where the CPU has AVX2
/// (0.46–0.67 of the baseline build's time). 640×480 from 320×240 takes 0.11–0.13 of the
/// time of blending every output pixel from four with a `round` call per channel, which took
/// 13–15 ms while streaming: the auto render scale's frames paid that on top of their render.
pub fn upscale_bilinear(src: &[u8], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<u8> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        #[target_feature(enable = "avx2")]
        fn avx2(src: &[u8], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<u8> {
            upscale_rows(src, sw, sh, dw, dh)
        }
        #[allow(unsafe_code)]
        // SAFETY: the CPU has AVX2 (detected above); the body is safe code.
        return unsafe { avx2(src, sw, sh, dw, dh) };
    }
    upscale_rows(src, sw, sh, dw, dh)
}

/// [`upscale_bilinear`]'s body, compiled for the baseline and, inlined, for AVX2 (its 32-bit
/// products 8 at a time): the same integers either way.
#[inline(always)]
fn upscale_rows(src: &[u8], sw: u32, sh: u32, dw: u32, dh: u32) -> Vec<u8> {
    const ONE: u32 = 1024;
    let (sw, sh, dw, dh) = (sw as usize, sh as usize, dw as usize, dh as usize);
    if sw == 0 || sh == 0 || dw == 0 || dh == 0 {
        return vec![0; dw * dh * 4];
    }
    // Source pixels and the second one's weight for each destination column/row.
    let taps = |d: usize, s: usize| -> Vec<(usize, usize, u32)> {
        (0..d)
            .map(|i| {
                let x = ((i as f32 + 0.5) * s as f32 / d as f32 - 0.5).clamp(0.0, (s - 1) as f32);
                let x0 = x as usize;
                (x0, (x0 + 1).min(s - 1), ((x - x0 as f32) * ONE as f32).round() as u32)
            })
            .collect()
    };
    let (cols, rows) = (taps(dw, sw), taps(dh, sh));
    // Source row `y` blended across to the output's columns, × ONE.
    let across = |y: usize, out: &mut [u32]| {
        let row = &src[y * sw * 4..(y + 1) * sw * 4];
        for (px, &(x0, x1, w)) in out.chunks_exact_mut(4).zip(&cols) {
            for c in 0..4 {
                px[c] = u32::from(row[x0 * 4 + c]) * (ONE - w) + u32::from(row[x1 * 4 + c]) * w;
            }
        }
    };
    let mut out = vec![0u8; dw * dh * 4];
    let (mut top, mut bottom) = ((usize::MAX, vec![0u32; dw * 4]), (usize::MAX, vec![0u32; dw * 4]));
    for (row, &(y0, y1, w)) in out.chunks_exact_mut(dw * 4).zip(&rows) {
        if top.0 != y0 {
            if bottom.0 == y0 {
                std::mem::swap(&mut top, &mut bottom);
            } else {
                across(y0, &mut top.1);
                top.0 = y0;
            }
        }
        if bottom.0 != y1 {
            across(y1, &mut bottom.1);
            bottom.0 = y1;
        }
        // At most 255 · ONE², rounded: fits u32 and then u8.
        for ((o, &a), &b) in row.iter_mut().zip(&top.1).zip(&bottom.1) {
            *o = ((a * (ONE - w) + b * w + ONE * ONE / 2) / (ONE * ONE)) as u8;
        }
    }
    out
}

/// A moving, renderer-like test image: smooth gradients, a sinusoidal texture and a hard-edged box.
pub fn test_pattern(width: u32, height: u32, frame_index: u32, rgba: &mut Vec<u8>) {
    let (w, h, t) = (width as usize, height as usize, frame_index as f32);
    rgba.resize(w * h * 4, 255);
    let box_x = (frame_index as usize * 3) % w.max(1);
    for (i, px) in rgba.chunks_exact_mut(4).enumerate() {
        let (x, y) = ((i % w) as f32, (i / w) as f32);
        let texture = ((x + 2.0 * t) / 9.0).sin() * ((y + t) / 13.0).sin();
        let in_box = (i % w).wrapping_sub(box_x) < w / 6 && (i / w).wrapping_sub(h / 3) < h / 4;
        let (r, g) = if in_box {
            (230, 40)
        } else {
            ((255.0 * x / w as f32) as u8, (255.0 * y / h as f32) as u8)
        };
        px.copy_from_slice(&[r, g, (128.0 + 90.0 * texture) as u8, 255]);
    }
}

#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct BenchResult {
    pub width: u32,
    pub height: u32,
    pub frames: u32,
    pub fps: u32,
    pub bitrate_bps: u32,
    pub convert_ms_p50: f64,
    pub convert_ms_p99: f64,
    pub encode_ms_p50: f64,
    pub encode_ms_p99: f64,
    /// Mean over all frames, including the first (IDR).
    pub bytes_per_frame: f64,
    pub idr_bytes: usize,
    /// Mean RGB PSNR of the decoded frames against the frames encoded, dB.
    pub psnr_db: f64,
}

/// Encode `frames` at 50 fps settings, `bits_per_pixel` and `threads` (each `width × height` RGBA; the
/// first is an IDR), decode them again (OpenH264), and report timings, sizes and PSNR.
pub fn bench_encode(width: u32, height: u32, frames: &[Vec<u8>], bits_per_pixel: f64, threads: u16) -> Result<BenchResult, EncodeError> {
    let cfg = EncoderConfig { threads, ..EncoderConfig::with_bits_per_pixel(width, height, 50, bits_per_pixel) };
    let mut encoder = FrameEncoder::new(cfg)?;
    let mut decoder = openh264::decoder::Decoder::new()?;
    let (mut convert, mut encode, mut bytes, mut idr_bytes) = (vec![], vec![], 0usize, 0);
    let (mut psnr_sum, mut decoded_frames, mut full) = (0.0, 0usize, Vec::new());
    for (i, rgba) in frames.iter().enumerate() {
        let frame = encoder.encode(rgba, width, height, i as u64)?;
        convert.push(frame.convert_ms);
        encode.push(frame.encode_ms);
        bytes += frame.annex_b.len();
        if i == 0 {
            idr_bytes = frame.annex_b.len();
        }
        if let Some(yuv) = decoder.decode(&frame.annex_b)? {
            let (dw, dh) = yuv.dimensions();
            full.resize(dw * dh * 4, 0);
            yuv.write_rgba8(&mut full);
            // The coded picture may be padded to even sizes: compare the frame's own pixels.
            let shown: Vec<u8> = full.chunks_exact(dw * 4).take(height as usize).flat_map(|row| &row[..width as usize * 4]).copied().collect();
            psnr_sum += nephele_renderer::render::psnr_rgb(&shown, rgba).min(99.0);
            decoded_frames += 1;
        }
    }
    let pct = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v.get(((v.len().max(1) - 1) as f64 * q).round() as usize).copied().unwrap_or(0.0)
    };
    Ok(BenchResult {
        width,
        height,
        frames: frames.len() as u32,
        fps: cfg.fps,
        bitrate_bps: cfg.bitrate_bps,
        convert_ms_p50: pct(&mut convert, 0.5),
        convert_ms_p99: pct(&mut convert, 0.99),
        encode_ms_p50: pct(&mut encode, 0.5),
        encode_ms_p99: pct(&mut encode, 0.99),
        bytes_per_frame: bytes as f64 / frames.len().max(1) as f64,
        idr_bytes,
        psnr_db: psnr_sum / decoded_frames.max(1) as f64,
    })
}

/// `frames` frames of the moving [`test_pattern`].
pub fn pattern_frames(width: u32, height: u32, frames: u32) -> Vec<Vec<u8>> {
    (0..frames.max(1))
        .map(|i| {
            let mut rgba = Vec::new();
            test_pattern(width, height, i, &mut rgba);
            rgba
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::{upscale_bilinear, upscale_rows};

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
        // Empty sizes give an empty or black frame, not a panic.
        assert!(upscale_bilinear(&src, 2, 1, 0, 3).is_empty());
        assert_eq!(upscale_bilinear(&[], 0, 0, 2, 1), vec![0; 8]);
    }

    /// The fixed-point resize is within 0.75 of a level of exact bilinear interpolation (f64, the
    /// same pixel-centre alignment) on noise, for up- and downscales, odd sizes and a single
    /// source pixel.
    #[test]
    fn fixed_point_upscaling_stays_near_exact_bilinear() {
        let mut seed = 14u32;
        let mut noise = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 24) as u8
        };
        for (sw, sh, dw, dh) in [(320, 240, 640, 480), (97, 31, 250, 77), (1, 1, 5, 3), (64, 48, 40, 30), (33, 17, 33, 17)] {
            let src: Vec<u8> = (0..sw * sh * 4).map(|_| noise()).collect();
            let out = upscale_bilinear(&src, sw as u32, sh as u32, dw as u32, dh as u32);
            let at = |d: usize, s: usize, i: usize| ((i as f64 + 0.5) * s as f64 / d as f64 - 0.5).clamp(0.0, (s - 1) as f64);
            let mut worst = 0.0f64;
            for y in 0..dh {
                let (fy, gy) = (at(dh, sh, y), at(dh, sh, y).floor() as usize);
                let (y1, wy) = ((gy + 1).min(sh - 1), fy - gy as f64);
                for x in 0..dw {
                    let (fx, gx) = (at(dw, sw, x), at(dw, sw, x).floor() as usize);
                    let (x1, wx) = ((gx + 1).min(sw - 1), fx - gx as f64);
                    for c in 0..4 {
                        let v = |xx: usize, yy: usize| f64::from(src[(yy * sw + xx) * 4 + c]);
                        let exact = (v(gx, gy) * (1.0 - wx) + v(x1, gy) * wx) * (1.0 - wy) + (v(gx, y1) * (1.0 - wx) + v(x1, y1) * wx) * wy;
                        worst = worst.max((f64::from(out[(y * dw + x) * 4 + c]) - exact).abs());
                    }
                }
            }
            assert!(worst <= 0.75, "{sw}x{sh} → {dw}x{dh}: {worst} levels off exact bilinear");
            assert_eq!(upscale_rows(&src, sw as u32, sh as u32, dw as u32, dh as u32), out, "the baseline build's integers");
        }
    }
}
