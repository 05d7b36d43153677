//! esrp-server's integration tests: start the real binary on an ephemeral port and talk gRPC;
//! property tests of the request conversions at the edge (`conversions`).

mod attempts;
mod challenge;
mod conversions;
mod dm_env;
mod episodes;
mod errors;
mod harness;
mod health_check;
mod hidden;
mod lifecycle;
mod replays;
mod scene_cache;
mod smoke;
mod startup;
mod unix_socket;
mod viewer;
