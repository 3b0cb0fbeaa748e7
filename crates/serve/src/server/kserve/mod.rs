//! The Open Inference Protocol (KServe v2) beside the native API, on the same port: REST routes
//! under `/v2` (with the binary tensor data extension) and the gRPC service
//! `inference.GRPCInferenceService`. Both turn tensors into a [`Frame`](posefuse_core::frame::Frame)
//! (`tensors`) and call the same `Predictor::predict` as `POST /v1/poses`. docs/KSERVE.md is the
//! contract.

pub mod config;
pub mod grpc;
mod mapping;
pub mod non_finite;
pub mod rest;
pub mod rest_shared_memory;
pub mod shared_memory;
pub mod shared_tensors;
pub mod tensors;

use std::sync::atomic::Ordering;
use std::sync::{Arc, OnceLock};

use super::AppState;
use crate::service::admission::Ticket;
use posefuse_core::error::{Error, Result};
use posefuse_core::image_decode::{RawImage, RawImages};
use shared_tensors::SharedInput;
use tensors::{InputTensor, OutputTensor, Placement, RequestedOutput};

/// Server name in server metadata.
pub const SERVER_NAME: &str = "posefuse";
/// Protocol extensions always served.
pub const EXTENSIONS: [&str; 1] = ["binary_tensor_data"];
/// The shared-memory extension's name, served when `--system-shared-memory` is on.
pub const SHARED_MEMORY_EXTENSION: &str = "system_shared_memory";

/// The extensions this server offers, in server metadata.
pub fn extensions(state: &AppState) -> Vec<&'static str> {
    let mut e = EXTENSIONS.to_vec();
    if state.shared_memory.enabled() {
        e.push(SHARED_MEMORY_EXTENSION);
    }
    e
}
/// Platform in model metadata: the whole pipeline, not one ONNX graph, answers.
pub const PLATFORM: &str = "posefuse";

/// Ready for inference: warmed up and not shutting down (as `/readyz`).
pub fn server_ready(state: &AppState) -> bool {
    state.ready.load(Ordering::SeqCst) && !state.shutting_down.load(Ordering::SeqCst)
}

/// The served model's name and version when `name` (and `version`, if given and not empty)
/// designate it; `NotFound` otherwise. The name is `--model-name` when given (an
/// InferenceService's), else the bundle manifest's.
pub fn model(state: &AppState, name: &str, version: Option<&str>) -> Result<(String, String)> {
    let bundle = state.predictor.bundle();
    let m = &bundle.manifest;
    let served = state.v2_model_name.as_deref().unwrap_or(&m.name);
    if name != served {
        return Err(Error::NotFound(format!("model `{name}`; this server serves `{served}`")));
    }
    match version {
        Some(v) if !v.is_empty() && v != m.version => {
            Err(Error::NotFound(format!("version `{v}` of model `{name}`; this server serves `{}`", m.version)))
        }
        _ => Ok((served.to_string(), m.version.clone())),
    }
}

/// An inference request, whatever its transport.
#[derive(Debug, Clone)]
pub struct InferRequest {
    pub model_name: String,
    pub model_version: Option<String>,
    /// The request id, echoed in the response and used as the frame id.
    pub id: Option<String>,
    pub inputs: Vec<InputTensor>,
    /// Inputs whose data lies in shared-memory regions, read when the request runs.
    pub shared_inputs: Vec<SharedInput>,
    /// `None` or empty: every output.
    pub outputs: Option<Vec<RequestedOutput>>,
    /// Binary form for outputs that do not say (REST `binary_data_output`).
    pub binary_output: bool,
}

/// An inference response, whatever its transport.
#[derive(Debug, Clone)]
pub struct InferResponse {
    pub model_name: String,
    pub model_version: String,
    pub id: Option<String>,
    /// Each output with where its data goes.
    pub outputs: Vec<(OutputTensor, Placement)>,
}

/// Runs one inference: tensors (those in shared memory read in the pre-processing step) →
/// frame → `Predictor::answer_built` (with the server's deadline) → tensors (those asked for in
/// shared memory written there), on the ticket the request was admitted with. Errors name the
/// tensor they come from.
pub async fn infer(state: &AppState, ticket: &Ticket, req: InferRequest) -> Result<InferResponse> {
    let (model_name, model_version) = model(state, &req.model_name, req.model_version.as_deref())?;
    tensors::check_requested(req.outputs.as_deref())?;
    let output_regions = shared_tensors::hold_output_regions(&state.shared_memory, req.outputs.as_deref())?;
    // The shared inputs are read, and the frame built, in the admitted pre-processing step.
    let persons = Arc::new(OnceLock::new());
    let build = {
        let (shm, limit, persons) = (state.shared_memory.clone(), state.body_limit, persons.clone());
        let (mut inputs, shared_inputs, id) = (req.inputs, req.shared_inputs, req.id.clone());
        move || {
            let mut shared_pixels = None;
            if !shared_inputs.is_empty() {
                let shared = shared_tensors::read_inputs(&shm, shared_inputs, limit)?;
                inputs.extend(shared.tensors);
                shared_pixels = shared.pixels;
            }
            let (frame, image) = tensors::frame_from_inputs(inputs, id)?;
            let raw = match (image, shared_pixels) {
                (None, None) => None,
                (Some(bytes), None) => Some(RawImages(vec![RawImage::Encoded(bytes)])),
                (None, Some(rows)) => Some(RawImages(vec![RawImage::Rows(rows)])),
                (Some(_), Some(_)) => {
                    return Err(Error::field(
                        "image_rgb",
                        "send either `image` (file bytes) or `image_rgb` (pixels), not both",
                    ))
                }
            };
            let _ = persons.set(frame.persons.len());
            Ok((frame, raw))
        }
    };
    let resp = state
        .predictor
        .answer_built(ticket, Box::new(build), state.request_timeout)
        .await
        .map_err(tensors::rename_error)?;
    let m = persons.get().copied().ok_or_else(|| Error::Runtime("the frame was answered unbuilt".into()))?;
    let all = tensors::outputs_from_response(&resp, m)?;
    let outputs = tensors::select_outputs(all, req.outputs.as_deref(), req.binary_output)?;
    let outputs = shared_tensors::write_outputs(outputs, &output_regions)?;
    Ok(InferResponse { model_name, model_version, id: req.id, outputs })
}
