//! How masters and render workers talk over NATS — subjects, headers, payloads — written
//! once for both sides.
//!
//! - **Discovery**: every worker runs a NATS service named [`SERVICE_NAME`]; its metadata
//!   ([`WorkerAnnouncement`]) says its id, farm (heavy/light), scenes, assets, backend,
//!   measured rays/s and slots. Masters ask `$SRV.INFO.nephele-worker` and gather replies.
//! - **Tasks**: a task is the JSON of a `RenderTask` ([`TaskMessage`] adds the attempt).
//!   Light tasks go to the queue group of the light farm for their asset,
//!   `nephele.render.light.<asset>` (NATS gives each to one light worker: the farm is packed);
//!   heavy tasks, and every re-issue after a failure, go to one chosen worker's own
//!   subject `nephele.render.worker.<id>` (one task per heavy worker). The request's reply
//!   subject is the master's inbox for that task and attempt.
//! - **Replies**, all on that reply subject, told apart by the `Nephele-Kind` header:
//!   `accepted` at once (with `Nephele-Worker`), `working` every [`KEEPALIVE`] while
//!   rendering, then the result as `chunk` messages `Nephele-Chunk: i/n` (the first carries
//!   `Nephele-Views`, per view `[w, h, x, y, rw, rh]`: its size and the rectangle sent, and
//!   `Nephele-Render-Ms`), or one `error` message with the reason as payload. The result
//!   payload is, per view in order, the rectangle's RGBA8 (`rw·rh·4` bytes) then, if the
//!   task `needs_depth` (its views will be composed by depth), its depth (`rw·rh`
//!   little-endian f32). Views for composing were rendered over black, so only the
//!   rectangle around what the object covers is sent (outside it: RGBA 0, depth ∞, exactly);
//!   other views are sent whole. All of it is cut into chunks of at most
//!   [`CHUNK_BYTES`]: half of NATS's default 1 MiB payload limit, leaving room for headers
//!   and for servers configured lower.
//! - **Cancel**: when every user of a task has left, the master publishes the task's reply
//!   subject to [`cancel_subject`] of the worker that accepted it; the worker stops that
//!   render at its next safe point and answers nothing more.

use std::{sync::Arc, time::Duration};

use bytes::Bytes;
use nephele_renderer::Frame;
use serde::{Deserialize, Serialize};

use nephele_core::task::{RenderTask, TaskId};

/// Name of the NATS service every render worker runs.
pub const SERVICE_NAME: &str = "nephele-worker";
/// Its version (semver, as the service API requires).
pub const SERVICE_VERSION: &str = "0.1.0";
/// Largest result chunk, bytes.
pub const CHUNK_BYTES: usize = 512 * 1024;
/// A rendering worker says `working` this often.
pub const KEEPALIVE: Duration = Duration::from_millis(40);
/// Largest task message a worker reads, bytes.
pub const MAX_TASK_BYTES: usize = 256 * 1024;

pub const KIND: &str = "Nephele-Kind";
pub const TASK: &str = "Nephele-Task";
pub const ATTEMPT: &str = "Nephele-Attempt";
pub const WORKER: &str = "Nephele-Worker";
pub const CHUNK: &str = "Nephele-Chunk";
pub const VIEWS: &str = "Nephele-Views";
pub const RENDER_MS: &str = "Nephele-Render-Ms";

/// Which farm a worker belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Farm {
    /// Takes heavy tasks (many pixels, close objects), one at a time.
    Heavy,
    /// Takes light tasks, several at a time.
    Light,
}

impl Farm {
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Heavy => "heavy",
            Self::Light => "light",
        }
    }

    /// Tasks a worker of this farm renders at once.
    pub fn slots(self) -> u32 {
        match self {
            Self::Heavy => 1,
            Self::Light => 2,
        }
    }
}

/// The queue-group subject of a farm for an asset.
pub fn farm_subject(farm: Farm, asset: &str) -> String {
    format!("nephele.render.{}.{asset}", farm.as_str())
}

/// A worker's own subject.
pub fn worker_subject(id: &str) -> String {
    format!("nephele.render.worker.{id}")
}

/// Where a worker hears that a task it accepted is no longer wanted (payload: the task's
/// reply subject).
pub fn cancel_subject(id: &str) -> String {
    format!("nephele.cancel.{id}")
}

/// What a worker announces in its service metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkerAnnouncement {
    pub id: String,
    pub farm: Farm,
    pub scenes: Vec<String>,
    pub assets: Vec<String>,
    pub backend: String,
    pub rays_per_s: f64,
    pub slots: u32,
}

impl WorkerAnnouncement {
    /// As the string map the NATS service API carries.
    pub fn to_metadata(&self) -> std::collections::HashMap<String, String> {
        [
            ("id", self.id.clone()),
            ("farm", self.farm.as_str().to_owned()),
            ("scenes", self.scenes.join(",")),
            ("assets", self.assets.join(",")),
            ("backend", self.backend.clone()),
            ("rays_per_s", format!("{:.0}", self.rays_per_s)),
            ("slots", self.slots.to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v))
        .collect()
    }

    /// Back from service metadata; `None` if anything is missing or malformed.
    pub fn from_metadata(m: &std::collections::HashMap<String, String>) -> Option<Self> {
        let list = |k: &str| -> Option<Vec<String>> { Some(m.get(k)?.split(',').filter(|s| !s.is_empty()).map(str::to_owned).collect()) };
        let farm = match m.get("farm")?.as_str() {
            "heavy" => Farm::Heavy,
            "light" => Farm::Light,
            _ => return None,
        };
        let a = Self {
            id: m.get("id")?.clone(),
            farm,
            scenes: list("scenes")?,
            assets: list("assets")?,
            backend: m.get("backend")?.clone(),
            rays_per_s: m.get("rays_per_s")?.parse().ok().filter(|r: &f64| r.is_finite() && *r >= 0.0)?,
            slots: m.get("slots")?.parse().ok().filter(|s| (1..=64).contains(s))?,
        };
        nephele_protocol::is_valid_name(&a.id).then_some(a)
    }
}

/// A task as sent: the render task and which attempt this is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskMessage {
    pub attempt: u32,
    pub task: RenderTask,
}

/// Why a result could not be read (the master treats the worker as failed for the task).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplyError {
    #[error("reply without a {0} header")]
    Missing(&'static str),
    #[error("reply header {0} is malformed")]
    Malformed(&'static str),
    #[error("result has {got} bytes; its views need {want}")]
    Size { got: usize, want: usize },
    #[error("chunk {index} of {count} is out of range")]
    Chunk { index: usize, count: usize },
}

/// A view of a result: its size, and the rectangle `[x, y, w, h]` of it that was sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(from = "[u32; 6]", into = "[u32; 6]")]
pub struct SentView {
    pub width: u32,
    pub height: u32,
    pub rect: [u32; 4],
}

impl From<[u32; 6]> for SentView {
    fn from(v: [u32; 6]) -> Self {
        Self { width: v[0], height: v[1], rect: [v[2], v[3], v[4], v[5]] }
    }
}

impl From<SentView> for [u32; 6] {
    fn from(v: SentView) -> Self {
        [v.width, v.height, v.rect[0], v.rect[1], v.rect[2], v.rect[3]]
    }
}

impl SentView {
    fn pixels(&self) -> usize {
        self.rect[2] as usize * self.rect[3] as usize
    }

    /// The rectangle lies inside the view.
    fn valid(&self) -> bool {
        let [x, y, w, h] = self.rect.map(u64::from);
        nephele_limits::render_size_ok(self.width, self.height) && x + w <= u64::from(self.width) && y + h <= u64::from(self.height)
    }
}

/// The smallest rectangle holding every pixel of `f` that is not empty (RGBA 0, depth ∞);
/// `[0, 0, 0, 0]` when the object is not in view.
fn covered_rect(f: &Frame) -> [u32; 4] {
    let (w, h) = (f.width as usize, f.height as usize);
    let (mut x0, mut y0, mut x1, mut y1) = (w, h, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if f.rgba[4 * i..4 * i + 4] != [0, 0, 0, 0] || f.depth.get(i).is_some_and(|d| d.is_finite()) {
                (x0, y0, x1, y1) = (x0.min(x), y0.min(y), x1.max(x + 1), y1.max(y + 1));
            }
        }
    }
    if x0 >= x1 { [0, 0, 0, 0] } else { [x0 as u32, y0 as u32, (x1 - x0) as u32, (y1 - y0) as u32] }
}

/// The result payload of rendered views (depth too if `with_depth`, and then only the
/// covered rectangle of each), in chunks of at most [`CHUNK_BYTES`].
pub fn result_chunks(frames: &[Arc<Frame>], with_depth: bool) -> (Vec<SentView>, Vec<Bytes>) {
    let views: Vec<SentView> = frames
        .iter()
        .map(|f| SentView { width: f.width, height: f.height, rect: if with_depth { covered_rect(f) } else { [0, 0, f.width, f.height] } })
        .collect();
    let mut all = Vec::with_capacity(views.iter().map(|v| v.pixels() * if with_depth { 8 } else { 4 }).sum());
    for (f, v) in frames.iter().zip(&views) {
        let [x, y, w, h] = v.rect.map(|c| c as usize);
        let stride = f.width as usize;
        for row in y..y + h {
            all.extend_from_slice(&f.rgba[4 * (row * stride + x)..4 * (row * stride + x + w)]);
        }
        if with_depth {
            for row in y..y + h {
                for d in &f.depth[row * stride + x..row * stride + x + w] {
                    all.extend_from_slice(&d.to_le_bytes());
                }
            }
        }
    }
    let all = Bytes::from(all);
    let chunks = if all.is_empty() {
        vec![all]
    } else {
        (0..all.len()).step_by(CHUNK_BYTES).map(|at| all.slice(at..(at + CHUNK_BYTES).min(all.len()))).collect()
    };
    (views, chunks)
}

/// Frames back from the joined chunks and the `Nephele-Views` layout. Without depth, the
/// frames' depth is empty (only a composed scene reads it).
pub fn frames_from(views: &[SentView], payload: &[u8], with_depth: bool) -> Result<Vec<Arc<Frame>>, ReplyError> {
    let per_pixel = if with_depth { 8 } else { 4 };
    let want: usize = views.iter().map(|v| v.pixels() * per_pixel).sum();
    if payload.len() != want {
        return Err(ReplyError::Size { got: payload.len(), want });
    }
    let mut at = 0;
    let mut frames = Vec::with_capacity(views.len());
    for v in views {
        let n = v.width as usize * v.height as usize;
        let [x, y, w, h] = v.rect.map(|c| c as usize);
        let stride = v.width as usize;
        let mut rgba = vec![0u8; 4 * n];
        for row in y..y + h {
            rgba[4 * (row * stride + x)..4 * (row * stride + x + w)].copy_from_slice(&payload[at..at + 4 * w]);
            at += 4 * w;
        }
        let depth = if with_depth {
            let mut d = vec![f32::INFINITY; n];
            for row in y..y + h {
                for (i, b) in payload[at..at + 4 * w].chunks_exact(4).enumerate() {
                    d[row * stride + x + i] = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
                at += 4 * w;
            }
            d
        } else {
            Vec::new()
        };
        frames.push(Arc::new(Frame { width: v.width, height: v.height, rgba, depth }));
    }
    Ok(frames)
}

/// Parses `Nephele-Views`: at most `max_views` views within the render limits, each
/// rectangle inside its view.
pub fn parse_views(text: &str, max_views: usize) -> Result<Vec<SentView>, ReplyError> {
    let views: Vec<SentView> = serde_json::from_str(text).map_err(|_| ReplyError::Malformed(VIEWS))?;
    if views.len() > max_views || !views.iter().all(SentView::valid) {
        return Err(ReplyError::Malformed(VIEWS));
    }
    Ok(views)
}

/// `i/n` of `Nephele-Chunk`.
pub fn parse_chunk(text: &str) -> Result<(usize, usize), ReplyError> {
    let (i, n) = text.split_once('/').ok_or(ReplyError::Malformed(CHUNK))?;
    let (i, n): (usize, usize) = (i.parse().map_err(|_| ReplyError::Malformed(CHUNK))?, n.parse().map_err(|_| ReplyError::Malformed(CHUNK))?);
    // A result is at most MAX_RENDER_PIXELS·8 bytes per view; n is bounded well above that.
    if n == 0 || n > 1 << 16 || i >= n {
        return Err(ReplyError::Chunk { index: i, count: n });
    }
    Ok((i, n))
}

/// The task id as a header value, and back.
pub fn task_header(id: TaskId) -> String {
    id.0.to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(w: u32, h: u32, seed: u8) -> Arc<Frame> {
        let n = (w * h) as usize;
        Arc::new(Frame {
            width: w,
            height: h,
            rgba: (0..4 * n).map(|i| (i as u8).wrapping_mul(seed)).collect(),
            depth: (0..n).map(|i| if i % 3 == 0 { f32::INFINITY } else { i as f32 * 0.5 }).collect(),
        })
    }

    /// An object covering a block of an otherwise empty view (rendered over black).
    fn object(w: u32, h: u32, block: [u32; 4]) -> Arc<Frame> {
        let n = (w * h) as usize;
        let mut f = Frame { width: w, height: h, rgba: vec![0; 4 * n], depth: vec![f32::INFINITY; n] };
        for y in block[1]..block[1] + block[3] {
            for x in block[0]..block[0] + block[2] {
                let i = (y * w + x) as usize;
                f.rgba[4 * i..4 * i + 4].copy_from_slice(&[x as u8, y as u8, 7, 200]);
                f.depth[i] = 1.0 + x as f32;
            }
        }
        Arc::new(f)
    }

    #[test]
    fn composed_views_send_only_what_the_object_covers_and_come_back_exact() {
        let frames = vec![object(640, 480, [100, 50, 200, 120]), object(64, 48, [0, 0, 0, 0]), object(64, 48, [63, 47, 1, 1])];
        let (views, chunks) = result_chunks(&frames, true);
        assert_eq!(views[0].rect, [100, 50, 200, 120]);
        assert_eq!(views[1].rect, [0, 0, 0, 0]);
        assert_eq!(views[2].rect, [63, 47, 1, 1]);
        let joined: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
        assert_eq!(joined.len(), 8 * (200 * 120 + 1));
        let text = serde_json::to_string(&views).unwrap();
        assert_eq!(text, "[[640,480,100,50,200,120],[64,48,0,0,0,0],[64,48,63,47,1,1]]");
        let back = frames_from(&parse_views(&text, 8).unwrap(), &joined, true).unwrap();
        assert_eq!(back, frames);
        // A rectangle outside its view is refused.
        for bad in ["[[64,48,60,0,5,1]]", "[[64,48,0,0,64,49]]", "[[64,48,1,2]]", "[[0,48,0,0,0,0]]"] {
            assert!(parse_views(bad, 8).is_err(), "{bad}");
        }
    }

    #[test]
    fn results_round_trip_through_chunks() {
        let frames = vec![frame(640, 480, 3), frame(1, 1, 5), frame(97, 31, 7)];
        let (sizes, chunks) = result_chunks(&frames, true);
        assert!(chunks.len() > 1 && chunks.iter().all(|c| c.len() <= CHUNK_BYTES));
        let joined: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
        let back = frames_from(&sizes, &joined, true).unwrap();
        assert_eq!(back, frames);
        // Truncated or padded payloads are refused.
        assert!(matches!(frames_from(&sizes, &joined[1..], true), Err(ReplyError::Size { .. })));
        assert!(matches!(frames_from(&sizes[..1], &joined, true), Err(ReplyError::Size { .. })));
        // Without depth: half the bytes, colours intact.
        let (_, chunks) = result_chunks(&frames, false);
        let joined: Vec<u8> = chunks.iter().flat_map(|c| c.iter().copied()).collect();
        assert_eq!(joined.len(), frames.iter().map(|f| f.rgba.len()).sum::<usize>());
        let back = frames_from(&sizes, &joined, false).unwrap();
        assert!(back.iter().zip(&frames).all(|(a, b)| a.rgba == b.rgba && a.depth.is_empty()));
    }

    #[test]
    fn headers_and_announcements_are_checked() {
        assert_eq!(parse_chunk("0/3"), Ok((0, 3)));
        for bad in ["3/3", "x/3", "1", "0/0", "-1/2", "1/99999999"] {
            assert!(parse_chunk(bad).is_err(), "{bad}");
        }
        let whole = |w, h| SentView { width: w, height: h, rect: [0, 0, w, h] };
        assert_eq!(parse_views("[[64,48,0,0,64,48],[1,1,0,0,1,1]]", 8), Ok(vec![whole(64, 48), whole(1, 1)]));
        for bad in ["[[0,1,0,0,0,0]]", "[[100000,1,0,0,1,1]]", "nonsense", "[[1,1,0,0,1,1],[1,1,0,0,1,1]]", "[[64,48]]"] {
            assert!(parse_views(bad, 1).is_err(), "{bad}");
        }
        let a = WorkerAnnouncement {
            id: "w-1".into(),
            farm: Farm::Light,
            scenes: vec!["lego".into(), "duo".into()],
            assets: vec!["lego".into(), "trio".into()],
            backend: "cpu".into(),
            rays_per_s: 2e6,
            slots: 2,
        };
        assert_eq!(WorkerAnnouncement::from_metadata(&a.to_metadata()), Some(a.clone()));
        let mut m = a.to_metadata();
        m.insert("farm".into(), "medium".into());
        assert_eq!(WorkerAnnouncement::from_metadata(&m), None);
        let mut m = a.to_metadata();
        m.insert("id".into(), "../x".into());
        assert_eq!(WorkerAnnouncement::from_metadata(&m), None);
        let mut m = a.to_metadata();
        m.insert("rays_per_s".into(), "NaN".into());
        assert_eq!(WorkerAnnouncement::from_metadata(&m), None);
    }
}
