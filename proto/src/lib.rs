//! The `pointfarm.v1` gRPC API. The service definitions arrive with the render service
//! (daemon and remote workers); until then this crate only reserves its place in the layout.
