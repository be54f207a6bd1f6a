//! `nephele serve` (the main job: signaling, a master and the pages in one process),
//! `nephele master` (a master registering with a separate signaling server) and
//! `nephele signal` (signaling alone).

use std::sync::Arc;

use anyhow::{Context, Result};
use nephele_limits::ConnLimits;

use nephele_core::{Admission, CoreConfig, scheduler::RenderScale};
use nephele_farm::{
    assets::{BackendChoice, DEFAULT_SCENES, make_backend},
    catalog::Catalog,
    protocol::Farm,
    worker::{NatsAuth, WorkerConfig},
};
use nephele_master::{
    self as master, MasterConfig, compositor::ComposeChoice, driver::NatsSettings, encoder::DEFAULT_BITS_PER_PIXEL, metrics::MasterMetrics, web,
};
use nephele_protocol::ice::{IceConfig, IceUrl, TurnAuth};
use nephele_rtc::{RtcConfig, UdpPorts};
use nephele_signaling::Health;

use super::lifecycle::{DrainArgs, say, stop_signal};
use nephele_master::Lifecycle;

/// What a master serves and how it schedules.
#[derive(clap::Args, Debug, Clone)]
pub struct MasterOptions {
    /// Scenes to serve: `name=asset` or an asset (a .nolf path or builtin:<scene>[-small]);
    /// repeat for several. The first is the default.
    #[arg(long = "scene", default_values = DEFAULT_SCENES)]
    pub scenes: Vec<String>,
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: BackendChoice,
    #[command(flatten)]
    pub knobs: nephele_farm::assets::RenderKnobs,
    /// Sessions this master accepts at once (a hard cap; admission by load comes first).
    #[arg(long, default_value_t = 8)]
    pub capacity: u32,
    /// The masters' secret this master presents when it registers with signaling (its
    /// `--master-token`); `nephele serve` makes one of its own.
    #[arg(long, env = "NEPHELE_MASTER_TOKEN", hide_env_values = true)]
    pub master_token: Option<String>,
    /// Offer loopback ICE candidates only (a browser on this machine, tests).
    #[arg(long)]
    pub loopback_only: bool,
    /// Public IP(s) to advertise in ICE candidates (server behind 1:1 NAT, or in a
    /// container whose UDP port is forwarded from the host).
    #[arg(long, env = "NEPHELE_PUBLIC_IP", value_delimiter = ',', value_parser = parse_public_ip)]
    pub public_ip: Vec<String>,
    /// UDP for the media: `N` carries every session over the one port N (open just that
    /// in a firewall or a Kubernetes Service); `MIN-MAX` gives each session its own port
    /// in the range. Default: any ephemeral port.
    #[arg(long, value_name = "N|MIN-MAX", value_parser = parse_udp_ports)]
    pub rtc_port: Option<UdpPorts>,
    #[command(flatten)]
    pub ice: IceArgs,
    /// Render at this fraction of the stream size and upscale (1 = exact), or `auto`:
    /// dynamic resolution, lowered fairly across users so the farm keeps up, and so that one
    /// frame renders in about --frame-budget-ms.
    #[arg(long, default_value = "auto")]
    pub render_scale: String,
    /// Render-time target of `--render-scale auto`, ms.
    #[arg(long, default_value_t = 30.0)]
    pub frame_budget_ms: f64,
    /// Render each user's frame as its own task instead of batching the views of users of
    /// one scene into one render task per round (NEPHELE §6.2.1, the default).
    #[arg(long)]
    pub no_batching: bool,
    /// Deprecated spelling: `--batching false` is `--no-batching`.
    #[arg(long, hide = true, action = clap::ArgAction::Set)]
    pub batching: Option<bool>,
    /// A frame whose pose is nearly a pose period old may wait up to this share of the
    /// period for the next pose, so it shows a fresh one (0: never waits; at most 0.5).
    #[arg(long, default_value_t = nephele_core::POSE_LATCH, value_parser = nephele_core::parse_pose_latch)]
    pub pose_latch: f64,
    /// `load`: refuse joins while a user starves or when the measured farm could not serve
    /// the newcomer at the lowest scale (NEPHELE Algorithm 1); `open`: admit up to
    /// --capacity whatever the load (for benchmarks of overload).
    #[arg(long, value_enum, default_value = "load")]
    pub admission: Admission,
    /// In-process render workers (threads sharing the backend).
    #[arg(long, default_value_t = 1)]
    pub workers: usize,
    /// Where the objects of a multi-object scene are composed by depth.
    #[arg(long, value_enum, default_value = "cpu")]
    pub compose: ComposeChoice,
    /// Video bits per pixel per frame: quality against bandwidth (kept within 0.3–20 Mbit/s).
    #[arg(long, default_value_t = DEFAULT_BITS_PER_PIXEL)]
    pub bits_per_pixel: f64,
    #[command(flatten)]
    pub nats: NatsArgs,
}

/// Where the NATS render farm is and how to log in to it.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct NatsArgs {
    /// Render on `nephele worker` processes reached through this NATS server (e.g.
    /// nats://10.0.0.5:4222) instead of in this process.
    #[arg(long)]
    pub nats: Option<String>,
    /// NATS token (as `nats-server --auth`); better given in the environment.
    #[arg(long, env = "NEPHELE_NATS_TOKEN", hide_env_values = true)]
    pub nats_token: Option<String>,
    /// NATS user (with --nats-password).
    #[arg(long, env = "NEPHELE_NATS_USER")]
    pub nats_user: Option<String>,
    #[arg(long, env = "NEPHELE_NATS_PASSWORD", hide_env_values = true)]
    pub nats_password: Option<String>,
    /// NATS credentials file (JWT + NKey, for NATS accounts).
    #[arg(long, env = "NEPHELE_NATS_CREDS")]
    pub nats_creds: Option<std::path::PathBuf>,
}

impl NatsArgs {
    pub fn auth(&self) -> Result<NatsAuth> {
        let user = match (&self.nats_user, &self.nats_password) {
            (Some(u), Some(p)) => Some((u.clone(), p.clone())),
            (None, None) => None,
            _ => anyhow::bail!("--nats-user and --nats-password go together"),
        };
        Ok(NatsAuth { token: self.nats_token.clone(), user, creds_file: self.nats_creds.clone() })
    }

    pub fn settings(&self) -> Result<Option<NatsSettings>> {
        Ok(match &self.nats {
            Some(url) => Some(NatsSettings { url: url.clone(), auth: self.auth()? }),
            None => None,
        })
    }
}

impl MasterOptions {
    /// Whether views are batched: on unless `--no-batching` (or the old `--batching false`,
    /// which still works, with a warning).
    fn batching(&self) -> bool {
        match self.batching {
            Some(b) => {
                say("warn", &format!("`--batching {b}` is deprecated; batching is on by default and `--no-batching` turns it off"));
                b && !self.no_batching
            }
            None => !self.no_batching,
        }
    }

    /// Loads the scenes on the chosen backend and builds the master's configuration.
    pub fn load(&self, name: &str) -> Result<(Arc<Catalog>, MasterConfig)> {
        let render_scale = RenderScale::parse(&self.render_scale, self.frame_budget_ms).map_err(anyhow::Error::msg)?;
        nephele_master::encoder::check_bits_per_pixel(self.bits_per_pixel).map_err(anyhow::Error::msg)?;
        let nats = self.nats.settings()?;
        // With a NATS farm the workers render; the master only needs the scenes' shapes.
        let backend = if nats.is_some() { Box::new(nephele_renderer::FastCpuBackend) } else { make_backend(self.backend)? };
        let settings = self.knobs.settings()?;
        settings.validate().map_err(anyhow::Error::msg)?;
        say("info", &format!("preparing {} scene(s) on {} ...", self.scenes.len(), backend.name()));
        let catalog = Arc::new(Catalog::load(&self.scenes, backend.as_ref(), settings)?);
        let cfg = MasterConfig {
            name: name.into(),
            token: self.master_token.clone(),
            rtc: RtcConfig { loopback_only: self.loopback_only, public_ips: self.public_ip.clone(), udp: self.rtc_port.unwrap_or_default(), ice: self.ice.config()? },
            core: CoreConfig { capacity: self.capacity, render_scale, batching: self.batching(), admission: self.admission, pose_latch: self.pose_latch, ..Default::default() },
            workers: self.workers,
            compose: self.compose,
            bits_per_pixel: self.bits_per_pixel,
            nats,
        };
        Ok((catalog, cfg))
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct ServeArgs {
    /// HTTP address for the pages and signaling; port 0 picks a free port.
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen: String,
    /// The clients' secret: a page joins only with `?token=…` (`None`: anyone may join).
    #[arg(long, env = "NEPHELE_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// The operators' secret for /status and /metrics (`Authorization: Bearer …`); without
    /// it they answer loopback addresses only.
    #[arg(long, env = "NEPHELE_OPERATOR_TOKEN", hide_env_values = true)]
    pub operator_token: Option<String>,
    #[command(flatten)]
    pub limits: LimitArgs,
    #[command(flatten)]
    pub drain: DrainArgs,
    #[command(flatten)]
    pub master: MasterOptions,
}

fn parse_udp_ports(text: &str) -> Result<UdpPorts, String> {
    text.parse()
}

fn parse_ice_url(text: &str) -> Result<IceUrl, String> {
    text.parse()
}

/// STUN and TURN servers: handed to every client in `joined` (by signaling) and used by the
/// master's own peer connections.
#[derive(clap::Args, Debug, Clone, Default)]
pub struct IceArgs {
    /// A STUN or TURN server: `stun:HOST[:PORT]`, `turn:HOST[:PORT][?transport=udp|tcp]`,
    /// `turns:HOST[:PORT]` (TLS); repeat, or separate with commas.
    #[arg(long = "ice-server", value_name = "URL", env = "NEPHELE_ICE_SERVERS", value_delimiter = ',', value_parser = parse_ice_url)]
    pub ice_servers: Vec<IceUrl>,
    /// Static TURN username (with --turn-credential), the same for every session.
    #[arg(long, env = "NEPHELE_TURN_USERNAME")]
    pub turn_username: Option<String>,
    /// Static TURN password.
    #[arg(long, env = "NEPHELE_TURN_CREDENTIAL", hide_env_values = true)]
    pub turn_credential: Option<String>,
    /// The secret shared with the TURN server (coturn: `use-auth-secret`,
    /// `static-auth-secret`): each session gets its own credential that expires, and the
    /// secret never leaves this server.
    #[arg(long, env = "NEPHELE_TURN_SECRET", hide_env_values = true, conflicts_with_all = ["turn_username", "turn_credential"])]
    pub turn_secret: Option<String>,
    /// Lifetime of a minted TURN credential, seconds (a relayed session longer than this
    /// loses its relay when the TURN server next checks).
    #[arg(long, default_value_t = 86_400)]
    pub turn_ttl: u64,
}

impl IceArgs {
    pub fn config(&self) -> Result<IceConfig> {
        let turn = match (&self.turn_secret, &self.turn_username, &self.turn_credential) {
            (Some(secret), _, _) => TurnAuth::Secret { secret: secret.clone(), ttl_s: self.turn_ttl },
            (None, Some(u), Some(c)) => TurnAuth::Static { username: u.clone(), credential: c.clone() },
            (None, None, None) => TurnAuth::None,
            _ => anyhow::bail!("--turn-username and --turn-credential go together"),
        };
        IceConfig::new(self.ice_servers.clone(), turn).map_err(anyhow::Error::msg)
    }
}

/// What the HTTP/websocket server allows each connection and address (defaults:
/// `nephele_limits::ConnLimits` and the signaling rate limits; README "Limits").
#[derive(clap::Args, Debug, Clone)]
pub struct LimitArgs {
    /// Open connections at once (more are closed on accept).
    #[arg(long, default_value_t = ConnLimits::default().max_connections)]
    pub max_connections: usize,
    /// Open connections at once from one IP address.
    #[arg(long, default_value_t = ConnLimits::default().max_connections_per_address)]
    pub max_connections_per_address: usize,
    /// An HTTP request's headers must arrive within this many ms (also the keep-alive idle time).
    #[arg(long, default_value_t = ConnLimits::default().header_timeout_ms)]
    pub header_timeout_ms: u64,
    /// A websocket must send `join`/`register` within this many ms.
    #[arg(long, default_value_t = ConnLimits::default().hello_timeout_ms)]
    pub hello_timeout_ms: u64,
    /// A websocket silent (no message, no pong) for this many ms is closed.
    #[arg(long, default_value_t = ConnLimits::default().idle_timeout_ms)]
    pub idle_timeout_ms: u64,
    /// Sessions from one IP address that may be joined but not yet connected.
    #[arg(long, default_value_t = ConnLimits::default().max_pending_joins_per_address)]
    pub max_pending_joins_per_address: usize,
    /// New sessions one IP address may start in a burst…
    #[arg(long, default_value_t = ConnLimits::default().join_burst_per_address)]
    pub join_burst_per_address: u32,
    /// …and per minute after it (beyond: `rate_limited`).
    #[arg(long, default_value_t = ConnLimits::default().joins_per_address_per_minute)]
    pub joins_per_address_per_minute: u32,
    /// Read and write buffer of each websocket, bytes.
    #[arg(long, default_value_t = ConnLimits::default().ws_buffer_bytes)]
    pub ws_buffer_bytes: usize,
    /// Signaling messages per second a client connection may send on average…
    #[arg(long, default_value_t = nephele_limits::CLIENT_SIGNAL_MESSAGES_PER_S)]
    pub client_messages_per_s: f64,
    /// …and in one burst (beyond: `rate_limited` and disconnected).
    #[arg(long, default_value_t = nephele_limits::CLIENT_SIGNAL_MESSAGE_BURST)]
    pub client_message_burst: f64,
}

impl LimitArgs {
    /// The connection limits `serve` and `signal` use without flags.
    pub fn default_limits() -> ConnLimits {
        ConnLimits::default()
    }

    /// Signaling's settings with these limits and `secrets` (token, master token, operator token).
    pub fn hub(&self, token: Option<String>, master_token: Option<String>, operator_token: Option<String>) -> Result<nephele_signaling::HubConfig> {
        let limits = ConnLimits {
            max_connections: self.max_connections,
            max_connections_per_address: self.max_connections_per_address,
            header_timeout_ms: self.header_timeout_ms,
            hello_timeout_ms: self.hello_timeout_ms,
            idle_timeout_ms: self.idle_timeout_ms,
            max_pending_joins_per_address: self.max_pending_joins_per_address,
            join_burst_per_address: self.join_burst_per_address,
            joins_per_address_per_minute: self.joins_per_address_per_minute,
            ws_buffer_bytes: self.ws_buffer_bytes,
        };
        if limits.max_connections == 0 || limits.max_connections_per_address == 0 {
            anyhow::bail!("--max-connections and --max-connections-per-address must be at least 1");
        }
        if limits.join_burst_per_address == 0 || limits.joins_per_address_per_minute == 0 {
            anyhow::bail!("--join-burst-per-address and --joins-per-address-per-minute must be at least 1");
        }
        if !(self.client_messages_per_s > 0.0 && self.client_message_burst >= 1.0) {
            anyhow::bail!("--client-messages-per-s must be > 0 and --client-message-burst ≥ 1");
        }
        Ok(nephele_signaling::HubConfig {
            token,
            master_token,
            operator_token,
            client_messages_per_s: self.client_messages_per_s,
            client_message_burst: self.client_message_burst,
            limits,
            ..Default::default()
        })
    }
}

impl ServeArgs {
    /// `nephele serve` with every default (what `nephele` alone runs).
    pub fn default_args() -> Self {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Just {
            #[command(flatten)]
            serve: ServeArgs,
        }
        Just::parse_from(["nephele"]).serve
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct MasterArgs {
    /// Signaling websocket, e.g. ws://host:8000/signal.
    #[arg(long)]
    pub signal: String,
    /// Name shown in signaling's /status.
    #[arg(long, default_value = "master")]
    pub name: String,
    /// Serve GET /metrics (Prometheus), /healthz and /readyz on this address.
    #[arg(long)]
    pub metrics_listen: Option<String>,
    #[command(flatten)]
    pub drain: DrainArgs,
    #[command(flatten)]
    pub master: MasterOptions,
}

#[derive(clap::Args, Debug, Clone)]
pub struct SignalArgs {
    /// Address to listen on; port 0 picks a free port (printed).
    #[arg(long, default_value = "127.0.0.1:8000")]
    pub listen: String,
    /// The clients' secret (`join`); `None`: anyone may join.
    #[arg(long, env = "NEPHELE_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// The masters' secret (`register`), never the clients'; needed whenever `--token` is.
    #[arg(long, env = "NEPHELE_MASTER_TOKEN", hide_env_values = true)]
    pub master_token: Option<String>,
    /// The operators' secret for /status (`Authorization: Bearer …`); without it /status
    /// answers loopback addresses only.
    #[arg(long, env = "NEPHELE_OPERATOR_TOKEN", hide_env_values = true)]
    pub operator_token: Option<String>,
    /// Also serve GET /metrics, /healthz and /readyz without a token on this (internal)
    /// address, for Prometheus and probes; `--listen` serves them too, /metrics for the
    /// operator only.
    #[arg(long)]
    pub metrics_listen: Option<String>,
    #[command(flatten)]
    pub limits: LimitArgs,
    #[command(flatten)]
    pub ice: IceArgs,
    #[command(flatten)]
    pub drain: DrainArgs,
}

pub fn serve(args: ServeArgs) -> Result<()> {
    let (catalog, cfg) = args.master.load("local")?;
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(&args.listen).await.with_context(|| format!("binding {}", args.listen))?;
        let names = catalog.names().join(", ");
        let backend = catalog.backend_name.clone();
        let mut hub = args.limits.hub(args.token.clone(), args.master.master_token.clone(), args.operator_token.clone())?;
        hub.ice = cfg.rtc.ice.clone();
        let life = Lifecycle { stop: Box::pin(stop_signal("serve")), drain_deadline: args.drain.deadline(), ..Lifecycle::default() };
        let (server, master) = web::spawn_local_until(listener, catalog, cfg, hub, life).await?;
        let addr = server.addr;
        println!("Nephele is serving {names} on {backend} — open http://{addr}/ (AR: http://{addr}/ar.html, metrics: http://{addr}/metrics)");
        let drained = master.await.context("the master task failed")?;
        // Signaling, in this process, has heard every session end from the master: once
        // it has told their clients, it closes every websocket properly.
        server.signaling.drain();
        let told_by = tokio::time::Instant::now() + std::time::Duration::from_secs(1);
        while server.signaling.stats().sessions > 0 && tokio::time::Instant::now() < told_by {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
        }
        server.signaling.close_all(std::time::Duration::from_secs(1)).await;
        drained?;
        say("info", "stopped");
        Ok(())
    })
}

pub fn master(args: MasterArgs) -> Result<()> {
    let (catalog, cfg) = args.master.load(&args.name)?;
    let metrics = Arc::new(MasterMetrics::new());
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        let life = Lifecycle { stop: Box::pin(stop_signal("master")), drain_deadline: args.drain.deadline(), ..Lifecycle::default() };
        if let Some(listen) = &args.metrics_listen {
            let listener = tokio::net::TcpListener::bind(listen).await.with_context(|| format!("binding {listen}"))?;
            println!("metrics on http://{}/metrics (health: /healthz, /readyz)", listener.local_addr()?);
            // Bind it to loopback or a private network: it has no token of its own.
            let m = Arc::clone(&metrics);
            tokio::spawn(web::serve_metrics(listener, move || m.encode(), life.health.clone()));
        }
        master::run_with(args.signal, cfg, catalog, metrics, life).await?;
        say("info", "stopped");
        Ok(())
    })
}

pub fn signal(args: SignalArgs) -> Result<()> {
    if args.token.is_some() && args.master_token.is_none() {
        anyhow::bail!("--token guards joins; masters need their own secret too: give --master-token (masters never accept the clients' token)");
    }
    let mut cfg = args.limits.hub(args.token, args.master_token, args.operator_token)?;
    cfg.ice = args.ice.config()?;
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async {
        let listener = tokio::net::TcpListener::bind(&args.listen).await.with_context(|| format!("binding {}", args.listen))?;
        let addr = listener.local_addr()?;
        println!("signaling on ws://{addr}/signal (status: http://{addr}/status, health: /healthz, /readyz) — the pages: http://{addr}/");
        let state = nephele_signaling::SignalState::new(cfg);
        state.spawn_tick_task();
        let gate = state.gate();
        let health = Health::default();
        if let Some(listen) = &args.metrics_listen {
            let listener = tokio::net::TcpListener::bind(listen).await.with_context(|| format!("binding {listen}"))?;
            println!("metrics on http://{}/metrics (health: /healthz, /readyz)", listener.local_addr()?);
            tokio::spawn(web::serve_metrics(listener, web::signaling_metrics(&state), health.clone()));
        }
        let app = web::signaling_router(state.clone()).merge(health.routes());
        let server = tokio::spawn(nephele_signaling::serve_limited(listener, app, gate));
        tokio::select! {
            ended = server => return ended.context("the signaling server task failed")?.context("signaling server failed"),
            () = stop_signal("signal") => {}
        }
        // Refuse joins; the sessions already paired stream on (their media is their
        // masters'); wait for those still connecting, then go.
        health.drain();
        state.drain();
        let deadline = tokio::time::Instant::now() + args.drain.deadline();
        while state.connecting() > 0 && tokio::time::Instant::now() < deadline {
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
        let connecting = state.connecting();
        state.close_all(std::time::Duration::from_secs(1)).await;
        say("info", &format!("stopped ({connecting} session(s) still connecting)"));
        Ok(())
    })
}

#[derive(clap::Args, Debug, Clone)]
pub struct WorkerArgs {
    /// Which farm: `heavy` takes heavy tasks one at a time, `light` packs light ones.
    #[arg(long, value_enum, default_value = "light")]
    pub farm: Farm,
    /// This worker's id in the farm (default: <farm>-<hostname>-<pid>).
    #[arg(long)]
    pub id: Option<String>,
    /// Scenes (and so assets) this worker renders: as for `serve`.
    #[arg(long = "scene", default_values = DEFAULT_SCENES)]
    pub scenes: Vec<String>,
    #[arg(long, value_enum, default_value = "auto")]
    pub backend: BackendChoice,
    /// With `--backend gpu`, render on a software Vulkan adapter (lavapipe) rather than
    /// refuse to start without a hardware GPU.
    #[arg(long)]
    pub allow_software_gpu: bool,
    #[command(flatten)]
    pub knobs: nephele_farm::assets::RenderKnobs,
    #[command(flatten)]
    pub nats: NatsArgs,
    /// Serve GET /metrics, /healthz and /readyz (NATS connected and taking tasks) on this
    /// address.
    #[arg(long)]
    pub metrics_listen: Option<String>,
    #[command(flatten)]
    pub drain: DrainArgs,
}

pub fn worker(args: WorkerArgs) -> Result<()> {
    let Some(url) = args.nats.nats.clone() else { anyhow::bail!("a worker needs --nats URL (the farm's NATS server)") };
    let settings = args.knobs.settings()?;
    settings.validate().map_err(anyhow::Error::msg)?;
    let backend = match args.backend {
        BackendChoice::Gpu if !args.allow_software_gpu => nephele_farm::assets::hardware_gpu_backend()?,
        choice => make_backend(choice)?,
    };
    say("info", &format!("preparing {} scene(s) on {} ...", args.scenes.len(), backend.name()));
    // A missing or corrupt asset stops the worker here, in words, before it takes any task.
    let catalog = Arc::new(Catalog::load(&args.scenes, backend.as_ref(), settings).context("this worker cannot serve its scenes")?);
    let host = std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_owned()).unwrap_or_else(|_| "host".into());
    let host: String = host.chars().filter(|c| c.is_ascii_alphanumeric() || *c == '-').take(32).collect();
    let id = args.id.clone().unwrap_or_else(|| format!("{}-{host}-{}", args.farm.as_str(), std::process::id()));
    let mut registry = nephele_signaling::metrics::registry("worker");
    let metrics = nephele_farm::worker::WorkerMetrics::register(&mut registry);
    let cfg = WorkerConfig { nats_url: url, auth: args.nats.auth()?, farm: args.farm, id, metrics };
    tokio::runtime::Runtime::new()?.block_on(async move {
        let health = Health::starting(&[("nats", "not serving tasks yet")]);
        if let Some(listen) = &args.metrics_listen {
            let listener = tokio::net::TcpListener::bind(listen).await.with_context(|| format!("binding {listen}"))?;
            println!("metrics on http://{}/metrics (health: /healthz, /readyz)", listener.local_addr()?);
            let registry = Arc::new(registry);
            tokio::spawn(web::serve_metrics(listener, move || nephele_signaling::metrics::encode_text(&registry), health.clone()));
        }
        let ready = |why: Option<&str>| match why {
            None => health.pass("nats"),
            Some(why) => health.fail("nats", why),
        };
        nephele_farm::worker::run_until(cfg, catalog, stop_signal("worker"), args.drain.deadline(), ready).await
    })
}

/// `--public-ip`: an IP address (not a host name: ICE candidates carry addresses).
fn parse_public_ip(text: &str) -> Result<String, String> {
    text.trim().parse::<std::net::IpAddr>().map(|ip| ip.to_string()).map_err(|_| format!("{text:?} is not an IP address (e.g. 203.0.113.7)"))
}
