//! In-process render workers: OS threads that take [`RenderTask`]s from the core, render
//! each whole task in one pass on the catalogue's backend (one parallel pass on the CPU, one
//! dispatch on the GPU), and report the frames. Each worker first renders a calibration view
//! of every scene so the scheduler starts from a measured throughput (rays per second) and
//! refines it online. A panicking render ends that task with an error, never the worker; a
//! task whose users all left is skipped if it has not started and stopped at the renderer's
//! next safe point if it has. Each worker queues at most
//! [`nephele_limits::MAX_QUEUED_TASKS_PER_WORKER`] tasks: the pool's memory has a bound.
//! The renders run on their own thread pool at a lower scheduling priority than the rest of
//! the process ([`render_pool`]), so that the short, latency-bound work beside them runs
//! first when both want a core.

use std::{
    collections::HashMap,
    panic::AssertUnwindSafe,
    sync::{Arc, Mutex, mpsc},
    time::Instant,
};

use nephele_renderer::{CancelFlag, Intrinsics, RenderError, View, ViewRequest};

use nephele_core::task::{CANCELLED, RenderTask, TaskClass, TaskId, TaskResult, WorkerId};
use crate::catalog::Catalog;

/// What a worker tells the driver.
#[derive(Debug)]
pub enum WorkerEvent {
    Up { worker: WorkerId, rays_per_s: f64, slots: u32, farm: Option<TaskClass>, assets: Option<Vec<String>> },
    Down { worker: WorkerId, tasks_lost: bool },
    Done(TaskResult),
}

/// Edge of the calibration view, pixels.
const CALIBRATION_EDGE: u32 = 256;

/// How much lower than the process's the render threads' priority is (a nice increment);
/// `NEPHELE_RENDER_NICE` changes it (0: the same priority).
pub const RENDER_NICE: i32 = 10;

/// The render threads of in-process workers: one per core, each at nice +[`RENDER_NICE`]
/// (or `NEPHELE_RENDER_NICE`) relative to the process, so that when the encoder (the frame
/// before's), WebRTC, signaling or an arriving pose want a core the renderer holds, they
/// take it at once instead of waiting for a time slice; the render, which takes every core
/// anyway, yields them that time and no more. `None` (renders then use the global pool) if
/// the pool cannot be built.
fn render_pool() -> Option<Arc<rayon::ThreadPool>> {
    let nice = std::env::var("NEPHELE_RENDER_NICE").ok().and_then(|v| v.parse::<i32>().ok()).unwrap_or(RENDER_NICE).clamp(0, 19);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("render-{i}"))
        .start_handler(move |_| lower_priority(nice))
        .build()
        .map_err(|e| tracing::warn!("render thread pool: {e}; rendering on the global pool"))
        .ok()
        .map(Arc::new)
}

/// Raises the calling thread's nice value by `by` (Linux keeps one per thread); a failure
/// only logs.
#[allow(unsafe_code)] // two FFI calls into libc
fn lower_priority(by: i32) {
    if by == 0 {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid takes no arguments; getpriority and setpriority only read and set
        // this thread's nice value.
        let changed = unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            let now = libc::getpriority(libc::PRIO_PROCESS, tid);
            libc::setpriority(libc::PRIO_PROCESS, tid, (now + by).min(19))
        };
        if changed != 0 {
            tracing::warn!("could not lower a render thread's priority: {}", std::io::Error::last_os_error());
        }
    }
}

/// Runs `f` on `pool` (the caller waits), or here (on the global pool) without one.
fn on_pool<T: Send>(pool: Option<&rayon::ThreadPool>, f: impl FnOnce() -> T + Send) -> T {
    match pool {
        Some(pool) => pool.install(f),
        None => f(),
    }
}

/// A pool of one or more render threads sharing the catalogue.
pub struct LocalWorkers {
    senders: Vec<(WorkerId, mpsc::SyncSender<RenderTask>)>,
    /// A flag per queued or running task; the worker removes it when the task is done.
    flags: Arc<Mutex<HashMap<TaskId, CancelFlag>>>,
}

impl LocalWorkers {
    /// Starts `count` workers named `local-1`, `local-2`, …; events go to `report`.
    pub fn spawn(catalog: Arc<Catalog>, count: usize, report: impl Fn(WorkerEvent) + Send + Clone + 'static) -> std::io::Result<Self> {
        let flags = Arc::new(Mutex::new(HashMap::new()));
        let mut senders = Vec::new();
        let pool = render_pool();
        for i in 1..=count.max(1) {
            let id = WorkerId(format!("local-{i}"));
            let (tx, rx) = mpsc::sync_channel::<RenderTask>(nephele_limits::MAX_QUEUED_TASKS_PER_WORKER);
            let (catalog, report, flags, name, pool) = (Arc::clone(&catalog), report.clone(), Arc::clone(&flags), id.clone(), pool.clone());
            std::thread::Builder::new().name(id.0.clone()).spawn(move || worker_loop(name, &catalog, pool.as_deref(), rx, &report, &flags))?;
            senders.push((id, tx));
        }
        Ok(Self { senders, flags })
    }

    /// Queues a task on `worker`; gives it back with the reason if that worker is gone or
    /// its queue is full.
    pub fn submit(&self, worker: &WorkerId, task: RenderTask) -> Result<(), (RenderTask, String)> {
        let Some((_, tx)) = self.senders.iter().find(|(id, _)| id == worker) else {
            return Err((task, format!("worker {} is gone", worker.0)));
        };
        let id = task.id;
        self.flags().insert(id, CancelFlag::default());
        tx.try_send(task).map_err(|e| {
            self.flags().remove(&id);
            match e {
                mpsc::TrySendError::Full(t) => {
                    (t, format!("worker {} already has {} tasks queued", worker.0, nephele_limits::MAX_QUEUED_TASKS_PER_WORKER))
                }
                mpsc::TrySendError::Disconnected(t) => (t, format!("worker {} is gone", worker.0)),
            }
        })
    }

    /// Stops `task`: skipped if it has not started, stopped at the next safe point if it has.
    pub fn cancel(&self, task: TaskId) {
        if let Some(flag) = self.flags().get(&task) {
            flag.cancel();
        }
    }

    fn flags(&self) -> std::sync::MutexGuard<'_, HashMap<TaskId, CancelFlag>> {
        self.flags.lock().unwrap_or_else(|e| e.into_inner())
    }
}

fn worker_loop(
    id: WorkerId,
    catalog: &Catalog,
    pool: Option<&rayon::ThreadPool>,
    tasks: mpsc::Receiver<RenderTask>,
    report: &impl Fn(WorkerEvent),
    flags: &Mutex<HashMap<TaskId, CancelFlag>>,
) {
    let rays_per_s = on_pool(pool, || calibrate(catalog));
    tracing::info!(worker = %id.0, backend = %catalog.backend_name, rays_per_s, "render worker up");
    report(WorkerEvent::Up { worker: id.clone(), rays_per_s, slots: 1, farm: None, assets: None });
    let lock = || flags.lock().unwrap_or_else(|e| e.into_inner());
    for task in tasks {
        let cancel = lock().get(&task.id).cloned().unwrap_or_default();
        let result = on_pool(pool, || render_task(catalog, &task, &cancel));
        lock().remove(&task.id);
        report(WorkerEvent::Done(result));
    }
}

/// Renders a whole task in one call of the backend, unless `cancel` is set before or during.
pub fn render_task(catalog: &Catalog, task: &RenderTask, cancel: &CancelFlag) -> TaskResult {
    if cancel.is_cancelled() {
        return TaskResult::failed(task.id, CANCELLED);
    }
    let _span = tracing::debug_span!("render_task", task = %task.id, asset = %task.asset, views = task.views.len(), class = ?task.class).entered();
    let started = Instant::now();
    let frames = match catalog.assets.get(&task.asset) {
        None => Err(format!("this worker has no asset {:?}", task.asset)),
        Some(asset) => {
            let requests = task.requests();
            match std::panic::catch_unwind(AssertUnwindSafe(|| asset.prepared.render_cancellable(&requests, &catalog.settings, cancel))) {
                Ok(Ok(out)) => Ok(out.frames.into_iter().map(Arc::new).collect()),
                Ok(Err(RenderError::Cancelled)) => Err(CANCELLED.into()),
                Ok(Err(e)) => Err(e.to_string()),
                Err(_) => Err("the renderer panicked on this task".into()),
            }
        }
    };
    TaskResult::local(task.id, frames, started.elapsed().as_secs_f64() * 1e3)
}

/// Rays per second of one warm render of each asset from a typical viewpoint.
pub fn calibrate(catalog: &Catalog) -> f64 {
    let (mut rays, mut seconds) = (0.0, 0.0);
    for asset in catalog.assets.values() {
        let b = asset.prepared.asset().bounds;
        let (center, radius) = (((b.min + b.max) * 0.5).as_dvec3(), f64::from((b.max - b.min).length() * 0.5));
        let k = Intrinsics::from_fov_x(CALIBRATION_EDGE, CALIBRATION_EDGE, 0.69);
        let view = View::orbit(center, 2.5 * radius.max(1e-3), 35.0, 25.0, k);
        let request = [ViewRequest::new(view)];
        for round in 0..2 {
            let t = Instant::now();
            if asset.prepared.render(&request, &catalog.settings).is_err() {
                break;
            }
            if round == 1 {
                seconds += t.elapsed().as_secs_f64();
                rays += f64::from(CALIBRATION_EDGE * CALIBRATION_EDGE);
            }
        }
    }
    if seconds > 0.0 { rays / seconds } else { 0.0 }
}

