//! Starting and running the server: [`run`] (the library's entry point, which `main` calls with
//! its bound listeners and a shutdown signal), the steps it takes in order, and [`ServeError`],
//! why the server could not start or stopped serving.
//!
//! [`run`] reads top to bottom: the tokens and the episode layer are built, the background tasks
//! start (the reaper, the metrics endpoint, the viewer), the gRPC services are assembled behind
//! the token check (with TLS where configured), then it serves until the shutdown signal, drains
//! for at most `--shutdown-grace-ms`, and stops everything in order.

use std::future::Future;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_stream::Stream;
use tonic::service::interceptor::InterceptedService;

use crate::config::Config;
use crate::episodes::Episodes;
use crate::listen::{self, UnixSocket};
use crate::{auth, dm_env, esrp_v1, metrics, proto, records, render, scenes, viewer};

/// The target of the server's own log lines (start, serving, stop): the crate's, as when they
/// were written at its root, since operators filter (`ESRP_LOG`) and search logs by it.
const LOG_TARGET: &str = "esrp_server";

/// Why the server could not start, or stopped serving.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The dataset folder (`--dataset`) cannot be served.
    #[error("cannot serve the dataset folder: {0}")]
    Dataset(#[from] esrp_dataset::files::FilesError),
    /// No renderer could be created.
    #[error("cannot create the renderer: {0}")]
    Renderer(#[from] esrp_render::RenderError),
    /// A file or socket operation failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// The error.
        source: std::io::Error,
    },
    /// gRPC reflection could not be set up (a bug in the embedded descriptors).
    #[error("cannot set up gRPC reflection: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    /// The gRPC transport failed (TLS configuration, serving).
    #[error("gRPC transport: {0}")]
    Transport(#[from] tonic::transport::Error),
    /// The token file (`--tokens`) cannot be used.
    #[error(transparent)]
    Tokens(#[from] auth::TokensError),
    /// The records folder (`--records`) cannot be used.
    #[error(transparent)]
    Records(#[from] records::RecordsError),
    /// The flags contradict each other or the served dataset.
    #[error("{0}")]
    Config(String),
}

/// The tokens of `config`: `--tokens FILE`, `--token` (one admin) or none. A `--token` no client
/// could send is refused here rather than by the flag parser, whose message would quote it.
pub fn tokens_of(config: &Config) -> Result<auth::Tokens, ServeError> {
    Ok(match (&config.tokens, &config.token) {
        (Some(path), _) => auth::Tokens::from_file(path)?,
        (None, Some(secret)) => {
            auth::sendable_secret(secret)
                .map_err(|why| ServeError::Config(format!("--token (ESRP_TOKEN): the token {why}")))?;
            auth::Tokens::single_admin(secret)
        }
        (None, None) => auth::Tokens::open(),
    })
}

/// Builds the episode layer: the scene store (with the hidden splits of `--challenge-seed`),
/// the records (`--records`, read back), the renderer and its thread.
pub fn build_episodes(config: &Config) -> Result<Arc<Episodes>, ServeError> {
    let store = scene_store(config)?;
    if let (Some(dir), Some(_)) = (&config.records, &config.challenge_seed) {
        records::check_same_challenge(dir, &store.dataset_hash())?;
    }
    let attempts = records::Attempts::default();
    let recorder = match &config.records {
        Some(dir) => Some(records::Recorder::open(dir, config.record, &attempts, config.records_key.as_deref())?),
        None => None,
    };
    let (backends, rasterizer, timestamps, depth_buffers) =
        (config.render_backend, config.render_rasterizer, config.render_timestamps, config.render_depth_buffers);
    let devices = match config.render_devices {
        0 => render::AUTO_RENDER_DEVICES,
        n => usize::from(n),
    };
    let renderers = (0..devices)
        .map(|_| {
            esrp_render::Renderer::new(esrp_render::RendererConfig {
                backends,
                rasterizer,
                timestamps,
                depth_buffers,
                ..Default::default()
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let (info, software, timed) =
        (renderers[0].adapter_info(), renderers[0].is_software(), renderers[0].times_device());
    let threads = match config.render_threads {
        0 => render::AUTO_RENDER_THREADS * devices,
        n => usize::from(n),
    };
    let in_flight = match config.render_pipeline {
        0 => render::AUTO_RENDER_PIPELINE,
        n => usize::from(n),
    };
    tracing::info!(target: LOG_TARGET, adapter = %info.name, backend = ?info.backend, software, %rasterizer, gpu_timestamps = timed, %depth_buffers, render_devices = devices, render_threads = threads, render_pipeline = in_flight, "renderer ready");
    let metrics = Arc::new(metrics::Metrics::new());
    let render = render::RenderScheduler::start(renderers, metrics.clone(), threads, in_flight);
    let episodes = Arc::new(Episodes::new(store, render, config.clone(), metrics, recorder, attempts));
    let recovered = episodes.recover_attempts().map_err(|e| ServeError::Io {
        what: "recording the attempts a crash cut".into(),
        source: std::io::Error::other(e.to_string()),
    })?;
    if recovered > 0 {
        tracing::warn!(target: LOG_TARGET, recovered, "recorded the counted attempts an interruption cut, as ended at their last journaled step");
    }
    if let (Some(dir), Some(_)) = (&config.records, &config.challenge_seed) {
        let observations = serde_json::json!({
            "challenge": config.challenge_observations.as_str(),
            "minival": config.minival_observations.as_str(),
        });
        records::write_challenge_scenes(dir, &episodes.dataset_hash, observations, episodes.store.infos())?;
    }
    Ok(episodes)
}

/// The served scenes: the dataset folder, or the built-in benchmark with its scene cache (and
/// its generation ahead of use unless `--no-generate-ahead`), with the hidden splits of
/// `--challenge-seed`.
fn scene_store(config: &Config) -> Result<scenes::SceneStore, ServeError> {
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
                tracing::warn!(target: LOG_TARGET, "no scene cache ({e}): every scene is generated on first use");
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
    Ok(store)
}

/// The sockets a server serves on, bound by its caller (so that it can print their addresses).
pub struct Listeners {
    /// gRPC (esrp.v1, dm_env_rpc, health, reflection).
    pub grpc: TcpListener,
    /// Prometheus metrics (`--metrics-listen`).
    pub metrics: Option<TcpListener>,
    /// The web viewer (`--http-listen`).
    pub viewer: Option<TcpListener>,
    /// gRPC on a Unix domain socket too (`--listen-unix`); its file is removed as the server
    /// stops.
    pub unix: Option<UnixSocket>,
}

/// Serves gRPC (and Prometheus metrics and the web viewer, where their listeners are given) until
/// `shutdown` completes, then drains in-flight calls for at most `--shutdown-grace-ms`.
pub async fn run(
    listeners: Listeners,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    let Listeners { grpc: listener, metrics: metrics_listener, viewer: viewer_listener, unix } = listeners;
    let tokens = Arc::new(tokens_of(&config)?);
    let episodes = build_episodes(&config)?;
    let render = episodes.render.clone();
    let address = listener
        .local_addr()
        .map_err(|source| ServeError::Io { what: "the listener has no address".into(), source })?;
    log_serving(address, unix.as_ref().map(UnixSocket::path), &tokens, &episodes);
    let (unix, socket_file) = unix.map(UnixSocket::into_parts).unzip();

    let reaper = spawn_reaper(episodes.clone(), config.idle_timeout(), config.claim_timeout());
    let metrics_server = metrics_listener.map(|listener| spawn_metrics(listener, episodes.clone()));
    let viewer_server = viewer_listener.map(|listener| spawn_viewer(listener, episodes.clone(), tokens.clone()));

    let result = serve_grpc(listen::incoming(listener, unix), &config, &episodes, tokens, shutdown).await;
    // No longer listening: a client that comes now is refused, and the next server may bind.
    drop(socket_file);

    // Shut down in order: the calls have drained (or the grace is over); end the background
    // tasks, then render what was submitted and join the render threads, so that no rendering
    // runs while the process exits (`main` then drops the runtime, and with it the episodes,
    // before returning).
    stop_task(reaper).await;
    // Every episode still open ends here: its run is recorded as cut by the shutdown.
    let closed = episodes.close_all().await;
    if closed > 0 {
        tracing::info!(target: LOG_TARGET, closed, "closed the episodes still open at shutdown");
    }
    for task in [metrics_server, viewer_server].into_iter().flatten() {
        stop_task(task).await;
    }
    if let Err(e) = tokio::task::spawn_blocking(move || render.stop()).await {
        tracing::error!(target: LOG_TARGET, "stopping the render thread failed: {e}");
    }
    tracing::info!(target: LOG_TARGET, "server stopped");
    result
}

/// Logs what is served, where, and to whom.
fn log_serving(address: std::net::SocketAddr, unix: Option<&Path>, tokens: &auth::Tokens, episodes: &Episodes) {
    tracing::info!(target: LOG_TARGET, %address, dataset = episodes.store.name(), scenes = episodes.store.infos().len(), "serving esrp.v1");
    if let Some(path) = unix {
        tracing::info!(target: LOG_TARGET, path = %path.display(), "serving on a Unix domain socket too");
    }
    if tokens.required() {
        tracing::info!(target: LOG_TARGET, tokens = %tokens.summary().join(", "), "calls need a bearer token");
    }
    if episodes.store.has_hidden() {
        let [by_split, ..] = episodes.store.counts();
        tracing::info!(
            target: LOG_TARGET,
            challenge = by_split.get("challenge").copied().unwrap_or(0),
            minival = by_split.get("minival").copied().unwrap_or(0),
            "serving the hidden challenge splits"
        );
    }
}

/// Closes idle episodes (`--idle-timeout-seconds`) and unclaimed ones (`Episodes::reap_unclaimed`,
/// `--claim-timeout-seconds`), checking ten times per shortest timeout (between 1 s and 60 s). A zero
/// timeout never reaps; with both zero the task ends at once.
fn spawn_reaper(episodes: Arc<Episodes>, idle: Duration, claim: Duration) -> JoinHandle<()> {
    let shortest = [idle, claim].into_iter().filter(|t| !t.is_zero()).min();
    tokio::spawn(async move {
        let Some(shortest) = shortest else { return }; // both 0: never reap
        let mut tick = tokio::time::interval((shortest / 10).clamp(Duration::from_secs(1), Duration::from_secs(60)));
        loop {
            tick.tick().await;
            if !idle.is_zero() {
                let reaped = episodes.reap_idle(idle).await;
                if reaped > 0 {
                    tracing::info!(target: LOG_TARGET, reaped, "closed idle episodes");
                }
            }
            if !claim.is_zero() {
                let reaped = episodes.reap_unclaimed(claim).await;
                if reaped > 0 {
                    tracing::info!(target: LOG_TARGET, reaped, "closed episodes whose id no call named (their create was abandoned)");
                }
            }
        }
    })
}

/// Serves the Prometheus metrics on `listener`, the live-episode gauge refreshed at each scrape.
fn spawn_metrics(listener: TcpListener, episodes: Arc<Episodes>) -> JoinHandle<()> {
    let refresh = {
        let episodes = episodes.clone();
        move || {
            episodes.metrics.live.set(episodes.live() as i64);
        }
    };
    tokio::spawn(async move {
        if let Err(e) = metrics::serve(listener, episodes.metrics.clone(), refresh).await {
            tracing::error!(target: LOG_TARGET, "the metrics endpoint stopped: {e}");
        }
    })
}

/// Serves the web viewer on `listener`.
fn spawn_viewer(listener: TcpListener, episodes: Arc<Episodes>, tokens: Arc<auth::Tokens>) -> JoinHandle<()> {
    tokio::spawn(async move {
        if let Err(e) = viewer::serve(listener, episodes, tokens).await {
            tracing::error!(target: LOG_TARGET, "the viewer stopped: {e}");
        }
    })
}

/// Ends a background task and waits until it has.
async fn stop_task(task: JoinHandle<()>) {
    task.abort();
    let _ = task.await;
}

/// Serves the gRPC services (health, reflection, and esrp.v1 and dm_env_rpc behind the token
/// check) on the `incoming` connections until `shutdown` completes, then drains in-flight calls
/// for at most `--shutdown-grace-ms`.
async fn serve_grpc(
    incoming: impl Stream<Item = std::io::Result<listen::Connection>> + Send + 'static,
    config: &Config,
    episodes: &Arc<Episodes>,
    tokens: Arc<auth::Tokens>,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
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

    let (shutdown, drain_timeout) = bounded_drain(shutdown, config.shutdown_grace());
    let serve = server_builder(config)?
        .add_service(health_service)
        .add_service(reflection)
        .add_service(InterceptedService::new(esrp_v1::answered::Answered::new(esrp), check.clone()))
        .add_service(InterceptedService::new(dm_env, check))
        .serve_with_incoming_shutdown(incoming, shutdown);
    tokio::select! {
        result = serve => Ok(result?),
        () = drain_timeout => {
            // The connections still open are dropped with the runtime, after the render
            // thread has stopped (in `run`): their clients see UNAVAILABLE.
            let grace_ms = config.shutdown_grace().as_millis() as u64;
            tracing::warn!(target: LOG_TARGET, grace_ms, "calls or streams still open after the shutdown grace: stopping anyway");
            Ok(())
        }
    }
}

/// The transport's builder, with TLS where `--tls-cert` and `--tls-key` are given.
fn server_builder(config: &Config) -> Result<tonic::transport::Server, ServeError> {
    let mut builder = tonic::transport::Server::builder();
    if let (Some(cert), Some(key)) = (&config.tls_cert, &config.tls_key) {
        let read = |flag: &str, path: &std::path::Path| {
            std::fs::read(path)
                .map_err(|source| ServeError::Io { what: format!("cannot read {flag} {}", path.display()), source })
        };
        let (cert_pem, key_pem) = (read("--tls-cert", cert)?, read("--tls-key", key)?);
        check_tls_identity(cert, &cert_pem, key, &key_pem).map_err(ServeError::Config)?;
        builder = builder.tls_config(
            tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(cert_pem, key_pem)),
        )?;
    }
    Ok(builder)
}

/// Checks the PEM files of `--tls-cert` and `--tls-key` before the transport takes them, so that
/// a refusal names the flag and the file at fault (the transport's own errors name neither: an
/// empty certificate file there is "peer sent no certificates", a certificate given as the key
/// "no RSA or PKCS8-encoded keys found", whatever the key's kind, and a key of another
/// certificate "KeyMismatch").
fn check_tls_identity(cert: &Path, cert_pem: &[u8], key: &Path, key_pem: &[u8]) -> Result<(), String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let (cert, key) = (cert.display(), key.display());
    let chain = CertificateDer::pem_slice_iter(cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("--tls-cert {cert}: not a PEM certificate chain: {e}"))?;
    if chain.is_empty() {
        return Err(format!(
            "--tls-cert {cert}: no certificate in it (a PEM block `-----BEGIN CERTIFICATE-----`, the server's \
             own first, then its chain)"
        ));
    }
    let private_key = PrivateKeyDer::from_pem_slice(key_pem).map_err(|e| {
        format!(
            "--tls-key {key}: no private key in it (a PEM block `-----BEGIN PRIVATE KEY-----`, or of an RSA or \
             EC key): {e}"
        )
    })?;
    let signing_key = rustls::crypto::ring::sign::any_supported_type(&private_key)
        .map_err(|e| format!("--tls-key {key}: a key TLS cannot sign with (RSA, ECDSA P-256/P-384 or Ed25519): {e}"))?;
    match rustls::sign::CertifiedKey::new(chain, signing_key).keys_match() {
        // Where rustls cannot tell (a key that does not give its public half), the handshake will.
        Ok(()) | Err(rustls::Error::InconsistentKeys(rustls::InconsistentKeys::Unknown)) => Ok(()),
        Err(rustls::Error::InconsistentKeys(_)) => Err(format!(
            "--tls-key {key} is not the key of --tls-cert {cert} (the chain's first certificate must be the one the \
             key is for)"
        )),
        Err(e) => Err(format!("--tls-cert {cert}: its first certificate cannot be read: {e}")),
    }
}

/// `shutdown`, passed on to the server, and a timer that completes `grace` after it did. The
/// drain after the signal is bounded: a client that keeps a stream open (or a call that does not
/// end) would otherwise hold the server up for as long as it likes. If the server ends without a
/// signal, the timer never completes: there is nothing to bound.
fn bounded_drain(
    shutdown: impl Future<Output = ()> + Send,
    grace: Duration,
) -> (impl Future<Output = ()> + Send, impl Future<Output = ()> + Send) {
    let (signalled, on_signal) = tokio::sync::oneshot::channel::<()>();
    let shutdown = async move {
        shutdown.await;
        let _ = signalled.send(());
    };
    let drain_timeout = async move {
        if on_signal.await.is_err() {
            std::future::pending::<()>().await;
        }
        tokio::time::sleep(grace).await;
    };
    (shutdown, drain_timeout)
}
