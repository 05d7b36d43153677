//! [`Client`]: a connection to an ESRP server, and the calls that are not about one episode
//! (server info, the dataset, scenes, batches, streams).

use std::collections::VecDeque;
use std::future::{Future, IntoFuture};
use std::pin::Pin;
use std::time::Duration;

use tokio_stream::Stream;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};

use crate::episode::Episode;
use crate::error::{ClientError, Result};
use crate::proto;
use crate::proto::esrp_client::EsrpClient;
use crate::raw::{Bearer, RawClient};
use crate::stream::EpisodeStream;
use crate::types::{Action, Difficulty, EpisodeOptions, Observation, SceneSummary, ServerInfo, Split, StepResult};

/// Largest message either side sends: a StepBatch of many high-resolution views.
pub const MAX_MESSAGE_BYTES: usize = 256 << 20;

/// The largest HTTP/2 frame this client accepts (SETTINGS_MAX_FRAME_SIZE, instead of the 16 KiB
/// default): a step's ~49 KB answer comes in one DATA frame instead of four.
pub const MAX_FRAME_BYTES: u32 = 1 << 20;

/// TLS settings: the certificate authority that signed the server's certificate, and the name
/// the certificate was issued for.
#[derive(Clone, Debug)]
pub struct Tls {
    config: ClientTlsConfig,
}

impl Tls {
    /// Trusts the CA certificate(s) in `pem`. The server's name defaults to the URL's host.
    pub fn ca_pem(pem: impl AsRef<[u8]>) -> Self {
        Tls { config: ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)) }
    }

    /// Trusts the CA certificate(s) in the PEM file `path`: a [`ClientError::Config`] naming
    /// it when it cannot be read or holds no certificate.
    pub fn ca_pem_file(path: impl AsRef<std::path::Path>) -> Result<Self> {
        let path = path.as_ref();
        let pem = std::fs::read(path)
            .map_err(|e| ClientError::Config(format!("cannot read the CA certificate {}: {e}", path.display())))?;
        if !pem.windows(27).any(|w| w == b"-----BEGIN CERTIFICATE-----") {
            return Err(ClientError::Config(format!("{} holds no PEM certificate", path.display())));
        }
        Ok(Self::ca_pem(pem))
    }

    /// Trusts the system's certificate authorities (what an `https://` URL uses when no
    /// [`ConnectBuilder::tls`] is given).
    pub fn system_roots() -> Self {
        Tls { config: ClientTlsConfig::new().with_native_roots() }
    }

    /// The settings of the tools' `--tls-ca FILE` and `--tls-domain NAME` for `server` (their
    /// `--server`): none without either; otherwise `server` must be an `https://` URL (refused
    /// here, before anything starts), trusting the CA in FILE (or else the system's) and checking
    /// the certificate against NAME (or else the URL's host).
    pub fn from_flags(
        server: Option<&str>,
        ca: Option<&std::path::Path>,
        domain: Option<&str>,
    ) -> Result<Option<Self>> {
        if ca.is_none() && domain.is_none() {
            return Ok(None);
        }
        if !server.is_some_and(is_https) {
            return Err(ClientError::Config(
                "--tls-ca and --tls-domain are for a server named by an https:// --server URL".into(),
            ));
        }
        let tls = match ca {
            Some(path) => Self::ca_pem_file(path)?,
            None => Self::system_roots(),
        };
        Ok(Some(match domain {
            Some(name) => tls.domain_name(name),
            None => tls,
        }))
    }

    /// Checks the server's certificate against `name` instead of the URL's host.
    pub fn domain_name(self, name: impl Into<String>) -> Self {
        Tls { config: self.config.domain_name(name) }
    }
}

/// Whether `url` starts with `https://` (in any case).
fn is_https(url: &str) -> bool {
    url.get(..8).is_some_and(|scheme| scheme.eq_ignore_ascii_case("https://"))
}

/// Settings of a connection; `.await` it to connect (see [`Client::connect`]).
#[must_use = "a ConnectBuilder does nothing until awaited"]
#[derive(Clone, Debug)]
pub struct ConnectBuilder {
    url: String,
    token: Option<String>,
    tls: Option<Tls>,
    connect_timeout: Duration,
}

impl ConnectBuilder {
    /// Sends `authorization: Bearer TOKEN` with every call (the server's `--token`).
    pub fn token(mut self, token: impl Into<String>) -> Self {
        self.token = Some(token.into());
        self
    }

    /// Sends `token` when it is `Some`.
    pub fn token_opt(mut self, token: Option<impl Into<String>>) -> Self {
        self.token = token.map(Into::into);
        self
    }

    /// Connects over TLS with these settings (use an `https://` URL; without them, an
    /// `https://` URL trusts the system's certificate authorities).
    pub fn tls(mut self, tls: Tls) -> Self {
        self.tls = Some(tls);
        self
    }

    /// Sets the TLS settings when `tls` is `Some`.
    pub fn tls_opt(mut self, tls: Option<Tls>) -> Self {
        self.tls = tls;
        self
    }

    /// Gives up connecting after `timeout` (default 10 s).
    pub fn connect_timeout(mut self, timeout: Duration) -> Self {
        self.connect_timeout = timeout;
        self
    }

    /// The URL to connect to: the one given, with `http://` put before a bare `host:port`
    /// (`https://` with TLS settings); an IPv6 address without its brackets is refused (its
    /// last `:` would be read as part of the address).
    fn full_url(&self) -> Result<String> {
        let url = self.url.trim();
        if url.starts_with("unix:") {
            return Ok(url.to_owned());
        }
        let (scheme, rest) = match url.split_once("://") {
            Some((scheme, rest)) => (scheme, rest),
            None => (if self.tls.is_some() { "https" } else { "http" }, url),
        };
        let authority = rest.split('/').next().unwrap_or_default();
        let host_port = authority.rsplit('@').next().unwrap_or_default();
        if host_port.matches(':').count() > 1 && !host_port.starts_with('[') {
            return Err(ClientError::Config(format!(
                "{url:?}: write an IPv6 address in brackets, as in http://[::1]:50051"
            )));
        }
        Ok(format!("{scheme}://{rest}"))
    }

    fn endpoint(&self) -> Result<Endpoint> {
        let url = self.full_url()?;
        let https = is_https(&url);
        let mut endpoint = Endpoint::from_shared(url.clone())
            .map_err(|e| {
                ClientError::Config(format!(
                    "{url:?} is not a URL like http://127.0.0.1:50051, 127.0.0.1:50051 or unix:/tmp/esrp.sock: {e}"
                ))
            })?
            // An agent waits for every answer: no Nagle delay. Windows large enough for many
            // ~49 KB observations in flight, and frames for one in one.
            .tcp_nodelay(true)
            .initial_connection_window_size(64 << 20)
            .initial_stream_window_size(16 << 20)
            .max_frame_size(MAX_FRAME_BYTES)
            .connect_timeout(self.connect_timeout);
        match &self.tls {
            Some(tls) if !https => {
                return Err(ClientError::Config(format!("TLS settings are for an https:// URL, not {url:?}")));
            }
            Some(tls) => endpoint = endpoint.tls_config(tls.config.clone())?,
            None if https => endpoint = endpoint.tls_config(Tls::system_roots().config)?,
            None => {}
        }
        Ok(endpoint)
    }

    fn bearer(&self) -> Result<Bearer> {
        Bearer::new(self.token.as_deref())
    }

    fn wrap(&self, channel: Channel) -> Result<Client> {
        let raw = EsrpClient::with_interceptor(channel.clone(), self.bearer()?)
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Ok(Client { raw, channel })
    }

    /// A client that connects on its first call instead of now (calls fail with
    /// [`ClientError::Unavailable`] while the server cannot be reached).
    pub fn connect_lazy(self) -> Result<Client> {
        let channel = self.endpoint()?.connect_lazy();
        self.wrap(channel)
    }

    async fn connect_now(self) -> Result<Client> {
        let channel = self.endpoint()?.connect().await?;
        self.wrap(channel)
    }
}

impl IntoFuture for ConnectBuilder {
    type Output = Result<Client>;
    type IntoFuture = Pin<Box<dyn Future<Output = Result<Client>> + Send>>;

    fn into_future(self) -> Self::IntoFuture {
        Box::pin(self.connect_now())
    }
}

/// Which scenes [`Client::scenes`] lists.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SceneFilter {
    /// Only this split (all when `None`).
    pub split: Option<Split>,
    /// Only this difficulty (all when `None`).
    pub difficulty: Option<Difficulty>,
    /// Scenes per request (0: the server's default, 100; at most 1,000).
    pub page_size: u32,
}

impl SceneFilter {
    /// Scenes of `split`.
    pub fn split(split: Split) -> Self {
        SceneFilter { split: Some(split), ..Default::default() }
    }

    /// Only scenes of `difficulty` too.
    pub fn difficulty(mut self, difficulty: Difficulty) -> Self {
        self.difficulty = Some(difficulty);
        self
    }
}

/// A connection to an ESRP server. Cheap to clone: clones share the connection (HTTP/2
/// multiplexes their calls), so give each task its own.
///
/// ```no_run
/// # async fn demo() -> Result<(), esrp_client::ClientError> {
/// use esrp_client::{Action, Client, EpisodeOptions};
/// let client = Client::connect("http://127.0.0.1:50051").token("secret").await?;
/// let (mut episode, first) = client.create_episode(EpisodeOptions::scene("esrp-bench-v2/00017")).await?;
/// assert_eq!(first.ego_rgb.width(), 128);
/// let result = episode.step(Action::TurnLeft).await?;
/// println!("reward {}", result.reward);
/// episode.close().await?;
/// # Ok(()) }
/// ```
#[derive(Clone, Debug)]
pub struct Client {
    raw: RawClient,
    channel: Channel,
}

impl Client {
    /// Starts a connection to `url` (`http://host:port`, or `host:port` alike; `https://`,
    /// trusting the system's certificate authorities or those of [`ConnectBuilder::tls`]; or
    /// `unix:PATH` for a server's `--listen-unix` socket on this machine; an IPv6 address in
    /// brackets, `http://[::1]:50051`); set the token and TLS on the builder, then `.await` it.
    pub fn connect(url: impl Into<String>) -> ConnectBuilder {
        ConnectBuilder { url: url.into(), token: None, tls: None, connect_timeout: Duration::from_secs(10) }
    }

    /// The connection itself (tuned as above, without the bearer token): for callers that
    /// speak to it below the generated stub, such as the Python client's native transport.
    pub fn channel(&self) -> Channel {
        self.channel.clone()
    }

    /// The generated stub, for RPCs and fields the typed API does not cover.
    pub fn raw(&self) -> RawClient {
        self.raw.clone()
    }

    /// Waits until the server's health service says `esrp.v1.Esrp` is serving, polling every
    /// 50 ms; fails with [`ClientError::DeadlineExceeded`] after `timeout`.
    pub async fn wait_healthy(&self, timeout: Duration) -> Result<()> {
        use tonic_health::pb::health_check_response::ServingStatus;
        let mut health = tonic_health::pb::health_client::HealthClient::new(self.channel.clone());
        let deadline = tokio::time::Instant::now() + timeout;
        let mut last = String::from("no answer yet");
        loop {
            let request = tonic_health::pb::HealthCheckRequest { service: "esrp.v1.Esrp".into() };
            match tokio::time::timeout_at(deadline, health.check(request)).await {
                Err(_) => break,
                Ok(Ok(r)) if r.get_ref().status == ServingStatus::Serving as i32 => return Ok(()),
                Ok(Ok(r)) => last = format!("status {:?}", r.get_ref().status()),
                Ok(Err(status)) => last = status.message().to_owned(),
            }
            if tokio::time::Instant::now() + Duration::from_millis(50) >= deadline {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        Err(ClientError::DeadlineExceeded(format!("the server was not healthy within {timeout:?}: {last}")))
    }

    /// The server's version, renderer, limits and live episode count.
    pub async fn server_info(&self) -> Result<ServerInfo> {
        Ok(self.raw().server_info(proto::ServerInfoRequest {}).await?.into_inner().into())
    }

    /// The served dataset: its name, size and counts by split, difficulty and room type.
    pub async fn describe_dataset(&self) -> Result<proto::DescribeDatasetResponse> {
        Ok(self.raw().describe_dataset(proto::DescribeDatasetRequest {}).await?.into_inner())
    }

    /// Every scene that passes `filter`, fetched page by page as the stream is read. The
    /// stream ends after the last page, or after yielding an error.
    pub fn scenes(&self, filter: SceneFilter) -> impl Stream<Item = Result<SceneSummary>> + Send + 'static {
        struct Listing {
            raw: RawClient,
            filter: SceneFilter,
            /// The next page's token; `None` after the last page or an error.
            token: Option<String>,
            buffered: VecDeque<SceneSummary>,
        }
        let start = Listing { raw: self.raw(), filter, token: Some(String::new()), buffered: VecDeque::new() };
        futures_util::stream::unfold(start, |mut listing| async move {
            loop {
                if let Some(scene) = listing.buffered.pop_front() {
                    return Some((Ok(scene), listing));
                }
                let request = proto::ListScenesRequest {
                    split: Split::to_proto(listing.filter.split),
                    difficulty: Difficulty::to_proto(listing.filter.difficulty),
                    page_size: listing.filter.page_size,
                    page_token: listing.token.take()?,
                };
                match listing.raw.list_scenes(request).await {
                    Ok(page) => {
                        let page = page.into_inner();
                        listing.buffered.extend(page.scenes.into_iter().map(SceneSummary::from));
                        listing.token = (!page.next_page_token.is_empty()).then_some(page.next_page_token);
                    }
                    Err(status) => return Some((Err(status.into()), listing)),
                }
            }
        })
    }

    /// Every scene that passes `filter`, collected.
    pub async fn list_scenes(&self, filter: SceneFilter) -> Result<Vec<SceneSummary>> {
        use tokio_stream::StreamExt;
        let mut scenes = Vec::new();
        let mut stream = std::pin::pin!(self.scenes(filter));
        while let Some(scene) = stream.next().await {
            scenes.push(scene?);
        }
        Ok(scenes)
    }

    /// Creates an episode; returns its handle and its first observation (with the goal image).
    ///
    /// Cancellation-safe: the call runs in a task of its own, so a caller that gives up (a
    /// `tokio::time::timeout`, a dropped future) leaves no episode behind — an answer that
    /// arrives after the caller left is closed on the server at once. (The server closes the
    /// episode itself when the call is abandoned before its answer is sent.)
    pub async fn create_episode(&self, options: EpisodeOptions) -> Result<(Episode, Observation)> {
        options.check()?;
        let (answer, waiting) = tokio::sync::oneshot::channel();
        let mut raw = self.raw();
        let request = options.to_proto();
        let creating = crate::episode::Creating::begin()?;
        tokio::spawn(async move {
            let result = raw.create_episode(request).await.map(tonic::Response::into_inner);
            if let Ok(created) = &result {
                creating.made(&created.episode_id, &raw);
            }
            drop(creating);
            if let Err(Ok(created)) = answer.send(result) {
                // Nobody waits for this episode any more.
                let episode_id = created.episode_id;
                let _ = raw.close_episode(proto::CloseEpisodeRequest { episode_id: episode_id.clone() }).await;
                crate::episode::forget(&episode_id);
            }
        });
        let created = waiting.await.map_err(|_| {
            ClientError::Unavailable("the create task ended without an answer (runtime shutting down)".into())
        })??;
        Episode::created(self.raw(), created)
    }

    /// Takes one step in each of several episodes in one call (at most one step per episode;
    /// the server's `max_batch` caps the count). All-or-nothing: a bad entry fails the call
    /// and no episode moves. Answers are in request order.
    pub async fn step_batch(&self, steps: &[(&Episode, Action)]) -> Result<Vec<StepResult>> {
        let request = proto::StepBatchRequest {
            steps: steps
                .iter()
                .map(|(episode, action)| proto::StepRequest {
                    episode_id: episode.id().to_owned(),
                    action: i32::from(action.code()),
                    include_goal: false,
                })
                .collect(),
            resets: Vec::new(),
        };
        let responses = self.raw().step_batch(request).await?.into_inner().responses;
        if responses.len() != steps.len() {
            return Err(ClientError::Protocol(format!(
                "{} answers to a batch of {} steps",
                responses.len(),
                steps.len()
            )));
        }
        responses.into_iter().map(StepResult::try_from).collect()
    }

    /// Opens a `StepStream` driven by an [`EpisodeStream`] that keeps up to `window` steps of
    /// each episode in flight.
    pub async fn episode_stream(&self, window: usize) -> Result<EpisodeStream> {
        EpisodeStream::open(self.raw(), window).await
    }
}

impl From<&Client> for RawClient {
    /// The client's generated stub ([`Client::raw`]): what episode and stream handles call.
    fn from(client: &Client) -> Self {
        client.raw()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bare_address_gets_its_scheme_and_an_ipv6_one_needs_brackets() {
        let url = |url: &str| Client::connect(url).full_url();
        assert_eq!(url("127.0.0.1:50051").unwrap(), "http://127.0.0.1:50051");
        assert_eq!(url(" esrp.example.org:443 ").unwrap(), "http://esrp.example.org:443");
        assert_eq!(Client::connect("h:1").tls(Tls::system_roots()).full_url().unwrap(), "https://h:1");
        assert_eq!(url("https://h:1/").unwrap(), "https://h:1/");
        assert_eq!(url("unix:/tmp/a:b.sock").unwrap(), "unix:/tmp/a:b.sock");
        assert_eq!(url("[::1]:50051").unwrap(), "http://[::1]:50051");
        assert_eq!(url("http://[fe80::1]:7").unwrap(), "http://[fe80::1]:7");
        for bare in ["::1:50051", "http://::1:50051", "fe80::1:7"] {
            let error = url(bare).unwrap_err().to_string();
            assert!(error.contains("write an IPv6 address in brackets"), "{bare}: {error}");
        }
    }
}
