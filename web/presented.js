// presented.js — honest latency: from the moment a pose left the page to the moment the
// frame rendered from it is presented, not when its frame-info message arrives (which is
// before the video frame is decoded and shown).
//
// requestVideoFrameCallback reports each presented frame's RTP timestamp; every frame-info
// message carries `rtp_ticks`, the frame's RTP timestamp minus the stream's first (the
// server's track starts at a random timestamp). The offset between the two is found by
// votes: each (presented frame, frame info) pair proposes one, and the offset at least
// MIN_VOTES presented frames agree on wins. Frame durations are real times in 90 kHz ticks,
// so their sequence is irregular and a wrong offset gathers no votes. A new stream (reconnect)
// starts over.

const KEEP_INFOS = 300;
const KEEP_PRESENTED = 60;
const MIN_VOTES = 3;
const WINDOW_MS = 1000;

export class PresentedLatency {
  constructor() {
    this.reset();
  }

  /** Forget the stream (a new peer connection has a new RTP clock). */
  reset() {
    this.infos = new Map();   // rtp_ticks → t_client_ms of the pose
    this.pending = [];        // presented frames not matched yet: {rtp, shown}
    this.offset = null;       // RTP timestamp of the stream's first frame
    this.samples = [];        // [shown, latency ms] over the last WINDOW_MS
    this.matched = 0;
  }

  /** Starts watching `video` (once; harmless where requestVideoFrameCallback is missing). */
  watch(video) {
    if (this.video === video || !video || typeof video.requestVideoFrameCallback !== 'function') return;
    this.video = video;
    const onFrame = (now, meta) => {
      if (Number.isFinite(meta.rtpTimestamp)) {
        this.pending.push({ rtp: meta.rtpTimestamp >>> 0, shown: meta.expectedDisplayTime ?? now });
        if (this.pending.length > KEEP_PRESENTED) this.pending.shift();
        this.match();
      }
      video.requestVideoFrameCallback(onFrame);
    };
    video.requestVideoFrameCallback(onFrame);
  }

  /** A frame-info message arrived. */
  addInfo(info) {
    if (!Number.isFinite(info.rtp_ticks) || !Number.isFinite(info.t_client_ms)) return;
    this.infos.set(info.rtp_ticks >>> 0, info.t_client_ms);
    if (this.infos.size > KEEP_INFOS) this.infos.delete(this.infos.keys().next().value);
    this.match();
  }

  match() {
    if (this.offset === null) this.findOffset();
    if (this.offset === null) return;
    const left = [];
    for (const p of this.pending) {
      const t = this.infos.get((p.rtp - this.offset) >>> 0);
      if (t === undefined) {
        left.push(p);
        continue;
      }
      this.samples.push([p.shown, p.shown - t]);
      this.matched += 1;
    }
    // Frames whose info never comes (lost, or a wrong offset after a stream change) age out;
    // many of them with infos at hand means the offset is stale.
    const cutoff = performance.now() - 2 * WINDOW_MS;
    this.pending = left.filter((p) => p.shown >= cutoff);
    if (this.pending.length >= KEEP_PRESENTED / 2) this.offset = null;
  }

  findOffset() {
    const votes = new Map();
    const ticks = [...this.infos.keys()].slice(-100);
    for (const p of this.pending.slice(-30)) {
      for (const k of ticks) {
        const o = (p.rtp - k) >>> 0;
        votes.set(o, (votes.get(o) || 0) + 1);
      }
    }
    let best = null, most = 0;
    for (const [o, n] of votes) if (n > most) { best = o; most = n; }
    if (most >= MIN_VOTES) this.offset = best;
  }

  /** Median pose → presented latency over the last second, ms (null if none). */
  p50() {
    const cutoff = performance.now() - WINDOW_MS;
    while (this.samples.length && this.samples[0][0] < cutoff) this.samples.shift();
    if (!this.samples.length) return null;
    const v = this.samples.map((s) => s[1]).sort((a, b) => a - b);
    return v[Math.floor(v.length / 2)];
  }
}
