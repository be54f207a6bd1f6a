//! `nephele worker`: a render worker of the NATS farm (docs/architecture.md §6). It loads its scenes'
//! assets on its backend (refusing, in words, to start when one is missing or corrupt),
//! measures its rays/s, announces itself through the NATS service API, and renders the
//! tasks masters send it ([`crate::protocol`]): from its farm's queue group per asset, and on its
//! own subject. While rendering it says `working` every 40 ms, so a master notices a dead
//! or stopped worker within a few hundred milliseconds and re-issues the task elsewhere.
//! A task its master cancels (every user left) stops at the renderer's next safe point.
//! [`WorkerMetrics`] counts what it did for `/metrics`.


use std::{
    collections::HashMap,
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use async_nats::{HeaderMap, service::ServiceExt};
use futures_util::StreamExt;
use nephele_renderer::CancelFlag;
use prometheus_client::{
    encoding::EncodeLabelSet,
    metrics::{
        counter::Counter,
        family::Family,
        gauge::Gauge,
        histogram::{Histogram, exponential_buckets},
    },
    registry::{Registry, Unit},
};
use tokio::sync::Semaphore;

use crate::protocol::{
    ATTEMPT, CHUNK, Farm, KEEPALIVE, KIND, MAX_TASK_BYTES, RENDER_MS, SERVICE_NAME, SERVICE_VERSION, TASK, TaskMessage, VIEWS, WORKER, WorkerAnnouncement,
    cancel_subject, farm_subject, result_chunks, task_header, worker_subject,
};
use crate::{
    catalog::Catalog,
    local::{calibrate, render_task},
};

/// How to log in to NATS: a token (`nats-server --auth`), a user and password, or a
/// credentials file (NATS accounts). Without one, a server that requires auth refuses us.
#[derive(Debug, Clone, Default)]
pub struct NatsAuth {
    pub token: Option<String>,
    pub user: Option<(String, String)>,
    pub creds_file: Option<std::path::PathBuf>,
}

/// Connects to `url` as `name`; `events` hears connection changes.
pub async fn connect(url: &str, auth: &NatsAuth, name: &str, events: impl Fn(async_nats::Event) + Send + Sync + 'static) -> Result<async_nats::Client> {
    let mut opts = match &auth.creds_file {
        Some(path) => async_nats::ConnectOptions::with_credentials_file(path).await.with_context(|| format!("reading NATS credentials {}", path.display()))?,
        None => async_nats::ConnectOptions::new(),
    };
    if let Some(token) = &auth.token {
        opts = opts.token(token.clone());
    }
    if let Some((user, pass)) = &auth.user {
        opts = opts.user_and_password(user.clone(), pass.clone());
    }
    let events = Arc::new(events);
    opts = opts
        .name(name)
        .connection_timeout(std::time::Duration::from_secs(5))
        .event_callback(move |e| {
            let events = Arc::clone(&events);
            async move { events(e) }
        });
    opts.connect(url).await.map_err(|e| {
        let text = e.to_string();
        if text.to_lowercase().contains("authorization") {
            anyhow::anyhow!("NATS at {url} refused us: {text} (give the token with --nats-token or NEPHELE_NATS_TOKEN, or --nats-creds)")
        } else {
            anyhow::anyhow!("cannot reach NATS at {url}: {text}")
        }
    })
}

/// A worker's settings.
#[derive(Debug, Clone)]
pub struct WorkerConfig {
    pub nats_url: String,
    pub auth: NatsAuth,
    pub farm: Farm,
    /// Unique id; default `<farm>-<host pid>`.
    pub id: String,
    /// Where it counts its work (registered in the caller's registry, or not at all).
    pub metrics: Arc<WorkerMetrics>,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabel {
    /// `rendered`, `failed` (the renderer or the task's content), `refused` (unreadable,
    /// too large, an asset it does not have) or `cancelled`.
    pub outcome: &'static str,
}

/// A worker's series: tasks by outcome, render time, result bytes, what runs now.
#[derive(Debug)]
pub struct WorkerMetrics {
    pub tasks: Family<OutcomeLabel, Counter>,
    pub render_seconds: Histogram,
    pub result_bytes: Counter,
    pub tasks_running: Gauge,
    pub rays_per_second: Gauge,
}

impl Default for WorkerMetrics {
    fn default() -> Self {
        Self {
            tasks: Family::default(),
            render_seconds: Histogram::new(exponential_buckets(0.001, 2.0, 14)),
            result_bytes: Counter::default(),
            tasks_running: Gauge::default(),
            rays_per_second: Gauge::default(),
        }
    }
}

impl WorkerMetrics {
    /// New series, registered in `registry` (as `nephele_worker_…`).
    pub fn register(registry: &mut Registry) -> Arc<Self> {
        let m = Arc::new(Self::default());
        registry.register("worker_tasks", "Render tasks this worker answered, by outcome", m.tasks.clone());
        registry.register_with_unit("worker_render", "Render time per task", Unit::Seconds, m.render_seconds.clone());
        registry.register_with_unit("worker_result", "Rendered results sent to masters", Unit::Bytes, m.result_bytes.clone());
        registry.register("worker_tasks_running", "Render tasks on this worker now", m.tasks_running.clone());
        registry.register("worker_rays_per_second", "This worker's measured render throughput (at start), rays per second", m.rays_per_second.clone());
        m
    }

    fn count(&self, outcome: &'static str) {
        self.tasks.get_or_create(&OutcomeLabel { outcome }).inc();
    }
}

/// Serves tasks until the process is stopped or NATS closes the connection for good.
pub async fn run(cfg: WorkerConfig, catalog: Arc<Catalog>) -> Result<()> {
    run_until(cfg, catalog, std::future::pending(), Duration::from_secs(30), |_| {}).await
}

/// [`run`] until `stop` resolves, then drains: its endpoints stop (the farm's queue sends
/// it nothing more and discovery no longer lists it), the tasks it is rendering finish and
/// are answered (up to `drain_deadline`), and it returns `Ok`. `ready` hears `None` once it
/// serves and `Some(why)` when it does not (draining).
pub async fn run_until(
    cfg: WorkerConfig,
    catalog: Arc<Catalog>,
    stop: impl std::future::Future<Output = ()>,
    drain_deadline: Duration,
    ready: impl Fn(Option<&str>),
) -> Result<()> {
    if !nephele_protocol::is_valid_name(&cfg.id) {
        bail!("worker id {:?} must be 1..=64 characters from [A-Za-z0-9_-]", cfg.id);
    }
    let client = connect(&cfg.nats_url, &cfg.auth, &cfg.id, |e| tracing::info!("NATS: {e}")).await?;
    let cat = Arc::clone(&catalog);
    let rays_per_s = tokio::task::spawn_blocking(move || calibrate(&cat)).await?;
    cfg.metrics.rays_per_second.set(rays_per_s as i64);
    let announcement = WorkerAnnouncement {
        id: cfg.id.clone(),
        farm: cfg.farm,
        scenes: catalog.names(),
        assets: catalog.asset_names(),
        backend: catalog.backend_name.clone(),
        rays_per_s,
        slots: cfg.farm.slots(),
    };
    let service = client
        .service_builder()
        .description("Nephele render worker")
        .metadata(announcement.to_metadata())
        .start(SERVICE_NAME, SERVICE_VERSION)
        .await
        .map_err(|e| anyhow::anyhow!("starting the NATS service: {e}"))?;
    let group = service.group_with_queue_group(format!("nephele.render.{}", cfg.farm.as_str()), cfg.farm.as_str());
    let mut endpoints = Vec::new();
    for asset in catalog.asset_names() {
        debug_assert_eq!(format!("nephele.render.{}.{asset}", cfg.farm.as_str()), farm_subject(cfg.farm, &asset));
        endpoints.push(group.endpoint(asset.clone()).await.map_err(|e| anyhow::anyhow!("subscribing to {asset}: {e}"))?);
    }
    endpoints.push(
        service.endpoint_builder().name("direct").queue_group(&cfg.id).add(worker_subject(&cfg.id)).await.map_err(|e| anyhow::anyhow!("subscribing to the worker subject: {e}"))?,
    );
    println!(
        "worker {} ({} farm) on {} serves {} ({} rays/s measured)",
        cfg.id,
        cfg.farm.as_str(),
        catalog.backend_name,
        catalog.names().join(", "),
        rays_per_s as u64
    );
    // Running tasks by reply subject (unique per master and attempt), for cancels.
    let running: Running = Arc::default();
    let mut cancels = client.subscribe(cancel_subject(&cfg.id)).await.map_err(|e| anyhow::anyhow!("subscribing to cancels: {e}"))?;
    let cancelled = Arc::clone(&running);
    tokio::spawn(async move {
        while let Some(msg) = cancels.next().await {
            let reply = String::from_utf8_lossy(&msg.payload);
            if let Some(flag) = cancelled.lock().unwrap_or_else(|e| e.into_inner()).get(reply.as_ref()) {
                tracing::debug!(task = %reply, "cancelled by its master");
                flag.cancel();
            }
        }
    });
    let slot_count = cfg.farm.slots();
    let slots = Arc::new(Semaphore::new(slot_count as usize));
    let mut requests = futures_util::stream::select_all(endpoints);
    ready(None);
    tokio::pin!(stop);
    loop {
        let request = tokio::select! {
            request = requests.next() => match request {
                Some(r) => r,
                None => bail!("NATS closed the worker's subscriptions"),
            },
            () = &mut stop => break,
        };
        let permit = Arc::clone(&slots).acquire_owned().await?;
        let (client, catalog, id, running, metrics) = (client.clone(), Arc::clone(&catalog), cfg.id.clone(), Arc::clone(&running), Arc::clone(&cfg.metrics));
        tokio::spawn(async move {
            metrics.tasks_running.inc();
            let outcome = handle(client, catalog, &id, request.message, &running, &metrics).await;
            metrics.tasks_running.dec();
            metrics.count(outcome);
            drop(permit);
        });
    }
    ready(Some("draining: the worker is shutting down"));
    // No new tasks: the endpoints unsubscribe, so the queue groups skip this worker.
    drop(requests);
    let busy = slot_count as usize - slots.available_permits();
    tracing::info!(worker = %cfg.id, busy, "draining");
    let finished = tokio::time::timeout(drain_deadline, slots.acquire_many(slot_count)).await.is_ok();
    service.stop().await.map_err(|e| anyhow::anyhow!("stopping the NATS service: {e}"))?;
    client.flush().await.ok();
    println!("worker {} stopped: {}", cfg.id, if finished { "every task finished" } else { "the drain deadline passed with tasks running" });
    Ok(())
}

/// Cancel flags of the tasks being rendered, by reply subject.
type Running = Arc<Mutex<HashMap<String, CancelFlag>>>;

/// Publishes replies for one task on its reply subject.
#[derive(Clone)]
struct Replier {
    client: async_nats::Client,
    reply: async_nats::Subject,
    worker: String,
}

impl Replier {
    async fn send(&self, kind: &'static str, extra: &[(&'static str, String)], payload: bytes::Bytes) {
        let mut headers = HeaderMap::new();
        headers.insert(KIND, kind);
        headers.insert(WORKER, self.worker.as_str());
        for (k, v) in extra {
            headers.insert(*k, v.as_str());
        }
        if let Err(e) = self.client.publish_with_headers(self.reply.clone(), headers, payload).await {
            tracing::debug!("replying: {e}");
        }
    }
}

/// One task: accept, keep saying `working`, render, send the result (or an error).
/// Returns its outcome (an [`OutcomeLabel`]).
async fn handle(client: async_nats::Client, catalog: Arc<Catalog>, id: &str, message: async_nats::Message, running: &Running, metrics: &WorkerMetrics) -> &'static str {
    let Some(reply) = message.reply.clone() else { return "refused" };
    let replier = Replier { client: client.clone(), reply, worker: id.to_owned() };
    let parsed = if message.payload.len() > MAX_TASK_BYTES {
        Err(format!("task of {} bytes refused (limit {MAX_TASK_BYTES})", message.payload.len()))
    } else {
        serde_json::from_slice::<TaskMessage>(&message.payload).map_err(|e| format!("unreadable task: {e}"))
    };
    let msg = match parsed {
        Ok(m) => m,
        Err(e) => {
            tracing::warn!("{e}");
            replier.send("error", &[], e.into_bytes().into()).await;
            return "refused";
        }
    };
    let ids = vec![(TASK, task_header(msg.task.id)), (ATTEMPT, msg.attempt.to_string())];
    if !catalog.assets.contains_key(&msg.task.asset) {
        let why = format!("worker {id} has no asset {:?} (it serves {})", msg.task.asset, catalog.asset_names().join(", "));
        replier.send("error", &ids, why.into_bytes().into()).await;
        return "refused";
    }
    replier.send("accepted", &ids, bytes::Bytes::new()).await;
    let keepalive = {
        let (replier, ids) = (replier.clone(), ids.clone());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(KEEPALIVE);
            loop {
                tick.tick().await;
                replier.send("working", &ids, bytes::Bytes::new()).await;
            }
        })
    };
    let started = Instant::now();
    let task = msg.task;
    let with_depth = task.needs_depth;
    let cancel = CancelFlag::default();
    let key = replier.reply.to_string();
    running.lock().unwrap_or_else(|e| e.into_inner()).insert(key.clone(), cancel.clone());
    let cancelled = cancel.clone();
    let result = tokio::task::spawn_blocking(move || render_task(&catalog, &task, &cancel)).await;
    running.lock().unwrap_or_else(|e| e.into_inner()).remove(&key);
    keepalive.abort();
    let outcome = match result.map_err(|e| e.to_string()).and_then(|r| r.frames.map(|f| (f, r.render_ms))) {
        Ok((frames, render_ms)) => {
            metrics.render_seconds.observe(render_ms / 1e3);
            let (sizes, chunks) = result_chunks(&frames, with_depth);
            metrics.result_bytes.inc_by(chunks.iter().map(|c| c.len() as u64).sum());
            let n = chunks.len();
            for (i, chunk) in chunks.into_iter().enumerate() {
                let mut extra = ids.clone();
                extra.push((CHUNK, format!("{i}/{n}")));
                if i == 0 {
                    extra.push((VIEWS, serde_json::to_string(&sizes).expect("sizes serialise")));
                    extra.push((RENDER_MS, format!("{render_ms:.3}")));
                }
                replier.send("chunk", &extra, chunk).await;
            }
            tracing::debug!(worker = id, ms = started.elapsed().as_secs_f64() * 1e3, "task done");
            "rendered"
        }
        Err(e) => {
            replier.send("error", &ids, e.into_bytes().into()).await;
            if cancelled.is_cancelled() { "cancelled" } else { "failed" }
        }
    };
    let _ = client.flush().await;
    outcome
}
