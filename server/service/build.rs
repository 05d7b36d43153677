//! Compiles `proto/esrp/v1/esrp.proto` and `proto/dm_env_rpc/v1/dm_env_rpc.proto` (with its
//! `google/rpc/status.proto`) with protox (pure Rust: no `protoc` needed) into prost messages
//! and tonic services, and writes the encoded descriptor set for gRPC reflection.

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto_root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../proto");
    let files =
        ["esrp/v1/esrp.proto", "dm_env_rpc/v1/dm_env_rpc.proto", "google/rpc/status.proto"].map(|f| proto_root.join(f));
    for file in &files {
        println!("cargo:rerun-if-changed={}", file.display());
    }
    let descriptors = protox::compile(&files, [&proto_root])?;
    let out_dir = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out_dir.join("esrp_descriptor.bin"), descriptors.encode_to_vec())?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .bytes(".esrp.v1")
        // Images travel as `Bytes` in both APIs, so they pass from one to the other uncopied.
        .bytes(".dm_env_rpc.v1")
        // `google.protobuf.Any` is generated here rather than taken from prost-types.
        .compile_well_known_types(true)
        .compile_fds(descriptors)?;
    Ok(())
}
