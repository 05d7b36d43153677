//! Compiles `esrp/v1/esrp.proto` and `dm_env_rpc/v1/dm_env_rpc.proto` (with its
//! `google/rpc/status.proto`) with protox (pure Rust: no `protoc` needed) into prost messages
//! and tonic stubs — client stubs with the `client` feature, server stubs with `server` — and
//! writes the encoded descriptor set for gRPC reflection.

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto_root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let files =
        ["esrp/v1/esrp.proto", "dm_env_rpc/v1/dm_env_rpc.proto", "google/rpc/status.proto"].map(|f| proto_root.join(f));
    for file in &files {
        println!("cargo:rerun-if-changed={}", file.display());
    }
    let descriptors = protox::compile(&files, [proto_root])?;
    let out_dir = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out_dir.join("esrp_descriptor.bin"), descriptors.encode_to_vec())?;
    tonic_prost_build::configure()
        .build_client(std::env::var_os("CARGO_FEATURE_CLIENT").is_some())
        .build_server(std::env::var_os("CARGO_FEATURE_SERVER").is_some())
        .bytes(".esrp.v1")
        // Images travel as `Bytes` in both APIs, so they pass from one to the other uncopied.
        .bytes(".dm_env_rpc.v1")
        // `google.protobuf.Any` is generated here rather than taken from prost-types.
        .compile_well_known_types(true)
        .compile_fds(descriptors)?;
    Ok(())
}
