//! The pose-sequence SEI: how an H.264 access unit says which pose it answers.
//!
//! An SEI `user_data_unregistered` NAL (type 6, payload type 5): our 16-byte UUID
//! ("NEPHELE:POSE-SEQ" in ASCII), then the pose sequence number as a big-endian u64, with
//! emulation prevention bytes. The master's encoder writes it after SPS/PPS and before the
//! first slice; RTP payloaders pass SEI through, so any client can match a decoded picture to
//! the pose it sent and measure pose-to-photon latency on its own clock.

/// UUID of our SEI `user_data_unregistered` message ("NEPHELE:POSE-SEQ" in ASCII).
pub const POSE_SEI_UUID: [u8; 16] = *b"NEPHELE:POSE-SEQ";

const NAL_SEI: u8 = 6;
const SEI_USER_DATA_UNREGISTERED: u8 = 5;

fn nal_type(nal: &[u8]) -> u8 {
    nal.first().map_or(0, |b| b & 0x1f)
}

/// Append the pose SEI NAL (start code, header, escaped RBSP) to `out`.
pub fn write_pose_sei(out: &mut Vec<u8>, pose_seq: u64) {
    let mut rbsp = Vec::with_capacity(27);
    rbsp.push(SEI_USER_DATA_UNREGISTERED); // payload type
    rbsp.push(24); // payload size: UUID + u64
    rbsp.extend_from_slice(&POSE_SEI_UUID);
    rbsp.extend_from_slice(&pose_seq.to_be_bytes());
    rbsp.push(0x80); // rbsp_trailing_bits
    out.extend_from_slice(&[0, 0, 0, 1, NAL_SEI]);
    let mut zeros = 0;
    for &b in &rbsp {
        if zeros >= 2 && b <= 3 {
            out.push(3); // emulation_prevention_three_byte
            zeros = 0;
        }
        out.push(b);
        zeros = if b == 0 { zeros + 1 } else { 0 };
    }
}

/// NAL units of an Annex-B stream, without start codes (first byte is the NAL header).
pub fn split_nals(annex_b: &[u8]) -> impl Iterator<Item = &[u8]> {
    let mut starts = annex_b
        .windows(3)
        .enumerate()
        .filter(|(_, w)| *w == [0, 0, 1])
        .map(|(i, _)| i)
        .peekable();
    std::iter::from_fn(move || {
        let begin = starts.next()? + 3;
        let end = starts.peek().copied().unwrap_or(annex_b.len());
        let mut nal = &annex_b[begin..end];
        while let [rest @ .., 0] = nal {
            nal = rest; // trailing_zero_8bits / leading zero of a 4-byte start code
        }
        Some(nal)
    })
}

/// The pose sequence carried in our SEI (as written by [`write_pose_sei`]), if present.
pub fn parse_pose_seq(annex_b: &[u8]) -> Option<u64> {
    let header = [SEI_USER_DATA_UNREGISTERED, 24];
    split_nals(annex_b)
        .filter(|n| nal_type(n) == NAL_SEI)
        .find_map(|nal| {
            let rbsp = unescape(&nal[1..]);
            let payload = rbsp.strip_prefix(&header)?.strip_prefix(&POSE_SEI_UUID)?;
            Some(u64::from_be_bytes(payload.get(..8)?.try_into().ok()?))
        })
}

/// Remove emulation prevention bytes (00 00 03 → 00 00).
fn unescape(ebsp: &[u8]) -> Vec<u8> {
    let mut rbsp = Vec::with_capacity(ebsp.len());
    let mut zeros = 0;
    for &b in ebsp {
        if zeros >= 2 && b == 3 {
            zeros = 0;
            continue;
        }
        rbsp.push(b);
        zeros = if b == 0 { zeros + 1 } else { 0 };
    }
    rbsp
}

