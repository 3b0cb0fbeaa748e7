//! Early admission, once for every transport: a request that carries one frame (`POST
//! /v1/poses`, KServe REST `…/infer`, gRPC `Predict` and KServe gRPC `ModelInfer`) is admitted
//! here, before its body or message is read. The ticket travels in the request's extensions
//! ([`ticket`]) to the handler, which answers with it (`Predictor::answer_ticketed`); a refusal
//! is answered at once in the route's own error shape. The frames of a batch or stream are
//! admitted one by one before each is parsed (`Predictor::answer_item`). See docs/ARCHITECTURE.md.

use std::sync::Arc;

use axum::extract::Request;
use axum::http::{header, Extensions, Method, Version};
use axum::response::{IntoResponse, Response};
use futures::StreamExt;

use super::errors::{self, HttpError};
use super::peer::Peer;
use super::request_context::RouteLabel;
use crate::service::admission::{Admission, Ticket};
use posefuse_core::error::Error;

/// The frame route a request is on, for the shape of its refusal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameRoute {
    /// `POST /v1/poses`.
    Native,
    /// `POST /v2/models/{name}[/versions/{version}]/infer`.
    KserveRest,
    /// `posefuse.v1.Posefuse/Predict` or `inference.GRPCInferenceService/ModelInfer`.
    Grpc,
}

impl FrameRoute {
    /// The route's label in the access log and the latency metric: the router's pattern, which
    /// the refused request never reached (gRPC: the method's path).
    pub fn label(self, path: &str) -> String {
        match self {
            FrameRoute::Native => "/v1/poses".into(),
            FrameRoute::KserveRest if path.contains("/versions/") => {
                "/v2/models/{name}/versions/{version}/infer".into()
            }
            FrameRoute::KserveRest => "/v2/models/{name}/infer".into(),
            FrameRoute::Grpc => path.into(),
        }
    }
}

/// The frame route of a request, `None` for every other request (they are not admitted here).
pub fn frame_route(method: &Method, path: &str, grpc: bool) -> Option<FrameRoute> {
    if grpc {
        return [super::grpc::PREDICT_PATH, super::kserve::grpc::INFER_PATH]
            .contains(&path)
            .then_some(FrameRoute::Grpc);
    }
    if method != Method::POST {
        return None;
    }
    if path == "/v1/poses" {
        return Some(FrameRoute::Native);
    }
    let segments: Vec<&str> = path.strip_prefix("/v2/models/")?.split('/').collect();
    match segments.as_slice() {
        [name, "infer"] | [name, "versions", _, "infer"] if !name.is_empty() => Some(FrameRoute::KserveRest),
        _ => None,
    }
}

/// Admits `req` when it carries one frame, the ticket in its extensions, after its wait in the
/// admission line when there is one; other requests pass untouched. `Err`: the refusal to send
/// instead (its body, if any, read and dropped beside it, up to `body_limit`).
pub async fn admit(
    admission: &Arc<Admission>,
    mut req: Request,
    grpc: bool,
    body_limit: usize,
) -> Result<Request, Box<Response>> {
    let Some(route) = frame_route(req.method(), req.uri().path(), grpc) else { return Ok(req) };
    // HTTP/2 and gRPC callers that go away drop the whole request instead.
    let peer = req.extensions().get::<Arc<Peer>>().filter(|_| req.version() <= Version::HTTP_11).cloned();
    match admit_while_the_client_waits(admission, peer).await {
        Ok(ticket) => {
            req.extensions_mut().insert(ticket);
            Ok(req)
        }
        Err(e) => {
            let label = route.label(req.uri().path());
            let mut refusal = match route {
                FrameRoute::Grpc => errors::grpc_status(&e).into_http(),
                FrameRoute::Native => {
                    discard_body(req, body_limit);
                    HttpError::from(e).into_response()
                }
                FrameRoute::KserveRest => {
                    discard_body(req, body_limit);
                    errors::v2_response(&e)
                }
            };
            refusal.extensions_mut().insert(RouteLabel(label));
            Err(Box::new(refusal))
        }
    }
}

/// A place for a frame, waiting in the line if there is one; given up when the client on `peer`
/// hangs up meanwhile.
async fn admit_while_the_client_waits(
    admission: &Arc<Admission>,
    peer: Option<Arc<Peer>>,
) -> Result<Arc<Ticket>, Error> {
    let Some(peer) = peer else { return admission.admit_in_line().await.map(Arc::new) };
    // Biased: a frame that gets its place (or its refusal) at once never asks the socket.
    tokio::select! {
        biased;
        admitted = admission.admit_in_line() => admitted.map(Arc::new),
        () = peer.until_hung_up() => {
            metrics::counter!("posefuse_frames_abandoned_total").increment(1);
            Err(Error::ClientGone("it hung up while its frame waited for admission".into()))
        }
    }
}

/// The ticket [`admit`] gave the request, when it went through it.
pub fn ticket(extensions: &Extensions) -> Option<Arc<Ticket>> {
    extensions.get::<Arc<Ticket>>().cloned()
}

/// Reads and drops a refused request's body beside its early answer. Closing a connection with
/// unread body bytes makes the kernel reset it, and a client still sending then sees a broken
/// connection instead of the 429 (and must reconnect); read to its end, the connection stays
/// usable. Bounded: at most `limit` bytes, each chunk within the body-read timeout. A client
/// that asked `Expect: 100-continue` has not sent its body and never will: reading it would
/// invite it to.
fn discard_body(req: Request, limit: usize) {
    let expects_continue = req
        .headers()
        .get(header::EXPECT)
        .is_some_and(|v| v.to_str().is_ok_and(|v| v.eq_ignore_ascii_case("100-continue")));
    if expects_continue {
        return;
    }
    let mut body = req.into_body().into_data_stream();
    tokio::spawn(async move {
        let mut read = 0usize;
        while let Some(Ok(chunk)) = body.next().await {
            read += chunk.len();
            if read > limit {
                break;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_routes_of_one_frame_are_admitted_here() {
        let post = Method::POST;
        assert_eq!(frame_route(&post, "/v1/poses", false), Some(FrameRoute::Native));
        assert_eq!(frame_route(&post, "/v2/models/default/infer", false), Some(FrameRoute::KserveRest));
        assert_eq!(frame_route(&post, "/v2/models/default/versions/0.2.0/infer", false), Some(FrameRoute::KserveRest));
        assert_eq!(frame_route(&post, super::super::grpc::PREDICT_PATH, true), Some(FrameRoute::Grpc));
        assert_eq!(frame_route(&post, super::super::kserve::grpc::INFER_PATH, true), Some(FrameRoute::Grpc));
        for (method, path, grpc) in [
            (Method::GET, "/v1/poses", false),
            (post.clone(), "/v1/poses:batch", false),
            (post.clone(), "/v1/evaluate", false),
            (post.clone(), "/v2/models//infer", false),
            (post.clone(), "/v2/models/default/ready", false),
            (post.clone(), "/v2/models/default/versions/1/infer/x", false),
            (post.clone(), "/posefuse.v1.Posefuse/PredictStream", true),
            (post.clone(), "/v1/poses", true),
        ] {
            assert_eq!(frame_route(&method, path, grpc), None, "{method} {path} grpc={grpc}");
        }
    }
}
