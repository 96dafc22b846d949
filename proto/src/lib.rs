//! The `pointfarm.v1` gRPC API: messages, clients and service traits generated from
//! `pointfarm/v1/pointfarm.proto` at build time.

/// Generated code for package `pointfarm.v1`.
pub mod v1 {
    // Generated code: its doc comments come from the .proto file.
    #![allow(clippy::all, missing_docs)]
    tonic::include_proto!("pointfarm.v1");

    /// The encoded file descriptor set, for gRPC server reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        include_bytes!(concat!(env!("OUT_DIR"), "/pointfarm_descriptor.bin"));
}
