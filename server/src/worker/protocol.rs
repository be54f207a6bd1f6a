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
//!   `Nephele-Views`, the JSON list of view sizes, and `Nephele-Render-Ms`), or one `error`
//!   message with the reason as payload. The result payload is, per view in order, RGBA8
//!   (`w·h·4` bytes) then, if the task `needs_depth` (its views will be composed by depth),
//!   depth (`w·h` little-endian f32), cut into chunks of at most
//!   [`CHUNK_BYTES`]: half of NATS's default 1 MiB payload limit, leaving room for headers
//!   and for servers configured lower.

use std::{sync::Arc, time::Duration};

use bytes::Bytes;
use nephele_renderer::Frame;
use serde::{Deserialize, Serialize};

use crate::master::core::task::{RenderTask, TaskId};

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
        nephele_signaling::protocol::is_valid_name(&a.id).then_some(a)
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

/// The result payload of rendered views (depth too if `with_depth`), in chunks of at most
/// [`CHUNK_BYTES`].
pub fn result_chunks(frames: &[Arc<Frame>], with_depth: bool) -> (Vec<(u32, u32)>, Vec<Bytes>) {
    let sizes = frames.iter().map(|f| (f.width, f.height)).collect();
    let mut all = Vec::with_capacity(frames.iter().map(|f| f.rgba.len() + if with_depth { 4 * f.depth.len() } else { 0 }).sum());
    for f in frames {
        all.extend_from_slice(&f.rgba);
        if with_depth {
            for d in &f.depth {
                all.extend_from_slice(&d.to_le_bytes());
            }
        }
    }
    let all = Bytes::from(all);
    let chunks = if all.is_empty() {
        vec![all]
    } else {
        (0..all.len()).step_by(CHUNK_BYTES).map(|at| all.slice(at..(at + CHUNK_BYTES).min(all.len()))).collect()
    };
    (sizes, chunks)
}

/// Frames back from the joined chunks and the `Nephele-Views` sizes. Without depth, the
/// frames' depth is empty (only a composed scene reads it).
pub fn frames_from(sizes: &[(u32, u32)], payload: &[u8], with_depth: bool) -> Result<Vec<Arc<Frame>>, ReplyError> {
    let per_pixel = if with_depth { 8 } else { 4 };
    let want: usize = sizes.iter().map(|(w, h)| *w as usize * *h as usize * per_pixel).sum();
    if payload.len() != want {
        return Err(ReplyError::Size { got: payload.len(), want });
    }
    let mut at = 0;
    let mut frames = Vec::with_capacity(sizes.len());
    for &(w, h) in sizes {
        let n = w as usize * h as usize;
        let rgba = payload[at..at + 4 * n].to_vec();
        at += 4 * n;
        let depth = if with_depth {
            let d = payload[at..at + 4 * n].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
            at += 4 * n;
            d
        } else {
            Vec::new()
        };
        frames.push(Arc::new(Frame { width: w, height: h, rgba, depth }));
    }
    Ok(frames)
}

/// Parses `Nephele-Views`: at most `max_views` sizes within the render limits.
pub fn parse_views(text: &str, max_views: usize) -> Result<Vec<(u32, u32)>, ReplyError> {
    let sizes: Vec<(u32, u32)> = serde_json::from_str(text).map_err(|_| ReplyError::Malformed(VIEWS))?;
    if sizes.len() > max_views || !sizes.iter().all(|&(w, h)| nephele_limits::render_size_ok(w, h)) {
        return Err(ReplyError::Malformed(VIEWS));
    }
    Ok(sizes)
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
        assert_eq!(parse_views("[[64,48],[1,1]]", 8), Ok(vec![(64, 48), (1, 1)]));
        for bad in ["[[0,1]]", "[[100000,1]]", "nonsense", "[[1,1],[1,1]]"] {
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
