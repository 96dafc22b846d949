//! Generates the Rust code of the `pointfarm.v1` API. The .proto files are parsed by protox
//! (pure Rust), so building needs no system `protoc`. The encoded descriptor set is written
//! next to the code for gRPC server reflection, and pbjson-build generates from it the serde
//! impls of every message and enum: the proto3 JSON mapping (`pointfarm.v1.serde.rs`).

use std::path::PathBuf;

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let proto = "pointfarm/v1/pointfarm.proto";
    println!("cargo:rerun-if-changed={proto}");
    let descriptors = protox::compile([proto], ["."])?;
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    let encoded = descriptors.encode_to_vec();
    std::fs::write(out_dir.join("pointfarm_descriptor.bin"), &encoded)?;
    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .compile_fds(descriptors)?;
    pbjson_build::Builder::new()
        .register_descriptors(&encoded)?
        .out_dir(&out_dir)
        .build(&[".pointfarm.v1"])?;
    Ok(())
}
