//! RTP packets in, whole H.264 access units out, in sequence order, as a receiver on a
//! lossy path needs them.
//!
//! Packets are held by (extended) sequence number, so reordered packets and NACK
//! retransmissions (the `webrtc` crate's NACK generator asks for every missing sequence
//! number every 100 ms; the master's responder resends them with their original numbers)
//! land in their place. An access unit is handed on only when every packet from its first
//! one to its marker is there. A hole that is still open [`Reassembler::new`]'s `wait`
//! after it formed is given up: the picture that lost it cannot be decoded, nor can the
//! P frames after it (one reference frame, IPPP), so everything is dropped until the first
//! packet of an IDR access unit (one that opens with the SPS, as the master's OpenH264
//! writes every IDR) and a picture-loss indication is due. Picture-loss indications are
//! at most one per [`MIN_PLI_INTERVAL`], repeated every [`PLI_RETRY`] while no IDR comes.
//! At the start of a stream the reassembler waits for the join's IDR the same way, asking
//! for one only if it has not begun within [`FIRST_IDR_GRACE`].

use std::{
    collections::BTreeMap,
    sync::atomic::{AtomicU64, Ordering},
    time::{Duration, Instant},
};

use bytes::Bytes;
use webrtc::rtp::{codecs::h264::H264Packet, packetizer::Depacketizer};

/// Two picture-loss indications are at least this far apart.
pub const MIN_PLI_INTERVAL: Duration = Duration::from_millis(200);
/// While waiting for an IDR, the picture-loss indication is repeated this often.
pub const PLI_RETRY: Duration = Duration::from_millis(300);
/// How long the first packets may come without the join's IDR before one is asked for.
pub const FIRST_IDR_GRACE: Duration = Duration::from_secs(1);
/// How long a hole may wait for a retransmission by default: two NACK rounds and change.
pub const DEFAULT_WAIT: Duration = Duration::from_millis(250);
/// Packets held at most (a hole that old is given up whatever its age).
const MAX_HELD: usize = 4096;

/// Counters of one receiver, shared with whoever wants to read them.
#[derive(Debug, Default)]
pub struct ReceiveStats {
    packets: AtomicU64,
    late: AtomicU64,
    duplicates: AtomicU64,
    stale: AtomicU64,
    lost: AtomicU64,
    gave_up: AtomicU64,
    units: AtomicU64,
    idrs: AtomicU64,
    units_dropped: AtomicU64,
    decode_errors: AtomicU64,
    plis_sent: AtomicU64,
}

/// A snapshot of [`ReceiveStats`].
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct ReceiveCounts {
    /// RTP packets of the video track that arrived (duplicates included).
    pub packets: u64,
    /// Packets that arrived after a higher sequence number and filled a hole in time: a NACK
    /// retransmission, or a packet the path reordered.
    pub late: u64,
    /// Packets that were already held.
    pub duplicates: u64,
    /// Packets that came after their place was passed (consumed, given up or skipped).
    pub stale: u64,
    /// Sequence numbers given up as lost (never arrived within the wait).
    pub lost: u64,
    /// Times a hole was given up (each makes an IDR necessary).
    pub gave_up: u64,
    /// Access units handed to the decoder.
    pub units: u64,
    /// ... of which IDRs.
    pub idrs: u64,
    /// Access units dropped: incomplete, or P frames while waiting for an IDR.
    pub units_dropped: u64,
    /// Access units the decoder refused.
    pub decode_errors: u64,
    /// Picture-loss indications sent (automatic and [`crate::client::StreamClient::send_pli`]).
    pub plis_sent: u64,
}

impl ReceiveCounts {
    /// The counts since `earlier`.
    pub fn since(&self, earlier: &ReceiveCounts) -> ReceiveCounts {
        ReceiveCounts {
            packets: self.packets - earlier.packets,
            late: self.late - earlier.late,
            duplicates: self.duplicates - earlier.duplicates,
            stale: self.stale - earlier.stale,
            lost: self.lost - earlier.lost,
            gave_up: self.gave_up - earlier.gave_up,
            units: self.units - earlier.units,
            idrs: self.idrs - earlier.idrs,
            units_dropped: self.units_dropped - earlier.units_dropped,
            decode_errors: self.decode_errors - earlier.decode_errors,
            plis_sent: self.plis_sent - earlier.plis_sent,
        }
    }
}

impl ReceiveStats {
    pub fn snapshot(&self) -> ReceiveCounts {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        ReceiveCounts {
            packets: get(&self.packets),
            late: get(&self.late),
            duplicates: get(&self.duplicates),
            stale: get(&self.stale),
            lost: get(&self.lost),
            gave_up: get(&self.gave_up),
            units: get(&self.units),
            idrs: get(&self.idrs),
            units_dropped: get(&self.units_dropped),
            decode_errors: get(&self.decode_errors),
            plis_sent: get(&self.plis_sent),
        }
    }

    pub(crate) fn count_decode_error(&self) {
        self.decode_errors.fetch_add(1, Ordering::Relaxed);
    }

    pub(crate) fn count_pli(&self) {
        self.plis_sent.fetch_add(1, Ordering::Relaxed);
    }
}

/// One access unit, Annex-B.
#[derive(Debug)]
pub struct Unit {
    pub annex_b: Vec<u8>,
    /// When its last packet arrived.
    pub arrived_at: Instant,
    /// It holds an IDR slice.
    pub idr: bool,
}

struct Held {
    payload: Bytes,
    timestamp: u32,
    marker: bool,
    arrived: Instant,
}

/// See the module documentation.
pub struct Reassembler {
    held: BTreeMap<u64, Held>,
    /// The next sequence number to hand on (or, while waiting for an IDR, the lowest one
    /// still accepted); `None` before the first packet.
    next: Option<u64>,
    highest: Option<u64>,
    wait: Duration,
    need_idr: bool,
    pli_due: Option<Instant>,
    last_pli: Option<Instant>,
    last_dropped_timestamp: Option<u32>,
    stats: std::sync::Arc<ReceiveStats>,
}

impl Reassembler {
    /// A hole is given up `wait` after the oldest packet waiting behind it arrived.
    pub fn new(wait: Duration, stats: std::sync::Arc<ReceiveStats>) -> Self {
        Self { held: BTreeMap::new(), next: None, highest: None, wait, need_idr: true, pli_due: None, last_pli: None, last_dropped_timestamp: None, stats }
    }

    /// Extends a 16-bit sequence number to the one nearest the highest seen.
    fn extend(&self, seq: u16) -> u64 {
        let Some(h) = self.highest else { return (1 << 32) | u64::from(seq) };
        let candidate = (h & !0xffff) | u64::from(seq);
        [candidate.wrapping_sub(1 << 16), candidate, candidate + (1 << 16)].into_iter().min_by_key(|c| c.abs_diff(h)).unwrap_or(candidate)
    }

    /// Takes one RTP packet of the track.
    pub fn push(&mut self, seq: u16, timestamp: u32, marker: bool, payload: Bytes, now: Instant) {
        self.stats.packets.fetch_add(1, Ordering::Relaxed);
        let ext = self.extend(seq);
        if self.highest.is_none() {
            // The first packet: waiting for the join's IDR starts now.
            self.pli_due = Some(now + FIRST_IDR_GRACE);
        }
        if self.next.is_some_and(|n| ext < n) {
            self.stats.stale.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if self.held.contains_key(&ext) {
            self.stats.duplicates.fetch_add(1, Ordering::Relaxed);
            return;
        }
        match self.highest {
            Some(h) if ext < h => {
                self.stats.late.fetch_add(1, Ordering::Relaxed);
            }
            _ => self.highest = Some(ext),
        }
        self.held.insert(ext, Held { payload, timestamp, marker, arrived: now });
    }

    /// The decoder refused an access unit: drop everything up to the next IDR and ask for one.
    pub fn request_idr(&mut self, now: Instant) {
        self.lose_picture(now);
    }

    fn lose_picture(&mut self, now: Instant) {
        self.need_idr = true;
        let earliest = self.last_pli.map_or(now, |t| t + MIN_PLI_INTERVAL);
        self.pli_due = Some(earliest.max(now));
    }

    /// Whether a picture-loss indication should go out now (then it counts as sent).
    pub fn take_pli(&mut self, now: Instant) -> bool {
        if !self.need_idr || self.pli_due.is_none_or(|d| d > now) {
            return false;
        }
        self.last_pli = Some(now);
        self.pli_due = Some(now + PLI_RETRY);
        true
    }

    /// When [`Reassembler::pop`] and [`Reassembler::take_pli`] should be called again even
    /// if no packet comes.
    pub fn deadline(&self) -> Option<Instant> {
        let hole = self.held.values().map(|h| h.arrived).min().map(|t| t + self.wait);
        let pli = if self.need_idr { self.pli_due } else { None };
        match (hole, pli) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    fn drop_packet(&mut self, seq: u64) {
        if let Some(h) = self.held.remove(&seq)
            && self.last_dropped_timestamp != Some(h.timestamp)
        {
            self.last_dropped_timestamp = Some(h.timestamp);
            self.stats.units_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// The next whole access unit, if there is one; gives up holes older than the wait.
    pub fn pop(&mut self, now: Instant) -> Option<Unit> {
        loop {
            if self.need_idr {
                let start = self.held.iter().find(|(_, h)| starts_idr(&h.payload)).map(|(s, _)| *s);
                match start {
                    Some(s) => {
                        let below: Vec<u64> = self.held.range(..s).map(|(k, _)| *k).collect();
                        below.into_iter().for_each(|k| self.drop_packet(k));
                        self.next = Some(s);
                        self.need_idr = false;
                    }
                    None => {
                        // Nothing here can be decoded; drop what has waited long enough (an
                        // IDR's first packet could still come late, below the others).
                        let old: Vec<u64> = self.held.iter().take_while(|(_, h)| h.arrived + self.wait <= now).map(|(k, _)| *k).collect();
                        if let Some(&last) = old.last() {
                            old.into_iter().for_each(|k| self.drop_packet(k));
                            self.next = Some(last + 1);
                        }
                        while self.held.len() > MAX_HELD {
                            let Some((&k, _)) = self.held.iter().next() else { break };
                            self.drop_packet(k);
                            self.next = Some(k + 1);
                        }
                        return None;
                    }
                }
            }
            let next = self.next?;
            if let Some(end) = self.complete_from(next) {
                let unit = self.take_unit(next, end);
                self.next = Some(end + 1);
                match unit {
                    Some(u) => {
                        self.stats.units.fetch_add(1, Ordering::Relaxed);
                        if u.idr {
                            self.stats.idrs.fetch_add(1, Ordering::Relaxed);
                        }
                        return Some(u);
                    }
                    None => {
                        // Not depacketizable: as good as lost.
                        self.stats.units_dropped.fetch_add(1, Ordering::Relaxed);
                        self.stats.gave_up.fetch_add(1, Ordering::Relaxed);
                        self.lose_picture(now);
                        continue;
                    }
                }
            }
            let oldest = self.held.values().map(|h| h.arrived).min()?;
            if oldest + self.wait > now && self.held.len() <= MAX_HELD {
                return None;
            }
            // Give the hole up: count what never came, then wait for an IDR.
            let top = self.held.keys().next_back().copied().unwrap_or(next);
            let missing = (next..=top).filter(|s| !self.held.contains_key(s)).count() as u64;
            self.stats.lost.fetch_add(missing, Ordering::Relaxed);
            self.stats.gave_up.fetch_add(1, Ordering::Relaxed);
            self.lose_picture(now);
        }
    }

    /// The last sequence number of the access unit that starts at `first`, if all of it is here.
    fn complete_from(&self, first: u64) -> Option<u64> {
        let timestamp = self.held.get(&first)?.timestamp;
        let mut s = first;
        loop {
            let h = self.held.get(&s)?;
            if h.timestamp != timestamp {
                // A new picture without a marker on the last one.
                return Some(s - 1);
            }
            if h.marker {
                return Some(s);
            }
            s += 1;
        }
    }

    fn take_unit(&mut self, first: u64, last: u64) -> Option<Unit> {
        let mut depacketizer = H264Packet::default();
        let mut annex_b = Vec::new();
        let mut arrived_at = None;
        let mut ok = true;
        for s in first..=last {
            let h = self.held.remove(&s)?;
            arrived_at = Some(h.arrived);
            match depacketizer.depacketize(&h.payload) {
                Ok(nals) => annex_b.extend_from_slice(&nals),
                Err(e) => {
                    tracing::debug!("undepacketizable RTP packet: {e}");
                    ok = false;
                }
            }
        }
        if !ok || annex_b.is_empty() {
            return None;
        }
        let idr = has_idr_slice(&annex_b);
        Some(Unit { annex_b, arrived_at: arrived_at?, idr })
    }
}

/// Whether an RTP payload opens an IDR access unit: its first NAL unit is an SPS (alone, or
/// first in a STAP-A, as the `webrtc` crate packs SPS and PPS).
fn starts_idr(payload: &[u8]) -> bool {
    const SPS: u8 = 7;
    const STAP_A: u8 = 24;
    match payload.first().map(|b| b & 0x1f) {
        Some(SPS) => true,
        Some(STAP_A) => payload.get(3).is_some_and(|b| b & 0x1f == SPS),
        _ => false,
    }
}

/// Whether an Annex-B access unit holds an IDR slice (NAL type 5).
pub fn has_idr_slice(annex_b: &[u8]) -> bool {
    annex_b.windows(4).any(|w| w[0] == 0 && w[1] == 0 && w[2] == 1 && w[3] & 0x1f == 5)
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    const SPS_PPS: &[u8] = &[0x78, 0x00, 0x02, 0x67, 0x42, 0x00, 0x02, 0x68, 0xce];

    fn idr_slice() -> Bytes {
        Bytes::from_static(&[0x65, 0x88, 0x84])
    }

    fn p_slice() -> Bytes {
        Bytes::from_static(&[0x41, 0x9a, 0x02])
    }

    struct Feed {
        r: Reassembler,
        t0: Instant,
    }

    impl Feed {
        fn new() -> Self {
            Self { r: Reassembler::new(Duration::from_millis(250), Arc::new(ReceiveStats::default())), t0: Instant::now() }
        }
        fn at(&self, ms: u64) -> Instant {
            self.t0 + Duration::from_millis(ms)
        }
        fn push(&mut self, ms: u64, seq: u16, ts: u32, marker: bool, payload: Bytes) {
            let t = self.at(ms);
            self.r.push(seq, ts, marker, payload, t);
        }
        fn pop_all(&mut self, ms: u64) -> Vec<bool> {
            let t = self.at(ms);
            std::iter::from_fn(|| self.r.pop(t)).map(|u| u.idr).collect()
        }
        /// IDR as three packets (SPS/PPS, SEI-less slice in two) at `seq`.
        fn idr(&mut self, ms: u64, seq: u16, ts: u32) {
            self.push(ms, seq, ts, false, Bytes::from_static(SPS_PPS));
            self.push(ms, seq.wrapping_add(1), ts, true, idr_slice());
        }
    }

    #[test]
    fn reordered_packets_and_retransmissions_land_in_place() {
        let mut f = Feed::new();
        f.idr(0, 100, 0);
        assert_eq!(f.pop_all(0), vec![true]);
        // P frames at 102, 103 (two packets: 103 no marker, 104 marker), 105; 103 comes late.
        f.push(10, 102, 3000, true, p_slice());
        f.push(50, 104, 6000, true, p_slice());
        f.push(51, 105, 9000, true, p_slice());
        assert_eq!(f.pop_all(51), vec![false], "only 102 is whole");
        f.push(150, 103, 6000, false, p_slice());
        assert_eq!(f.pop_all(150), vec![false, false]);
        let c = f.r.stats.snapshot();
        assert_eq!((c.late, c.lost, c.gave_up, c.units, c.idrs), (1, 0, 0, 4, 1));
        assert!(!f.r.take_pli(f.at(150)), "nothing was lost");
    }

    #[test]
    fn a_hole_given_up_skips_to_the_next_idr_and_asks_for_one() {
        let mut f = Feed::new();
        f.idr(0, 65534, 0); // wraps: 65534, 65535
        assert_eq!(f.pop_all(0), vec![true]);
        f.push(40, 1, 6000, true, p_slice()); // 0 never comes
        f.push(80, 2, 9000, true, p_slice());
        assert!(f.pop_all(100).is_empty());
        assert!(!f.r.take_pli(f.at(100)));
        assert!(f.pop_all(300).is_empty(), "given up at 40 + 250 ms");
        assert!(f.r.take_pli(f.at(300)));
        assert!(!f.r.take_pli(f.at(400)), "not again so soon");
        f.push(420, 3, 12000, true, p_slice()); // still a P frame: dropped
        assert!(f.r.take_pli(f.at(600)), "repeated while no IDR comes");
        f.idr(650, 4, 15000);
        f.push(690, 6, 18000, true, p_slice());
        assert_eq!(f.pop_all(690), vec![true, false]);
        let c = f.r.stats.snapshot();
        assert_eq!((c.lost, c.gave_up, c.idrs, c.units), (1, 1, 2, 3));
        assert!(c.units_dropped >= 2, "{c:?}");
        assert!(!f.r.take_pli(f.at(2000)));
    }

    #[test]
    fn the_stream_starts_at_the_first_idr() {
        let mut f = Feed::new();
        f.push(0, 9, 0, true, p_slice()); // a P frame before the IDR (not from our master)
        f.idr(5, 10, 3000);
        assert_eq!(f.pop_all(5), vec![true]);
        assert!(!f.r.take_pli(f.at(5000)));
    }

    #[test]
    fn idr_slices_are_recognised() {
        assert!(has_idr_slice(&[0, 0, 0, 1, 0x67, 1, 0, 0, 0, 1, 0x65, 2]));
        assert!(!has_idr_slice(&[0, 0, 0, 1, 0x41, 1, 2]));
        assert!(starts_idr(SPS_PPS) && !starts_idr(&p_slice()) && !starts_idr(&idr_slice()));
    }
}
