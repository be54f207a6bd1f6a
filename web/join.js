// The join's rules, checked on the page before a join is sent: the same rules and the same
// words as the server's (`JoinSpec::check` in the nephele-protocol crate), with the numbers
// the server publishes at GET /limits, never a copy kept here. A join that breaks them is
// shown in words and not sent; the server checks again whatever the page says.

/** The server's limits (GET /limits), fetched once per page. */
let limitsPromise = null;
export function fetchLimits() {
  if (!limitsPromise) {
    limitsPromise = fetch(new URL('limits', location.href), { cache: 'no-store' }).then((r) => {
      if (!r.ok) throw new Error(`GET /limits: HTTP ${r.status}`);
      return r.json();
    });
    limitsPromise.catch(() => { limitsPromise = null; });
  }
  return limitsPromise;
}

const NAME = /^[A-Za-z0-9_-]+$/;

/** The first rule `join` ({scene, mode, width, height, fps, quilt?}) breaks, in words, or
 *  null. The order and the words are the server's. */
export function checkJoin(join, limits) {
  const { scene, mode, width, height, fps } = join;
  if (typeof scene !== 'string' || scene.length < 1 || scene.length > limits.name_max_chars || !NAME.test(scene)) {
    return 'scene must be 1 to 64 characters of A-Z a-z 0-9 _ -';
  }
  if (join.quilt && mode !== 'quilt') return 'a quilt layout is only for mode "quilt"';
  const long = Math.max(width, height);
  const short = Math.min(width, height);
  const L = limits.max_long_edge_px;
  const S = limits.max_short_edge_px;
  if (!(short >= 1 && long <= L && short <= S)) {
    return `frame size ${width}x${height} is outside the stream limits: at least 1x1, at most ${L}x${S} (or ${S}x${L} portrait)`;
  }
  if (!(fps >= limits.min_fps && fps <= limits.max_fps)) return `fps ${fps} is outside ${limits.min_fps}..=${limits.max_fps}`;
  if (mode === 'quilt') {
    const q = join.quilt || limits.default_quilt;
    if (q.cols === 0 || q.rows === 0 || q.cols * q.rows > limits.max_quilt_views) {
      return `a ${q.cols}x${q.rows} quilt is outside 1..=${limits.max_quilt_views} views`;
    }
    if (width % q.cols !== 0 || height % q.rows !== 0 || width < q.cols || height < q.rows) {
      return `a ${width}x${height} frame does not split into ${q.cols}x${q.rows} equal tiles (each edge must divide evenly)`;
    }
    if (!(q.cone_deg > 0 && q.cone_deg <= limits.max_quilt_cone_deg)) {
      return `quilt view cone ${q.cone_deg} degrees is outside (0, ${limits.max_quilt_cone_deg}]`;
    }
  }
  return null;
}
