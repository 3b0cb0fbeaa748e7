//! posefuse's serving layer. Data flows one way: request (`posefuse_core::frame`) → [`service`]
//! (validation, decode, mode policy) → `posefuse_core::pipeline` (pure) → [`runtime`] (ONNX
//! Runtime workers) → response; [`server`] carries it over HTTP and gRPC and [`eval`] scores it.
//! See docs/ARCHITECTURE.md.

pub mod eval;
pub mod runtime;
pub mod server;
pub mod service;
