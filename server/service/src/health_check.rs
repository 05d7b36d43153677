//! `esrp-server health-check`: asks a running server's `grpc.health.v1` service whether it is
//! serving. Part of the binary (not the library), so that a container image that holds only
//! `esrp-server` can check itself (Docker `HEALTHCHECK`, a Kubernetes exec probe) without a
//! `grpc_health_probe` or a shell.
//!
//! Exit status: 0 when the answer is SERVING; 1 otherwise (not serving, unknown service, no
//! answer in time, refused connection, TLS failure), with a one-line reason on stderr. 1 is the
//! only failure status because Docker reserves 2 for itself.
//!
//! The health service answers without a bearer token (kubelet's gRPC probes cannot send one),
//! so the check needs none against a server started with `--token`. TLS: with an `https://`
//! address, or when the server's `--tls-cert` (`ESRP_TLS_CERT`) is set in the environment the
//! check runs in, as it is inside the server's own container, the check speaks TLS. It trusts
//! `--tls-ca` when given (checking the certificate's name: the address's host, or
//! `--tls-domain`); else, with the server's `--tls-cert` set, exactly the certificate that file
//! starts with, whatever its names and kind (`pinned`; with `--tls-domain`, that chain and the
//! system's authorities, the name checked); else the system's authorities.

use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, anyhow, bail};
use esrp_server::Config;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// Flags of `esrp-server health-check`.
#[derive(Clone, Debug, clap::Args)]
pub struct HealthCheckArgs {
    /// The server: `HOST:PORT`, `http://HOST:PORT` or `https://HOST:PORT`. Default: the
    /// server's own --listen (`ESRP_LISTEN`), with an unspecified address (0.0.0.0, [::]) asked
    /// on loopback.
    pub address: Option<String>,
    /// The service whose health to ask for; the empty name is the whole server.
    #[arg(long, env = "ESRP_HEALTH_CHECK_SERVICE", default_value = "")]
    pub service: String,
    /// Give up after this many milliseconds, connecting included.
    #[arg(long, env = "ESRP_HEALTH_CHECK_TIMEOUT_MS", default_value_t = 3000, value_parser = clap::value_parser!(u64).range(1..))]
    pub timeout_ms: u64,
    /// TLS: the certificates to trust (PEM). Default: exactly the certificate of the server's
    /// --tls-cert (`ESRP_TLS_CERT`) where it is set, whatever its names; else the system's
    /// certificate authorities.
    #[arg(long, env = "ESRP_HEALTH_CHECK_TLS_CA")]
    pub tls_ca: Option<PathBuf>,
    /// TLS: the name the server's certificate must carry. Default: the address's host, checked
    /// unless the server's own certificate is what is trusted.
    #[arg(long, env = "ESRP_HEALTH_CHECK_TLS_DOMAIN")]
    pub tls_domain: Option<String>,
}

/// Runs the check; `Ok` means SERVING. `config` is the server's configuration as the same
/// environment gives it (the default address and TLS certificate come from it).
pub fn run(args: &HealthCheckArgs, config: &Config) -> anyhow::Result<String> {
    let target = Target::new(args, config)?;
    let timeout = Duration::from_millis(args.timeout_ms);
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    runtime.block_on(async {
        match tokio::time::timeout(timeout, target.check(&args.service)).await {
            Ok(answer) => answer,
            Err(_) => bail!("{}: no answer within {} ms", target.url, args.timeout_ms),
        }
    })
}

mod pinned;

/// Where to connect and how.
struct Target {
    url: String,
    trust: Trust,
}

/// How the check trusts the server.
#[derive(Debug)]
enum Trust {
    /// Plain HTTP/2.
    Plain,
    /// TLS verified as any client would (a CA, the certificate's name).
    Authorities(ClientTlsConfig),
    /// TLS trusting exactly the certificate of the server's own `--tls-cert`.
    Itself(std::sync::Arc<rustls::ClientConfig>),
}

impl Target {
    fn new(args: &HealthCheckArgs, config: &Config) -> anyhow::Result<Self> {
        let address = match &args.address {
            Some(address) => address.clone(),
            None => loopback_for(config.listen).to_string(),
        };
        let (scheme, rest) = match address.split_once("://") {
            Some((scheme @ ("http" | "https"), rest)) => (scheme, rest.to_owned()),
            Some((scheme, _)) => bail!("unknown scheme {scheme:?} in {address:?}: use http:// or https://"),
            None => ("", address.clone()),
        };
        let use_tls = match scheme {
            "https" => true,
            "http" => false,
            _ => args.tls_ca.is_some() || config.tls_cert.is_some(),
        };
        // Verified as any client would: these certificates, the name checked (--tls-domain).
        let authorities = |tls: ClientTlsConfig| {
            Trust::Authorities(match &args.tls_domain {
                Some(domain) => tls.domain_name(domain.clone()),
                None => tls,
            })
        };
        let trust = match (use_tls, &args.tls_ca, &config.tls_cert) {
            (false, _, _) => Trust::Plain,
            (true, Some(path), _) => {
                let pem = std::fs::read(path).with_context(|| format!("cannot read --tls-ca {}", path.display()))?;
                authorities(ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)))
            }
            (true, None, Some(path)) if args.tls_domain.is_none() => Trust::Itself(pinned::config(path)?),
            (true, None, chain) => {
                // The system's authorities, and the server's own chain when it is set (with a
                // --tls-domain to check: the certificate's kind and names as any client would).
                let mut tls = ClientTlsConfig::new().with_native_roots();
                if let Some(path) = chain {
                    let pem = std::fs::read(path)
                        .with_context(|| format!("cannot read the server's --tls-cert {}", path.display()))?;
                    tls = tls.ca_certificate(Certificate::from_pem(pem));
                }
                authorities(tls)
            }
        };
        let url = format!("{}://{rest}", if use_tls { "https" } else { "http" });
        Ok(Self { url, trust })
    }

    /// Connects and asks; the caller bounds the time of the whole (one clock for connecting and
    /// answering, one message for running out of it).
    async fn check(&self, service: &str) -> anyhow::Result<String> {
        let endpoint =
            || Endpoint::from_shared(self.url.clone()).map_err(|e| anyhow!("{:?} is not an address: {e}", self.url));
        let channel = match &self.trust {
            Trust::Plain => endpoint()?.connect().await.map_err(anyhow::Error::from),
            Trust::Authorities(tls) => {
                let endpoint =
                    endpoint()?.tls_config(tls.clone()).with_context(|| format!("{}: TLS settings", self.url))?;
                endpoint.connect().await.map_err(anyhow::Error::from)
            }
            Trust::Itself(config) => pinned::connect(self.url.trim_start_matches("https://"), config.clone()).await,
        };
        let channel = channel.with_context(|| format!("{}: cannot connect", self.url))?;
        let answer = HealthClient::new(channel)
            .check(HealthCheckRequest { service: service.to_owned() })
            .await
            .map_err(|status| {
                anyhow!("{}: the health check failed: {:?}: {}", self.url, status.code(), status.message())
            })?
            .into_inner();
        let status = ServingStatus::try_from(answer.status).unwrap_or(ServingStatus::Unknown);
        let what = if service.is_empty() { "the server".to_owned() } else { format!("service {service:?}") };
        match status {
            ServingStatus::Serving => Ok(format!("{}: {what} is SERVING", self.url)),
            other => bail!("{}: {what} is {}", self.url, other.as_str_name()),
        }
    }
}

/// `error` and its causes on one line, `: ` between them, a cause whose text is already said (one
/// that repeats the one before it, as hyper's connect errors do, or that an error's own message
/// holds) left out.
pub fn one_line(error: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in error.chain() {
        let text = cause.to_string();
        // A cause an error's own message already gives (`{source}` in it) is said once.
        if !line.contains(&text) {
            if !line.is_empty() {
                line.push_str(": ");
            }
            line.push_str(&text);
        }
    }
    line.replace('\n', " ")
}

/// The address to ask a server that listens on `listen`: loopback for an unspecified address.
fn loopback_for(listen: SocketAddr) -> SocketAddr {
    match listen.ip() {
        IpAddr::V4(ip) if ip.is_unspecified() => SocketAddr::new(Ipv4Addr::LOCALHOST.into(), listen.port()),
        IpAddr::V6(ip) if ip.is_unspecified() => SocketAddr::new(Ipv6Addr::LOCALHOST.into(), listen.port()),
        _ => listen,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unspecified_listen_address_is_asked_on_loopback() {
        let check = |listen: &str, expected: &str| {
            assert_eq!(loopback_for(listen.parse().unwrap()).to_string(), expected, "{listen}");
        };
        check("0.0.0.0:50051", "127.0.0.1:50051");
        check("[::]:7", "[::1]:7");
        check("10.1.2.3:50051", "10.1.2.3:50051");
        check("127.0.0.1:1", "127.0.0.1:1");
    }

    #[test]
    fn an_error_and_its_causes_make_one_line_without_repeats() {
        let error = anyhow!("refused").context("tcp connect").context("tcp connect").context("h:1: cannot\nconnect");
        assert_eq!(one_line(&error), "h:1: cannot connect: tcp connect: refused");
        // A cause its error's message already holds is said once.
        let error = anyhow!("No such file").context("d/manifest.json: No such file").context("cannot serve d");
        assert_eq!(one_line(&error), "cannot serve d: d/manifest.json: No such file");
    }

    #[test]
    fn the_scheme_and_the_server_s_certificate_choose_tls() {
        let args = |address: &str| HealthCheckArgs {
            address: Some(address.to_owned()),
            service: String::new(),
            timeout_ms: 1000,
            tls_ca: None,
            tls_domain: None,
        };
        let plain = Config::with_listen("0.0.0.0:50051".parse().unwrap());
        let target = |address: &str, config: &Config| Target::new(&args(address), config);
        assert_eq!(target("127.0.0.1:9", &plain).unwrap().url, "http://127.0.0.1:9");
        assert_eq!(target("http://h:9", &plain).unwrap().url, "http://h:9");
        // Without a certificate to trust, the system's authorities.
        let system = target("https://h:9", &plain).unwrap();
        assert!(system.url == "https://h:9" && matches!(system.trust, Trust::Authorities(_)));
        let error = target("ftp://h:9", &plain).err().unwrap().to_string();
        assert!(error.contains("unknown scheme"), "{error}");
        // A server configured for TLS is checked over TLS, trusting its own certificate (which
        // must be readable).
        let mut tls = plain.clone();
        tls.tls_cert = Some("/nonexistent/cert.pem".into());
        let error = target("127.0.0.1:9", &tls).err().unwrap().to_string();
        assert!(error.contains("cannot read the server's --tls-cert /nonexistent/cert.pem"), "{error}");
        assert_eq!(target("http://127.0.0.1:9", &tls).unwrap().url, "http://127.0.0.1:9");
    }
}
