//! Encoder stage: RGBA → I420 → OpenH264, decoded back with OpenH264's decoder.

use nephele_master::encoder::{EncodeError, EncodedFrame, EncoderConfig, FrameEncoder, MAX_ENCODER_THREADS, bench_encode, default_encoder_threads, pattern_frames, test_pattern};
use nephele_wire::sei::{parse_pose_seq, split_nals};
use openh264::decoder::Decoder;
use openh264::formats::YUVSource;
use yuv::{YuvPlanarImage, YuvRange, YuvStandardMatrix, yuv420_to_rgba};

const SPS: u8 = 7;
const PPS: u8 = 8;
const SEI: u8 = 6;
const IDR: u8 = 5;
const SLICE: u8 = 1;

fn nal_types(au: &[u8]) -> Vec<u8> {
    split_nals(au).map(|n| n[0] & 0x1f).collect()
}

/// `head` NALs, then one or more slices of type `slice`, each within one RTP payload.
fn assert_layout(frame: &EncodedFrame, head: &[u8], slice: u8, what: &str) {
    let types = nal_types(&frame.annex_b);
    assert!(types.len() > head.len() && types.starts_with(head), "{what} access unit layout: {types:?}");
    assert!(types[head.len()..].iter().all(|&t| t == slice), "{what} access unit layout: {types:?}");
    let largest = split_nals(&frame.annex_b).map(<[u8]>::len).max().unwrap();
    assert!(largest <= nephele_master::encoder::MAX_SLICE_BYTES as usize, "a {largest}-byte NAL exceeds the slice limit");
}

fn assert_idr(frame: &EncodedFrame) {
    assert!(frame.is_idr);
    assert_layout(frame, &[SPS, PPS, SEI], IDR, "IDR");
}

fn assert_p(frame: &EncodedFrame) {
    assert!(!frame.is_idr);
    assert_layout(frame, &[SEI], SLICE, "P");
}

/// Decode one access unit and convert it to RGBA (BT.601 limited, as the encoder converts).
fn decode_rgba(decoder: &mut Decoder, au: &[u8]) -> (Vec<u8>, usize, usize) {
    let yuv = decoder
        .decode(au)
        .expect("decode")
        .expect("a picture per access unit");
    let (w, h) = yuv.dimensions();
    let (ys, us, vs) = yuv.strides();
    let image = YuvPlanarImage {
        y_plane: yuv.y(),
        y_stride: ys as u32,
        u_plane: yuv.u(),
        u_stride: us as u32,
        v_plane: yuv.v(),
        v_stride: vs as u32,
        width: w as u32,
        height: h as u32,
    };
    let mut rgba = vec![0; w * h * 4];
    yuv420_to_rgba(
        &image,
        &mut rgba,
        w as u32 * 4,
        YuvRange::Limited,
        YuvStandardMatrix::Bt601,
    )
    .unwrap();
    (rgba, w, h)
}

/// PSNR of the RGB channels over the `w`×`h` input region of a decoded frame `decoded_w` wide.
fn psnr_db(input: &[u8], w: usize, h: usize, decoded: &[u8], decoded_w: usize) -> f64 {
    let mut sum_sq = 0.0;
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let d = f64::from(input[(y * w + x) * 4 + c])
                    - f64::from(decoded[(y * decoded_w + x) * 4 + c]);
                sum_sq += d * d;
            }
        }
    }
    let mse = sum_sq / (w * h * 3) as f64;
    10.0 * (255.0 * 255.0 / mse.max(1e-10)).log10()
}

fn check_stream(width: u32, height: u32) {
    let mut encoder = FrameEncoder::new(EncoderConfig::new(width, height, 30)).unwrap();
    let mut decoder = Decoder::new().unwrap();
    let (padded_w, padded_h) = (
        width.next_multiple_of(2) as usize,
        height.next_multiple_of(2) as usize,
    );
    let mut rgba = Vec::new();
    let mut psnrs = vec![];
    for i in 0..40u32 {
        if i == 20 {
            encoder.force_idr();
        }
        test_pattern(width, height, i, &mut rgba);
        let pose_seq = 1_000 + u64::from(i) * 7;
        let frame = encoder.encode(&rgba, width, height, pose_seq).unwrap();
        if i == 0 || i == 20 {
            assert_idr(&frame);
        } else {
            assert_p(&frame);
        }
        assert_eq!(parse_pose_seq(&frame.annex_b), Some(pose_seq), "frame {i}");

        let (decoded, w, h) = decode_rgba(&mut decoder, &frame.annex_b);
        assert_eq!((w, h), (padded_w, padded_h));
        psnrs.push(psnr_db(&rgba, width as usize, height as usize, &decoded, w));
    }
    let min = psnrs.iter().copied().fold(f64::INFINITY, f64::min);
    let mean = psnrs.iter().sum::<f64>() / psnrs.len() as f64;
    println!("{width}x{height}: PSNR min {min:.1} dB, mean {mean:.1} dB");
    assert!(min >= 30.0, "PSNR {min:.1} dB < 30 dB ({psnrs:?})");
}

#[test]
fn even_size_stream_is_idr_then_p_with_pose_and_quality() {
    check_stream(320, 240);
}

#[test]
fn odd_size_is_padded_and_decodes() {
    check_stream(321, 241);
}

#[test]
fn identical_frames_are_not_skipped() {
    let (w, h) = (160, 120);
    let mut encoder = FrameEncoder::new(EncoderConfig::new(w, h, 50)).unwrap();
    let mut decoder = Decoder::new().unwrap();
    let mut rgba = Vec::new();
    test_pattern(w, h, 0, &mut rgba);
    for i in 0..20 {
        let frame = encoder.encode(&rgba, w, h, i).unwrap();
        if i == 0 {
            assert_idr(&frame);
        } else {
            assert_p(&frame);
        }
        assert_eq!(parse_pose_seq(&frame.annex_b), Some(i));
        decode_rgba(&mut decoder, &frame.annex_b);
    }
}

#[test]
fn pose_sei_is_escaped_and_round_trips() {
    let (w, h) = (64, 48);
    let mut encoder = FrameEncoder::new(EncoderConfig::new(w, h, 30)).unwrap();
    let mut decoder = Decoder::new().unwrap();
    let mut rgba = Vec::new();
    test_pattern(w, h, 0, &mut rgba);
    for pose_seq in [
        0,
        1,
        2,
        3,
        0x300,
        0x0003_0000_0000,
        1 << 56,
        u64::MAX - 1,
        u64::MAX,
    ] {
        let frame = encoder.encode(&rgba, w, h, pose_seq).unwrap();
        assert_eq!(parse_pose_seq(&frame.annex_b), Some(pose_seq));
        let sei = split_nals(&frame.annex_b)
            .find(|n| n[0] & 0x1f == SEI)
            .unwrap();
        assert!(
            !sei.windows(3).any(|w| w[0] == 0 && w[1] == 0 && w[2] <= 2),
            "start-code emulation in SEI for {pose_seq:#x}: {sei:02x?}"
        );
        decode_rgba(&mut decoder, &frame.annex_b);
    }
}

#[test]
fn parse_pose_seq_ignores_foreign_data() {
    assert_eq!(parse_pose_seq(&[]), None);
    assert_eq!(parse_pose_seq(&[0, 0, 0, 1, 0x65, 0x88, 0x80]), None);
    // Another user_data_unregistered SEI (different UUID), then a truncated one.
    let mut foreign = vec![0, 0, 0, 1, 6, 5, 24];
    foreign.extend_from_slice(&[0xab; 24]);
    foreign.push(0x80);
    assert_eq!(parse_pose_seq(&foreign), None);
    assert_eq!(parse_pose_seq(&[0, 0, 1, 6, 5, 24, b'N', b'E']), None);
}

#[test]
fn wrong_sizes_are_errors_not_panics() {
    let (w, h) = (321, 241);
    let mut encoder = FrameEncoder::new(EncoderConfig::new(w, h, 30)).unwrap();
    let mut rgba = Vec::new();
    test_pattern(w, h, 0, &mut rgba);
    assert!(matches!(
        encoder.encode(&rgba[..rgba.len() - 4], w, h, 0),
        Err(EncodeError::BufferSize { .. })
    ));
    assert!(matches!(
        encoder.encode(&rgba, w + 1, h, 0),
        Err(EncodeError::FrameSize { .. })
    ));
    let mut other = Vec::new();
    test_pattern(322, 242, 0, &mut other);
    assert!(matches!(
        encoder.encode(&other, 322, 242, 0),
        Err(EncodeError::FrameSize { .. })
    ));
    // The encoder is still usable, and its first real frame is the IDR.
    assert_idr(&encoder.encode(&rgba, w, h, 0).unwrap());

    assert!(matches!(
        FrameEncoder::new(EncoderConfig::new(0, 240, 30)),
        Err(EncodeError::InvalidConfig(_))
    ));
    // The shared stream limits: 3840×2160 landscape, 2160×3840 portrait.
    for (w, h) in [(3842, 240), (3840, 2162), (240, 3842), (2162, 2162)] {
        let err = FrameEncoder::new(EncoderConfig::new(w, h, 30)).err().expect("refused");
        assert!(err.to_string().contains("stream limits"), "{w}x{h}: {err}");
    }
    assert!(matches!(
        FrameEncoder::new(EncoderConfig::new(320, 240, 0)),
        Err(EncodeError::InvalidConfig(_))
    ));
}

#[test]
fn config_bitrate_scales_and_clamps() {
    assert_eq!(EncoderConfig::new(160, 120, 30).bitrate_bps, 300_000);
    assert_eq!(EncoderConfig::new(1280, 720, 50).bitrate_bps, 6_912_000);
    assert_eq!(EncoderConfig::new(3840, 2160, 60).bitrate_bps, 20_000_000);
    assert_eq!(EncoderConfig::new(321, 241, 30).padded_size(), (322, 242));
}

/// Any thread count OpenH264 takes gives a stream that decodes (one band of macroblock rows
/// or several); outside 1..=4, a clear error instead of OpenH264's silent clamp.
#[test]
fn encoder_threads_take_one_to_four() {
    let frames = pattern_frames(320, 240, 6);
    for threads in [1, 2, 3, MAX_ENCODER_THREADS] {
        let r = bench_encode(320, 240, &frames, 0.15, threads).unwrap();
        assert!(r.psnr_db > 30.0 && r.psnr_db < 99.0, "{threads} threads: {} dB", r.psnr_db);
    }
    for threads in [0, MAX_ENCODER_THREADS + 1] {
        let cfg = EncoderConfig { threads, ..EncoderConfig::new(320, 240, 30) };
        let err = FrameEncoder::new(cfg).err().expect("rejected").to_string();
        assert!(err.contains("encoder threads"), "{err}");
    }
    assert!((1..=MAX_ENCODER_THREADS).contains(&default_encoder_threads()));
}

/// Timings for the report: `cargo test --release -p nephele --test encode bench -- --nocapture --test-threads=1`.
#[test]
fn bench_encode_reports_numbers() {
    for (w, h) in [(640, 480), (1280, 720)] {
        let frames = pattern_frames(w, h, 100);
        let [r, low] = [nephele_master::encoder::DEFAULT_BITS_PER_PIXEL, 0.03].map(|bpp| bench_encode(w, h, &frames, bpp, default_encoder_threads()).unwrap());
        for r in [r, low] {
            println!(
                "{w}x{h}@{}fps {} kbps: convert p50 {:.2} ms p99 {:.2} ms | encode p50 {:.2} ms p99 {:.2} ms | {:.0} B/frame, IDR {} B, {:.2} dB",
                r.fps,
                r.bitrate_bps / 1000,
                r.convert_ms_p50,
                r.convert_ms_p99,
                r.encode_ms_p50,
                r.encode_ms_p99,
                r.bytes_per_frame,
                r.idr_bytes,
                r.psnr_db
            );
            assert!(r.bytes_per_frame > 0.0 && r.encode_ms_p50 > 0.0);
        }
        // Every frame decodes, and fewer bits cost quality: the trade the table measures.
        assert!(r.psnr_db > 30.0 && r.psnr_db < 99.0, "{} dB at the default rate", r.psnr_db);
        assert!(low.bytes_per_frame < r.bytes_per_frame && low.psnr_db < r.psnr_db, "{low:?} against {r:?}");
    }
}

#[test]
fn the_largest_stream_frames_encode() {
    // At the edges of nephele_limits: OpenH264 takes 3840×2160 and 2160×3840, and nothing
    // larger (so those are the limits).
    for (w, h) in [(3840, 2160), (2160, 3840)] {
        let mut rgba = Vec::new();
        test_pattern(w, h, 0, &mut rgba);
        let mut encoder = FrameEncoder::new(EncoderConfig::new(w, h, 30)).unwrap();
        let frame = encoder.encode(&rgba, w, h, 7).unwrap();
        assert!(frame.is_idr && parse_pose_seq(&frame.annex_b) == Some(7), "{w}x{h}");
    }
}

/// Frames that come at a fraction of the configured rate (a render-bound session) still get
/// the configured bitrate: the encoder follows their real rate, so each frame gets its share
/// of the bits instead of a share sized for frames that never come.
#[test]
fn slow_frames_get_the_whole_bitrate() {
    let (w, h) = (640, 480);
    let cfg = EncoderConfig { threads: 1, ..EncoderConfig::with_bits_per_pixel(w, h, 50, 0.15) };
    let mut encoder = FrameEncoder::new(cfg).unwrap();
    let frames = pattern_frames(w, h, 120);
    let (interval_ms, warm_up) = (50, 40);
    let mut bytes = 0;
    for (i, rgba) in frames.iter().enumerate() {
        let frame = encoder.encode_at(rgba, w, h, i as u64, i as u64 * interval_ms).unwrap();
        if i >= warm_up {
            bytes += frame.annex_b.len();
        }
    }
    let seconds = (frames.len() - warm_up) as f64 * interval_ms as f64 / 1000.0;
    let spent = bytes as f64 * 8.0 / seconds / f64::from(cfg.bitrate_bps);
    assert!(spent > 0.85, "20 frames a second spent {:.0}% of the bitrate", 100.0 * spent);
}
