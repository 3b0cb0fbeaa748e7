//! Generates the gRPC types from proto/posefuse.proto and proto/inference.proto (the Open
//! Inference Protocol) with a vendored protoc, so building needs no system protobuf compiler.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // Build scripts run single-threaded before the crate compiles; nothing else reads PROTOC here.
    std::env::set_var("PROTOC", protoc);
    // The protos live at the repository root (proto/), beside the clients that read them.
    println!("cargo:rerun-if-changed=../../proto/posefuse.proto");
    println!("cargo:rerun-if-changed=../../proto/inference.proto");
    tonic_prost_build::configure()
        .compile_protos(&["../../proto/posefuse.proto", "../../proto/inference.proto"], &["../../proto"])?;
    Ok(())
}
