//! esrp-client end to end: every call against the real `esrp-server` binary on an ephemeral
//! port (built by `cargo test --workspace`; or set ESRP_SERVER_BIN).

mod bench;
mod calls;
mod errors;
mod eval;
mod harness;
mod planning;
mod signals;
mod streams;
