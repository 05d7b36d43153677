//! **esrp-server**: the ESRP environment server. A tonic gRPC service (`esrp.v1.Esrp`) hosting
//! many concurrent episodes, each with its own simulator state (esrp-core) and views rendered
//! in batches across all episodes by one render thread (esrp-render), on the built-in
//! benchmark esrp-bench-v2 or esrp-bench-v1 (`--benchmark`; scenes generated lazily by index) or a
//! dataset folder.
//!
//! # Module map
//!
//! - [`types`]: the values the episode layer speaks (ids, options, observations, answers); the
//!   leaf every other module may use.
//! - [`config`]: flags and environment variables.
//! - [`auth`]: who calls: the tokens (`--token`, `--tokens`) with their roles and quotas, and the
//!   interceptor that identifies each call's [`types::Caller`].
//! - [`records`]: the server's own `esrp.results/v1` records (`--records`) and the challenge's
//!   counted attempts.
//! - [`scenes`]: the served scenes, built lazily and cached.
//! - [`registry`]: a plain map from unguessable id to entry, each locked alone; limits; idle
//!   and unclaimed reaping.
//! - [`render`]: the render scheduler (one thread, batches of every waiting view; the renderer
//!   chunks them to its own limits).
//! - [`episodes`]: the protocol-free episode layer: [`episodes::Episodes`] creates, steps
//!   (batches and stream waves), resets, plans for and closes episodes in [`types`], its
//!   public methods listed in one `impl`.
//! - [`esrp_v1`]: the `esrp.v1.Esrp` adapter: tonic handlers, `TryFrom`/`From` conversions at
//!   its edge.
//! - [`dm_env`]: the `dm_env_rpc.v1.Environment` adapter, a sibling of `esrp_v1` over the same
//!   core.
//! - [`viewer`]: the web viewer (`--http-listen`), a third adapter: an axum server with an
//!   embedded page and a JSON/event-stream API over the same episodes.
//! - [`metrics`]: Prometheus metrics and their HTTP endpoint.
//! - [`error`]: typed errors and their one mapping to gRPC status codes.
//!
//! # Invariants
//!
//! - **The runtime never blocks on simulation or rendering.** Steps run on blocking threads
//!   (a whole batch per hop), scene generation and uploads too, and rendering on the render
//!   thread behind a channel.
//! - **Each episode is locked alone**; a batch locks its episodes in id order, so concurrent
//!   batches cannot deadlock. The registry's own lock is held only for map operations.
//! - **No proto type below the adapters**: [`episodes`], [`registry`], [`render`],
//!   [`records`] and [`scenes`] speak core types; only [`esrp_v1`] and [`dm_env`] know their
//!   protocols ([`auth`] knows tonic's interceptor, not the messages).
//! - **Policy at the episode layer's edge**: what a token may do is decided before a call moves
//!   anything (`episodes::access`, the registry's owner and quota checks); the simulator and
//!   the renderer know nothing of tokens.
//! - **No import circle**: `types` ← `error` ← {`auth`, `records`, `scenes`, `registry`, `render`} ← `episodes` ←
//!   the adapters ← the crate root (`scripts/module_cycles.py`, run by the tests).
//! - **No client input panics or stops the server**: every field is validated into a
//!   [`error::ServiceError`] with a precise status code and a message that says what to change.
//! - **Same scene and actions, same observations**, whatever else the server is doing: episodes
//!   share nothing mutable, and a batch renders each view as it would alone.

#![warn(missing_docs)]
// Proving the episode layer Send + Sync walks deep into wgpu's types.
#![recursion_limit = "256"]

pub mod auth;
pub mod config;
pub mod dm_env;
pub mod episodes;
pub mod error;
pub mod esrp_v1;
pub mod metrics;
pub mod records;
pub mod registry;
pub mod render;
pub mod scenes;
pub mod types;
pub mod viewer;

use std::future::Future;
use std::sync::Arc;

use tokio::net::TcpListener;
use tonic::service::interceptor::InterceptedService;

/// Generated protobuf messages and gRPC stubs of `esrp.v1` (from esrp-proto).
pub use esrp_proto::esrp::v1 as proto;

pub use config::Config;
pub use error::ServeError;

/// The tokens of `config`: `--tokens FILE`, `--token` (one admin) or none.
pub fn tokens_of(config: &Config) -> Result<auth::Tokens, ServeError> {
    Ok(match (&config.tokens, &config.token) {
        (Some(path), _) => auth::Tokens::from_file(path)?,
        (None, Some(secret)) => auth::Tokens::single_admin(secret),
        (None, None) => auth::Tokens::open(),
    })
}

/// Builds the episode layer: the scene store (with the hidden splits of `--challenge-seed`),
/// the records (`--records`, read back), the renderer and its thread.
pub fn build_episodes(config: &Config) -> Result<Arc<episodes::Episodes>, ServeError> {
    let mut store = match &config.dataset {
        Some(dir) => scenes::SceneStore::folder(dir)?,
        None => {
            let mut store = scenes::SceneStore::built_in(config.benchmark, config.bench_seed);
            let root = if config.no_scene_cache {
                None
            } else {
                config.scene_cache.clone().or_else(esrp_dataset::cache::default_root)
            };
            // A cache that cannot be made costs speed, never service.
            if let Some(root) = root
                && let Err(e) = store.keep_on_disk(&root)
            {
                tracing::warn!("no scene cache ({e}): every scene is generated on first use");
            }
            store
        }
    };
    if let Some(secret) = &config.challenge_seed {
        let hidden = scenes::HiddenSplits {
            secret: secret.clone(),
            version: config.benchmark,
            challenge: config.challenge_scenes as usize,
            minival: config.minival_scenes as usize,
        };
        store = store.with_hidden(&hidden).map_err(ServeError::Config)?;
    }
    if !config.no_generate_ahead {
        // Detached: it ends when every scene is on disk, or with the process.
        drop(store.generate_ahead());
    }
    let attempts = records::Attempts::default();
    let recorder = match &config.records {
        Some(dir) => Some(records::Recorder::open(dir, config.record, &attempts)?),
        None => None,
    };
    let backends = config.render_backend;
    let renderer = esrp_render::Renderer::new(esrp_render::RendererConfig { backends, ..Default::default() })?;
    let info = renderer.adapter_info();
    tracing::info!(adapter = %info.name, backend = ?info.backend, software = renderer.is_software(), "renderer ready");
    let metrics = Arc::new(metrics::Metrics::new());
    let render = render::RenderScheduler::start(renderer, metrics.clone());
    Ok(Arc::new(episodes::Episodes::new(store, render, config.clone(), metrics, recorder, attempts)))
}

/// The sockets a server serves on, bound by its caller (so that it can print their addresses).
pub struct Listeners {
    /// gRPC (esrp.v1, dm_env_rpc, health, reflection).
    pub grpc: TcpListener,
    /// Prometheus metrics (`--metrics-listen`).
    pub metrics: Option<TcpListener>,
    /// The web viewer (`--http-listen`).
    pub viewer: Option<TcpListener>,
}

/// Serves gRPC (and Prometheus metrics and the web viewer, where their listeners are given) until
/// `shutdown` completes, then drains in-flight calls for at most `--shutdown-grace-ms`.
pub async fn run(
    listeners: Listeners,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    let Listeners { grpc: listener, metrics: metrics_listener, viewer: viewer_listener } = listeners;
    let tokens = Arc::new(tokens_of(&config)?);
    let episodes = build_episodes(&config)?;
    let render = episodes.render.clone();
    let address = listener
        .local_addr()
        .map_err(|source| ServeError::Io { what: "the listener has no address".into(), source })?;
    tracing::info!(%address, dataset = episodes.store.name(), scenes = episodes.store.infos().len(), "serving esrp.v1");
    if tokens.required() {
        tracing::info!(tokens = %tokens.summary().join(", "), "calls need a bearer token");
    }
    if episodes.store.has_hidden() {
        let [by_split, ..] = episodes.store.counts();
        tracing::info!(
            challenge = by_split.get("challenge").copied().unwrap_or(0),
            minival = by_split.get("minival").copied().unwrap_or(0),
            "serving the hidden challenge splits"
        );
    }

    // Close idle episodes, and unclaimed ones (`Episodes::reap_unclaimed`).
    let reaper = {
        let episodes = episodes.clone();
        let (idle, claim) = (config.idle_timeout(), config.claim_timeout());
        let shortest = [idle, claim].into_iter().filter(|t| !t.is_zero()).min();
        tokio::spawn(async move {
            let Some(shortest) = shortest else { return }; // both 0: never reap
            let mut tick = tokio::time::interval(
                (shortest / 10).clamp(std::time::Duration::from_secs(1), std::time::Duration::from_secs(60)),
            );
            loop {
                tick.tick().await;
                if !idle.is_zero() {
                    let reaped = episodes.reap_idle(idle).await;
                    if reaped > 0 {
                        tracing::info!(reaped, "closed idle episodes");
                    }
                }
                if !claim.is_zero() {
                    let reaped = episodes.reap_unclaimed(claim).await;
                    if reaped > 0 {
                        tracing::info!(reaped, "closed episodes whose id no call named (their create was abandoned)");
                    }
                }
            }
        })
    };

    let metrics_server = metrics_listener.map(|listener| {
        let episodes = episodes.clone();
        let refresh = {
            let episodes = episodes.clone();
            move || {
                episodes.metrics.live.set(episodes.live() as i64);
            }
        };
        tokio::spawn(async move {
            if let Err(e) = metrics::serve(listener, episodes.metrics.clone(), refresh).await {
                tracing::error!("the metrics endpoint stopped: {e}");
            }
        })
    });

    let viewer_server = viewer_listener.map(|listener| {
        let (episodes, tokens) = (episodes.clone(), tokens.clone());
        tokio::spawn(async move {
            if let Err(e) = viewer::serve(listener, episodes, tokens).await {
                tracing::error!("the viewer stopped: {e}");
            }
        })
    });

    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<proto::esrp_server::EsrpServer<esrp_v1::EsrpService>>().await;
    health
        .set_serving::<dm_env::wire::dm_env_rpc::v1::environment_server::EnvironmentServer<dm_env::DmEnvService>>()
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(esrp_proto::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let dm_env = dm_env::server(episodes.clone());
    let esrp = proto::esrp_server::EsrpServer::new(esrp_v1::EsrpService::new(episodes.clone()))
        .max_decoding_message_size(config.max_message_bytes)
        .max_encoding_message_size(config.max_message_bytes);
    let check = auth::TokenCheck::new(tokens);

    let mut builder = tonic::transport::Server::builder();
    if let (Some(cert), Some(key)) = (&config.tls_cert, &config.tls_key) {
        let read = |flag: &str, path: &std::path::Path| {
            std::fs::read(path)
                .map_err(|source| ServeError::Io { what: format!("cannot read {flag} {}", path.display()), source })
        };
        let (cert, key) = (read("--tls-cert", cert)?, read("--tls-key", key)?);
        builder = builder.tls_config(
            tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(cert, key)),
        )?;
    }
    // The drain after the signal is bounded: a client that keeps a stream open (or a call
    // that does not end) would otherwise hold the server up for as long as it likes.
    let (signalled, on_signal) = tokio::sync::oneshot::channel::<()>();
    let shutdown = async move {
        shutdown.await;
        let _ = signalled.send(());
    };
    let grace = config.shutdown_grace();
    let drain_timeout = async move {
        if on_signal.await.is_err() {
            // The server ended without a signal: nothing to bound.
            std::future::pending::<()>().await;
        }
        tokio::time::sleep(grace).await;
    };
    let serve = builder
        .add_service(health_service)
        .add_service(reflection)
        .add_service(InterceptedService::new(esrp_v1::answered::Answered::new(esrp), check.clone()))
        .add_service(InterceptedService::new(dm_env, check))
        // TCP_NODELAY: an agent waits for each answer, so Nagle + delayed ACK would add ~40 ms a step.
        .serve_with_incoming_shutdown(
            tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true)),
            shutdown,
        );
    let result = tokio::select! {
        result = serve => result,
        () = drain_timeout => {
            // The connections still open are dropped with the runtime, after the render
            // thread has stopped (below): their clients see UNAVAILABLE.
            tracing::warn!(grace_ms = grace.as_millis() as u64, "calls or streams still open after the shutdown grace: stopping anyway");
            Ok(())
        }
    };
    // Shut down in order: the calls have drained (or the grace is over); end the background tasks, then render what
    // was submitted and join the render threads, so that no rendering runs while the process
    // exits (`main` then drops the runtime, and with it the episodes, before returning).
    reaper.abort();
    let _ = reaper.await;
    // Every episode still open ends here: its run is recorded as cut by the shutdown.
    let closed = episodes.close_all().await;
    if closed > 0 {
        tracing::info!(closed, "closed the episodes still open at shutdown");
    }
    for task in [metrics_server, viewer_server].into_iter().flatten() {
        task.abort();
        let _ = task.await;
    }
    if let Err(e) = tokio::task::spawn_blocking(move || render.stop()).await {
        tracing::error!("stopping the render thread failed: {e}");
    }
    tracing::info!("server stopped");
    Ok(result?)
}
