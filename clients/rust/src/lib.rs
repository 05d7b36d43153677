//! **esrp-client**: a typed async client of the ESRP server's native API (`esrp.v1` over
//! gRPC), for Rust agents, planners and evaluation tools. It depends on the generated code of
//! `esrp-proto` and on tonic only: no renderer, no physics, no dataset.
//!
//! ```no_run
//! use esrp_client::{Action, Client, EpisodeOptions, SceneFilter, Split};
//!
//! # async fn demo() -> Result<(), esrp_client::ClientError> {
//! let client = Client::connect("http://127.0.0.1:50051").await?;
//! let scenes = client.list_scenes(SceneFilter::split(Split::Test)).await?;
//! let (mut episode, observation) = client.create_episode(EpisodeOptions::scene(&scenes[0].id)).await?;
//! println!("{}x{} view, holding: {}", observation.ego_rgb.width(), observation.ego_rgb.height(), observation.grasping);
//! loop {
//!     let result = episode.step(Action::TurnLeft).await?;
//!     if result.ended() {
//!         println!("success: {}", result.metrics.map_or(false, |m| m.success));
//!         break;
//!     }
//! }
//! episode.close().await?;
//! # Ok(()) }
//! ```
//!
//! # Module map
//!
//! - [`client`]: [`Client`] — connecting (token, TLS), server info, the dataset and its
//!   scenes (paged as a stream), creating episodes, [`Client::step_batch`].
//! - [`episode`]: [`Episode`] — one live episode: step, reset, goal, metrics, privileged
//!   state, the server's planner ([`Episode::plan_actions`]), close (also on drop, best
//!   effort).
//! - [`stream`]: [`EpisodeStream`] — a pipelined `StepStream` with up to N steps of each
//!   episode in flight, answers in request order.
//! - [`types`]: [`Action`], [`Observation`] (pixels shared with the answer, never copied),
//!   [`StepResult`], [`EpisodeMetrics`], [`SceneSummary`], [`EpisodeOptions`].
//! - [`raw`]: [`RawClient`], the generated stub with the bearer token, which every handle
//!   holds (handles never hold each other: no module imports one that imports it).
//! - [`local`]: [`LocalServer`] — an `esrp-server` child process on a free port.
//! - [`random`]: [`RandomActions`] — seeded, portable uniform random actions.
//! - [`signals`]: [`signals::exit_on_signals`] — how the tools stop on SIGTERM and SIGINT.
//! - [`results`]: the results schema `esrp.results/v1` of every evaluation tool
//!   (`docs/evaluation.md`): [`results::EpisodeRecord`], reading, appending, summaries.
//! - [`error`]: [`ClientError`], one variant per status a caller may handle.
//!
//! The crate's binaries are `esrp-demo` (the expert and a random agent on a few test scenes),
//! `esrp-eval` (an agent over a whole split, results in `esrp.results/v1`) and `esrp-bench`
//! (end-to-end throughput and latency).
//!
//! Features: `image` adds `Image::to_rgb_image` (an observation as an `image::RgbImage`); `tools` (default) builds the binaries and
//! their dependencies (clap, indicatif, anyhow, humantime), which a library user turns off with
//! `default-features = false`.

#![warn(missing_docs)]

pub mod client;
pub mod episode;
pub mod error;
pub mod local;
pub mod malloc;
pub mod random;
pub mod raw;
pub mod results;
pub mod signals;
pub mod stream;
pub mod types;

/// The generated `esrp.v1` messages and stub (from esrp-proto), for what the typed API does
/// not cover.
pub use esrp_proto::esrp::v1 as proto;

pub use client::{Client, ConnectBuilder, MAX_MESSAGE_BYTES, SceneFilter, Tls};
pub use episode::Episode;
pub use error::{ClientError, Result};
pub use local::{LocalServer, find_server_binary, reach_or_start};
pub use random::RandomActions;
pub use raw::{Bearer, RawClient};
pub use stream::{Answer, EpisodeStream, StreamAnswer};
pub use types::{
    Action, DepthImage, Difficulty, EpisodeMetrics, EpisodeOptions, Goal, Image, LabelImage, Observation, Obstacle,
    ObstacleKind, PlanAnswer, PlanFailure, PlanStats, PrivilegedState, RewardTerms, SceneChoice, SceneSummary, Sensors,
    ServerInfo, Split, StepInfo, StepResult, ValueImage,
};
