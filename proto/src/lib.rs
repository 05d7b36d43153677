//! **esrp-proto**: the one place where Rust code is generated from ESRP's `.proto` files — the
//! native API `esrp.v1`, the `dm_env_rpc.v1` protocol and the `google.rpc`/`google.protobuf`
//! messages it uses. The server and every Rust client depend on this crate; nothing else
//! generates protobuf code.
//!
//! Features: `client` (default) generates the client stubs ([`esrp::v1::esrp_client`],
//! [`dm_env_rpc::v1::environment_client`]); `server` generates the server stubs
//! ([`esrp::v1::esrp_server`], [`dm_env_rpc::v1::environment_server`]). Image pixels are
//! [`bytes::Bytes`](prost::bytes::Bytes) in both APIs, so they pass between them uncopied.
//!
//! The message and field documentation is in the `.proto` files beside this crate and in
//! `proto/esrp/v1/README.md` (one section per RPC).

/// The `esrp` packages.
pub mod esrp {
    /// `esrp.v1`: ESRP's native API.
    #[allow(missing_docs, clippy::all)]
    pub mod v1 {
        tonic::include_proto!("esrp.v1");
    }
}

/// The `dm_env_rpc` packages.
pub mod dm_env_rpc {
    /// `dm_env_rpc.v1`: DeepMind's environment protocol, wire-compatible declarations.
    #[allow(missing_docs, clippy::all)]
    pub mod v1 {
        tonic::include_proto!("dm_env_rpc.v1");
    }
}

/// The `google` packages `dm_env_rpc.v1` uses.
pub mod google {
    /// `google.rpc` (only `Status`).
    #[allow(missing_docs, clippy::all)]
    pub mod rpc {
        tonic::include_proto!("google.rpc");
    }
    /// `google.protobuf` (only `Any`).
    #[allow(missing_docs, clippy::all)]
    pub mod protobuf {
        tonic::include_proto!("google.protobuf");
    }
}

/// The encoded file descriptor set of every API above, for gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/esrp_descriptor.bin"));

pub use prost;
