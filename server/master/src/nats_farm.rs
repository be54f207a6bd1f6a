//! The master's side of the NATS render farm (`nephele serve|master --nats URL`): it finds
//! workers through the NATS service API (no static list), sends each task where the core
//! routed it (`crate::worker::protocol`), gathers the chunked results, and fails over.
//!
//! Failover: a task must be `accepted` within [`ACCEPT_TIMEOUT`], and its worker must say
//! `working` at least every [`SILENCE`] until the result is in. A worker that misses that
//! (killed, stopped, hung), answers garbage (malformed headers, a result of the wrong size)
//! or refuses the task has it re-issued to another worker that has the asset, chosen here
//! (never the one that failed), up to [`MAX_ATTEMPTS`]; the core hears one result per task
//! either way. Replies to an attempt that was re-issued are ignored. A worker that fails is
//! reported down at once and comes back when discovery sees it healthy again.

use std::{
    collections::{HashMap, HashSet},
    time::{Duration, Instant},
};

use anyhow::Result;
use bytes::Bytes;
use futures_util::StreamExt;
use tokio::sync::mpsc;

use nephele_core::task::{CANCELLED, RenderTask, TaskClass, TaskId, TaskResult, WorkerId};
use nephele_farm::{
    local::WorkerEvent,
    protocol::{
        CHUNK, Farm, KIND, RENDER_MS, SERVICE_NAME, TaskMessage, VIEWS, WORKER, WorkerAnnouncement, cancel_subject, farm_subject, frames_from, parse_chunk,
        parse_views, worker_subject,
    },
    worker::{NatsAuth, connect},
};

/// A task not accepted within this time is re-issued.
pub const ACCEPT_TIMEOUT: Duration = Duration::from_millis(200);
/// A rendering worker silent for this long is taken for dead.
pub const SILENCE: Duration = Duration::from_millis(160);
/// Attempts per task (the first and the re-issues).
pub const MAX_ATTEMPTS: u32 = 3;
/// Discovery asks every worker for its info this often…
pub const DISCOVERY_EVERY: Duration = Duration::from_millis(500);
/// …gathers answers for this long…
const DISCOVERY_WAIT: Duration = Duration::from_millis(150);
/// …and forgets a worker unseen for this long.
const FORGET_AFTER: Duration = Duration::from_millis(1600);
/// A worker that failed a task is not trusted again for this long, even if discovery sees it.
const SUSPECT_FOR: Duration = Duration::from_secs(2);
/// After (re)connecting, workers are trusted only after this long (their subscriptions are
/// being restored too).
const SETTLE: Duration = Duration::from_millis(600);
/// No task waits longer than this in all.
const TASK_DEADLINE: Duration = Duration::from_secs(30);
/// Most views a result may carry.
const MAX_RESULT_VIEWS: usize = 4096;

enum Command {
    Submit { worker: WorkerId, task: RenderTask },
    Cancel(TaskId),
}

/// Handle to the farm loop.
pub struct NatsFarm {
    commands: mpsc::UnboundedSender<Command>,
}

impl NatsFarm {
    /// Connects and starts discovery; worker events go to `report`.
    pub async fn start(url: &str, auth: &NatsAuth, name: &str, report: impl Fn(WorkerEvent) + Send + Sync + 'static) -> Result<Self> {
        let (conn_tx, conn_rx) = mpsc::unbounded_channel();
        let client = connect(url, auth, name, move |e| {
            let _ = conn_tx.send(e);
        })
        .await?;
        let prefix = client.new_inbox();
        let replies = client.subscribe(format!("{prefix}.>")).await.map_err(|e| anyhow::anyhow!("subscribing to our reply inbox: {e}"))?;
        let (commands, rx) = mpsc::unbounded_channel();
        let farm = FarmLoop { client, settle_until: None, connected: true, prefix, known: HashMap::new(), pending: HashMap::new(), report: Box::new(report) };
        tokio::spawn(farm.run(rx, replies, conn_rx));
        Ok(Self { commands })
    }

    pub fn submit(&self, worker: WorkerId, task: RenderTask) -> Result<(), RenderTask> {
        self.commands.send(Command::Submit { worker, task }).map_err(|e| match e.0 {
            Command::Submit { task, .. } => task,
            Command::Cancel(_) => unreachable!("sent a submit"),
        })
    }

    pub fn cancel(&self, task: TaskId) {
        let _ = self.commands.send(Command::Cancel(task));
    }
}

struct Known {
    info: WorkerAnnouncement,
    last_seen: Instant,
    /// The core was told it is up.
    up: bool,
    suspect_until: Option<Instant>,
}

struct Pending {
    task: RenderTask,
    attempt: u32,
    /// The worker it was sent to directly, if any (queue-group sends name none).
    sent_to: Option<String>,
    accepted_by: Option<String>,
    sent_at: Instant,
    first_sent: Instant,
    last_heard: Instant,
    failed: HashSet<String>,
    sizes: Option<Vec<nephele_farm::protocol::SentView>>,
    render_ms: f64,
    chunks: Vec<Option<Bytes>>,
}

struct FarmLoop {
    client: async_nats::Client,
    /// No worker is reported up before this (set when the connection comes back).
    settle_until: Option<Instant>,
    connected: bool,
    prefix: String,
    known: HashMap<String, Known>,
    pending: HashMap<TaskId, Pending>,
    report: Box<dyn Fn(WorkerEvent) + Send + Sync>,
}

fn class_farm(class: TaskClass) -> Farm {
    match class {
        TaskClass::Heavy => Farm::Heavy,
        TaskClass::Light => Farm::Light,
    }
}

impl FarmLoop {
    async fn run(
        mut self,
        mut commands: mpsc::UnboundedReceiver<Command>,
        mut replies: async_nats::Subscriber,
        mut connection: mpsc::UnboundedReceiver<async_nats::Event>,
    ) {
        let (found_tx, mut found) = mpsc::unbounded_channel::<Vec<WorkerAnnouncement>>();
        let mut discovery = tokio::time::interval(DISCOVERY_EVERY);
        let mut check = tokio::time::interval(Duration::from_millis(20));
        loop {
            tokio::select! {
                cmd = commands.recv() => match cmd {
                    None => return,
                    Some(Command::Submit { worker, task }) => self.submit(&worker, task).await,
                    Some(Command::Cancel(id)) => if let Some(p) = self.pending.remove(&id) {
                        if let Some(worker) = &p.accepted_by {
                            let reply = format!("{}.{}.{}", self.prefix, id.0, p.attempt);
                            if let Err(e) = self.client.publish(cancel_subject(worker), reply.into()).await {
                                tracing::debug!(task = %id, "telling {worker} to cancel: {e}");
                            }
                        }
                        (self.report)(WorkerEvent::Done(TaskResult::failed(id, CANCELLED)));
                    },
                },
                msg = replies.next() => match msg {
                    Some(msg) => self.reply(msg).await,
                    None => return,
                },
                Some(event) = connection.recv() => self.connection(event),
                Some(workers) = found.recv() => self.discovered(workers),
                _ = discovery.tick() => {
                    let (client, tx) = (self.client.clone(), found_tx.clone());
                    tokio::spawn(async move {
                        if let Ok(found) = discover(&client).await {
                            let _ = tx.send(found);
                        }
                    });
                }
                _ = check.tick() => self.check_deadlines().await,
            }
        }
    }

    fn connection(&mut self, event: async_nats::Event) {
        match event {
            async_nats::Event::Disconnected | async_nats::Event::Closed => {
                tracing::warn!("lost the NATS connection: every render worker is out of reach");
                self.connected = false;
                for (id, k) in &mut self.known {
                    if std::mem::take(&mut k.up) {
                        (self.report)(WorkerEvent::Down { worker: WorkerId(id.clone()), tasks_lost: false });
                    }
                }
            }
            async_nats::Event::Connected => {
                tracing::info!("NATS connection (re)established");
                self.connected = true;
                self.settle_until = Some(Instant::now() + SETTLE);
            }
            other => tracing::debug!("NATS: {other}"),
        }
    }

    fn discovered(&mut self, found: Vec<WorkerAnnouncement>) {
        let now = Instant::now();
        // Answers gathered across a disconnect, or before the workers' subscriptions are
        // back, say nothing reliable.
        if !self.connected || self.settle_until.is_some_and(|t| now < t) {
            return;
        }
        for info in found {
            let k = self.known.entry(info.id.clone()).or_insert(Known { info: info.clone(), last_seen: now, up: false, suspect_until: None });
            k.info = info;
            k.last_seen = now;
            if !k.up && k.suspect_until.is_none_or(|t| now >= t) {
                k.up = true;
                k.suspect_until = None;
                tracing::info!(worker = %k.info.id, farm = k.info.farm.as_str(), assets = %k.info.assets.join(","), "render worker up");
                (self.report)(WorkerEvent::Up {
                    worker: WorkerId(k.info.id.clone()),
                    rays_per_s: k.info.rays_per_s,
                    slots: k.info.slots,
                    farm: Some(match k.info.farm {
                        Farm::Heavy => TaskClass::Heavy,
                        Farm::Light => TaskClass::Light,
                    }),
                    assets: Some(k.info.assets.clone()),
                });
            }
        }
        let gone: Vec<String> = self.known.iter().filter(|(_, k)| now.duration_since(k.last_seen) > FORGET_AFTER).map(|(id, _)| id.clone()).collect();
        for id in gone {
            if self.known.remove(&id).is_some_and(|k| k.up) {
                tracing::warn!(worker = %id, "render worker gone (no discovery answer)");
                (self.report)(WorkerEvent::Down { worker: WorkerId(id), tasks_lost: false });
            }
        }
    }

    /// Sends a task where the core routed it: a light worker's farm queue group when that
    /// whole farm is healthy, else straight to the chosen worker.
    async fn submit(&mut self, worker: &WorkerId, task: RenderTask) {
        let now = Instant::now();
        let chosen = self.known.get(&worker.0);
        let healthy_farm = |farm: Farm| self.known.values().filter(|k| k.info.farm == farm && k.info.assets.contains(&task.asset)).all(|k| k.up);
        let subject = match chosen {
            Some(k) if k.info.farm == Farm::Light && healthy_farm(Farm::Light) => (farm_subject(Farm::Light, &task.asset), None),
            _ => (worker_subject(&worker.0), Some(worker.0.clone())),
        };
        let id = task.id;
        let pending = Pending {
            task,
            attempt: 0,
            sent_to: subject.1.clone(),
            accepted_by: None,
            sent_at: now,
            first_sent: now,
            last_heard: now,
            failed: HashSet::new(),
            sizes: None,
            render_ms: 0.0,
            chunks: Vec::new(),
        };
        self.pending.insert(id, pending);
        self.publish(id, subject.0).await;
    }

    async fn publish(&mut self, id: TaskId, subject: String) {
        let Some(p) = self.pending.get(&id) else { return };
        let reply = format!("{}.{}.{}", self.prefix, id.0, p.attempt);
        let body = serde_json::to_vec(&TaskMessage { attempt: p.attempt, task: p.task.clone() }).expect("tasks serialise");
        if let Err(e) = self.client.publish_with_reply(subject.clone(), reply, body.into()).await {
            tracing::debug!(task = %id, "publishing to {subject}: {e}");
        }
    }

    async fn reply(&mut self, msg: async_nats::Message) {
        // Subject: <prefix>.<task>.<attempt>
        let mut parts = msg.subject.rsplit('.');
        let (Some(attempt), Some(task)) = (parts.next().and_then(|a| a.parse::<u32>().ok()), parts.next().and_then(|t| t.parse::<u64>().ok())) else {
            return;
        };
        let id = TaskId(task);
        let Some(p) = self.pending.get_mut(&id) else {
            tracing::debug!(task = %id, "reply for a task that is done or was cancelled; ignored");
            return;
        };
        if p.attempt != attempt {
            tracing::debug!(task = %id, attempt, current = p.attempt, "reply to an attempt that was re-issued; ignored");
            return;
        }
        let now = Instant::now();
        p.last_heard = now;
        if msg.status.is_some_and(|s| s == async_nats::StatusCode::NO_RESPONDERS) {
            let who = p.sent_to.clone();
            self.fail(id, "no worker listens for it".into(), who).await;
            return;
        }
        let header = |name: &str| msg.headers.as_ref().and_then(|h| h.get(name)).map(|v| v.as_str().to_owned());
        let worker = header(WORKER);
        let kind = header(KIND).unwrap_or_default();
        match kind.as_str() {
            "accepted" => p.accepted_by = worker.or(p.accepted_by.take()),
            "working" => {}
            "error" => {
                let why = String::from_utf8_lossy(&msg.payload).chars().take(300).collect::<String>();
                let blame = worker.or(p.accepted_by.clone());
                self.fail(id, format!("worker refused: {why}"), blame).await;
            }
            "chunk" => {
                let blame = worker.clone().or(p.accepted_by.clone());
                match self.take_chunk(id, &msg) {
                    Ok(Some(result)) => {
                        self.pending.remove(&id);
                        (self.report)(WorkerEvent::Done(result));
                    }
                    Ok(None) => {}
                    Err(e) => self.fail(id, format!("garbage from the worker: {e}"), blame).await,
                }
            }
            other => {
                let blame = worker.or(p.accepted_by.clone());
                self.fail(id, format!("garbage from the worker: unknown reply kind {other:?}"), blame).await;
            }
        }
    }

    /// Stores one chunk; the whole result once every chunk is in.
    fn take_chunk(&mut self, id: TaskId, msg: &async_nats::Message) -> Result<Option<TaskResult>, String> {
        let p = self.pending.get_mut(&id).expect("checked by the caller");
        let header = |name: &str| msg.headers.as_ref().and_then(|h| h.get(name)).map(|v| v.as_str().to_owned());
        let (i, n) = parse_chunk(&header(CHUNK).ok_or("a chunk without Nephele-Chunk")?).map_err(|e| e.to_string())?;
        if p.chunks.is_empty() {
            p.chunks = vec![None; n];
        } else if p.chunks.len() != n {
            return Err(format!("chunk counts disagree ({} and {n})", p.chunks.len()));
        }
        if i == 0 {
            let sizes = parse_views(&header(VIEWS).ok_or("the first chunk has no Nephele-Views")?, MAX_RESULT_VIEWS).map_err(|e| e.to_string())?;
            let expected: Vec<(u32, u32)> = p.task.views.iter().map(|v| (v.view.intrinsics.width, v.view.intrinsics.height)).collect();
            if sizes.iter().map(|v| (v.width, v.height)).ne(expected.iter().copied()) {
                return Err("the result's view sizes are not the task's".into());
            }
            p.sizes = Some(sizes);
            p.render_ms = header(RENDER_MS).and_then(|m| m.parse::<f64>().ok()).filter(|m| m.is_finite() && *m >= 0.0).unwrap_or(0.0);
        }
        p.chunks[i] = Some(msg.payload.clone());
        if p.chunks.iter().any(Option::is_none) {
            return Ok(None);
        }
        let sizes = p.sizes.clone().ok_or("the first chunk never came")?;
        let joined: Vec<u8> = p.chunks.iter().flatten().flat_map(|c| c.iter().copied()).collect();
        let frames = frames_from(&sizes, &joined, p.task.needs_depth).map_err(|e| e.to_string())?;
        let round_trip_ms = p.sent_at.elapsed().as_secs_f64() * 1e3;
        let transfer_ms = (round_trip_ms - p.render_ms).max(0.0);
        Ok(Some(TaskResult { id, frames: Ok(frames), render_ms: p.render_ms, transfer_ms, bytes: joined.len() as u64, rendered_by: p.accepted_by.clone() }))
    }

    async fn check_deadlines(&mut self) {
        let now = Instant::now();
        let late: Vec<(TaskId, String, Option<String>)> = self
            .pending
            .iter()
            .filter_map(|(id, p)| {
                if now.duration_since(p.first_sent) > TASK_DEADLINE {
                    Some((*id, format!("no result within {} s", TASK_DEADLINE.as_secs()), p.accepted_by.clone()))
                } else if p.accepted_by.is_none() && now.duration_since(p.sent_at) > ACCEPT_TIMEOUT {
                    Some((*id, format!("not accepted within {} ms", ACCEPT_TIMEOUT.as_millis()), p.sent_to.clone()))
                } else if p.accepted_by.is_some() && now.duration_since(p.last_heard) > SILENCE {
                    let who = p.accepted_by.clone();
                    Some((*id, format!("worker {} went silent for {} ms", who.as_deref().unwrap_or("?"), SILENCE.as_millis()), who))
                } else {
                    None
                }
            })
            .collect();
        for (id, why, blame) in late {
            self.fail(id, why, blame).await;
        }
    }

    /// An attempt failed: blame its worker, re-issue elsewhere, or give the task up.
    async fn fail(&mut self, id: TaskId, why: String, blame: Option<String>) {
        let now = Instant::now();
        if let Some(w) = &blame {
            if let Some(k) = self.known.get_mut(w) {
                k.suspect_until = Some(now + SUSPECT_FOR);
                if std::mem::take(&mut k.up) {
                    tracing::warn!(worker = %w, task = %id, "{why}; taking the worker out of the farm");
                    (self.report)(WorkerEvent::Down { worker: WorkerId(w.clone()), tasks_lost: false });
                }
            }
        }
        let Some(p) = self.pending.get_mut(&id) else { return };
        if let Some(w) = blame {
            p.failed.insert(w);
        }
        let (class, attempt, asset, failed) = (p.task.class, p.attempt, p.task.asset.clone(), p.failed.clone());
        let load = |w: &str| self.pending.values().filter(|q| q.sent_to.as_deref() == Some(w) || q.accepted_by.as_deref() == Some(w)).count();
        let target = (attempt + 1 < MAX_ATTEMPTS)
            .then(|| {
                self.known
                    .values()
                    .filter(|k| k.up && k.info.assets.contains(&asset) && !failed.contains(&k.info.id))
                    .min_by_key(|k| (k.info.farm != class_farm(class), load(&k.info.id)))
                    .map(|k| k.info.id.clone())
            })
            .flatten();
        let p = self.pending.get_mut(&id).expect("still pending");
        let Some(target) = target else {
            let attempts = p.attempt + 1;
            self.pending.remove(&id);
            tracing::warn!(task = %id, attempts, "{why}; no other worker can take it");
            let message = format!("{why}; no other render worker could take the task after {attempts} attempt(s)");
            (self.report)(WorkerEvent::Done(TaskResult::failed(id, message)));
            return;
        };
        tracing::info!(task = %id, to = %target, "{why}; re-issuing");
        p.attempt += 1;
        p.sent_to = Some(target.clone());
        p.accepted_by = None;
        p.sent_at = now;
        p.last_heard = now;
        p.sizes = None;
        p.chunks.clear();
        self.publish(id, worker_subject(&target)).await;
    }
}

/// Asks every worker for its service info; gathers for [`DISCOVERY_WAIT`].
async fn discover(client: &async_nats::Client) -> Result<Vec<WorkerAnnouncement>> {
    let inbox = client.new_inbox();
    let mut answers = client.subscribe(inbox.clone()).await?;
    client.publish_with_reply(format!("$SRV.INFO.{SERVICE_NAME}"), inbox, Bytes::new()).await?;
    let until = tokio::time::Instant::now() + DISCOVERY_WAIT;
    let mut found = Vec::new();
    while let Ok(Some(msg)) = tokio::time::timeout_at(until, answers.next()).await {
        match serde_json::from_slice::<async_nats::service::Info>(&msg.payload) {
            Ok(info) => match WorkerAnnouncement::from_metadata(&info.metadata) {
                Some(a) => found.push(a),
                None => tracing::debug!("a {SERVICE_NAME} service with unreadable metadata: {:?}", info.metadata),
            },
            Err(e) => tracing::debug!("unreadable service info: {e}"),
        }
    }
    Ok(found)
}
