//! **esrp-server**: the ESRP environment server. A tonic gRPC service (`esrp.v1.Esrp`) hosting
//! many concurrent episodes, each with its own simulator state (esrp-core) and views rendered
//! in batches across all episodes by one render thread (esrp-render), on the built-in
//! benchmark esrp-bench-v2 or esrp-bench-v1 (`--benchmark`; scenes generated lazily by index) or a
//! dataset folder.
//!
//! # Module map
//!
//! - [`types`]: the values the episode layer speaks (ids, options, observations, answers); a
//!   leaf every other module may use.
//! - [`quote`]: client-given text in error messages, bounded; a leaf too.
//! - [`config`]: flags and environment variables.
//! - [`auth`]: who calls: the tokens (`--token`, `--tokens`) with their roles and quotas, and the
//!   interceptor that identifies each call's [`types::Caller`].
//! - [`records`]: the server's own `esrp.results/v1` records (`--records`) and the challenge's
//!   counted attempts; its errors are its own ([`records::AlreadyPlayed`],
//!   [`records::RecordsError`]), which [`error`] and [`serve`] wrap.
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
//! - [`error`]: [`error::ServiceError`], the typed errors of calls, and their one mapping to
//!   gRPC status codes.
//! - [`listen`]: where gRPC is served: the TCP listener and the Unix domain socket of
//!   `--listen-unix` (bound, stale files replaced, removed at stop), one stream of connections.
//! - [`serve`]: [`run`], the entry point `main` calls with its listeners and a shutdown signal,
//!   in steps (the episode layer, the reaper, the side servers, the gRPC services with TLS, the
//!   bounded drain, the ordered stop), and [`ServeError`], why the server could not start.
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
//! - **No import circle**: {`types`, `quote`} ← `records` ← `error` ← {`scenes`, `registry`,
//!   `render`} ← `episodes` ← the adapters ← `serve` ← the crate root (`listen` is a leaf `serve` uses); `auth` uses only `types`
//!   (`scripts/module_cycles.py`, run by the tests, checks that no two modules use each other).
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
pub mod listen;
pub mod metrics;
pub mod quote;
pub mod records;
pub mod registry;
pub mod render;
pub mod scenes;
pub mod serve;
pub mod types;
pub mod viewer;

/// Generated protobuf messages and gRPC stubs of `esrp.v1` (from esrp-proto).
pub use esrp_proto::esrp::v1 as proto;

pub use config::Config;
pub use serve::{Listeners, ServeError, build_episodes, run, tokens_of};
