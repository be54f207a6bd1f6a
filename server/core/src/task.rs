//! Render tasks (docs/architecture.md §6): the unit of work the scheduler hands to a render worker. A task
//! is one scene object and a list of views, each tagged with the user and frame it belongs
//! to; a worker renders the whole list in one pass (one parallel pass on the CPU, one
//! dispatch on the GPU) and answers with RGBA (alpha = object opacity) plus depth per view.
//! One user's frame may need several tasks (one per object of a composed scene); one task
//! may serve several users (shared tasks, §6.2.1). Tasks and results cross process
//! boundaries (render workers over NATS), so they serialise.

use std::sync::Arc;

use glam::Vec3;
use nephele_renderer::{Frame, Instance, View, ViewRequest};
use serde::{Deserialize, Serialize};

/// Names a task for the life of a master.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct TaskId(pub u64);

impl std::fmt::Display for TaskId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "t{}", self.0)
    }
}

/// Names a render worker (in-process, or later a process reached over NATS).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WorkerId(pub String);

/// Heavy tasks (many pixels, or a close object) and light ones ([`super::estimate`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskClass {
    Heavy,
    Light,
}

/// The user frame (and which of its scene's objects) one rendered view answers: usually
/// one, several when identical requests of different users were merged.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ViewTag {
    pub session: String,
    pub frame: u64,
    /// Index of the scene object (the layer of the composition).
    pub part: u32,
}

/// One view of a task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskView {
    /// Camera with intrinsics already at the render scale.
    pub view: View,
    /// Where the object sits in the scene.
    pub instance: Instance,
    /// Linear RGB behind the object.
    pub background: Vec3,
    /// Fraction of the stream size this view is rendered at.
    pub render_scale: f32,
    /// Who asked for it.
    pub tags: Vec<ViewTag>,
}

/// One asset and the views to render of it (each view with its own placement).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RenderTask {
    pub id: TaskId,
    /// The asset's name in the catalogues of master and workers.
    pub asset: String,
    pub views: Vec<TaskView>,
    pub class: TaskClass,
    /// Primary rays (pixels) of all views.
    pub rays: u64,
    /// Pixels the proxy expects the object to cover, all views.
    pub est_pixels: u64,
    /// The views will be composed by depth (objects of a multi-object scene): a remote
    /// worker sends depth back only then, halving what crosses the network otherwise.
    #[serde(default = "yes")]
    pub needs_depth: bool,
}

fn yes() -> bool {
    true
}

impl RenderTask {
    /// The views as the renderer takes them.
    pub fn requests(&self) -> Vec<ViewRequest> {
        self.views.iter().map(|v| ViewRequest { view: v.view, instance: v.instance, background: v.background }).collect()
    }

    /// Distinct users in this task.
    pub fn users(&self) -> usize {
        let mut sessions: Vec<&str> = self.views.iter().flat_map(|v| v.tags.iter().map(|t| t.session.as_str())).collect();
        sessions.sort_unstable();
        sessions.dedup();
        sessions.len()
    }
}

/// Why a cancelled task has no frames (workers answer with exactly this).
pub const CANCELLED: &str = "cancelled: the users of most of the task left";

/// What a worker reports for a task.
#[derive(Debug, Clone)]
pub struct TaskResult {
    pub id: TaskId,
    /// One frame per view, in the task's order; or why the task failed.
    pub frames: Result<Vec<Arc<Frame>>, String>,
    /// Wall time the worker spent on the task, ms.
    pub render_ms: f64,
    /// Getting the task to a remote worker and its result back, less the render (0 for
    /// in-process workers), ms.
    pub transfer_ms: f64,
    /// Bytes of the result that crossed the network (0 in process).
    pub bytes: u64,
    /// The worker that rendered it, when the farm knows better than the core which one did
    /// (a light farm's queue group picks its own); `None`: the worker it was handed to.
    pub rendered_by: Option<String>,
}

impl TaskResult {
    /// A result rendered in this process.
    pub fn local(id: TaskId, frames: Result<Vec<Arc<Frame>>, String>, render_ms: f64) -> Self {
        Self { id, frames, render_ms, transfer_ms: 0.0, bytes: 0, rendered_by: None }
    }

    /// A task that did not render, and why.
    pub fn failed(id: TaskId, why: impl Into<String>) -> Self {
        Self::local(id, Err(why.into()), 0.0)
    }
}
