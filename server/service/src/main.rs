//! `esrp-server`: parses the configuration, sets up logging and serves until SIGINT/SIGTERM.

use clap::Parser;
use esrp_server::Config;
use esrp_server::config::LogFormat;

async fn shutdown_signal() {
    let interrupt = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut terminate = match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(s) => s,
            Err(_) => {
                let _ = interrupt.await;
                return;
            }
        };
        tokio::select! {
            _ = interrupt => {},
            _ = terminate.recv() => {},
        }
    }
    #[cfg(not(unix))]
    let _ = interrupt.await;
    tracing::info!("shutting down");
}

/// Mesa's CPU renderers (llvmpipe, lavapipe) rasterise with a pool of `LP_NUM_THREADS`
/// threads (one per core by default). On a few cores, handing every small view to that pool
/// costs more than it saves: rasterising in the submitting thread (the render thread for
/// llvmpipe through OpenGL, lavapipe's queue thread for Vulkan) measured 1.3-1.7x the steps/s
/// on 2 cores. So unless the user chose, machines with at most 4 cores do that.
#[allow(unsafe_code)]
fn default_lavapipe_threads() {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    if std::env::var_os("LP_NUM_THREADS").is_none() && cores <= 4 {
        // SAFETY: called first thing in `main`, before any other thread exists (the async
        // runtime is built after), so nothing reads the environment concurrently.
        unsafe { std::env::set_var("LP_NUM_THREADS", "0") };
    }
}

fn main() -> anyhow::Result<()> {
    default_lavapipe_threads();
    let config = Config::parse();
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(config.worker_threads())
        .enable_all()
        .build()?
        .block_on(serve(config))
}

async fn serve(config: Config) -> anyhow::Result<()> {
    let filter = tracing_subscriber::EnvFilter::try_from_env("ESRP_LOG").unwrap_or_else(|_| "info".into());
    match config.log_format {
        LogFormat::Text => tracing_subscriber::fmt().with_env_filter(filter).init(),
        LogFormat::Json => tracing_subscriber::fmt().json().with_env_filter(filter).init(),
    }
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", config.listen))?;
    // Tests and scripts read the bound address (useful with port 0) from this line.
    println!("esrp-server listening on {}", listener.local_addr()?);
    let metrics_listener = match config.metrics_listen {
        Some(address) => {
            let listener = tokio::net::TcpListener::bind(address)
                .await
                .map_err(|e| anyhow::anyhow!("cannot listen on {address} for --metrics-listen: {e}"))?;
            println!("esrp-server metrics on http://{}/metrics", listener.local_addr()?);
            Some(listener)
        }
        None => None,
    };
    Ok(esrp_server::run(listener, metrics_listener, config, shutdown_signal()).await?)
}
