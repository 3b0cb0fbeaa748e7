//! The one place where [`Error`] becomes an HTTP status, a gRPC status and the JSON error body.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

use crate::service::api::{ErrorBody, ErrorDetail};
use posefuse_core::error::Error;

/// nginx's status for a client that closed its connection before the answer: not a server error,
/// so 5xx alerts stay quiet. Nobody receives it; the access log and the latency metric do.
pub const CLIENT_CLOSED_REQUEST: StatusCode = match StatusCode::from_u16(499) {
    Ok(s) => s,
    Err(_) => StatusCode::BAD_REQUEST,
};

/// HTTP status of an error.
pub fn http_status(e: &Error) -> StatusCode {
    match e {
        Error::Malformed(_) => StatusCode::BAD_REQUEST,
        Error::InvalidField { .. } | Error::InsufficientData { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        Error::PayloadTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
        Error::Overloaded => StatusCode::TOO_MANY_REQUESTS,
        Error::NotFound(_) => StatusCode::NOT_FOUND,
        Error::Forbidden(_) => StatusCode::FORBIDDEN,
        Error::Timeout(_) => StatusCode::GATEWAY_TIMEOUT,
        Error::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
        Error::ClientGone(_) => CLIENT_CLOSED_REQUEST,
        Error::Bundle(_) | Error::Runtime(_) | Error::Io(_) => StatusCode::INTERNAL_SERVER_ERROR,
    }
}

/// gRPC status code of an error.
pub fn grpc_code(e: &Error) -> tonic::Code {
    match e {
        Error::Malformed(_) | Error::InvalidField { .. } => tonic::Code::InvalidArgument,
        Error::InsufficientData { .. } => tonic::Code::FailedPrecondition,
        Error::PayloadTooLarge { .. } | Error::Overloaded => tonic::Code::ResourceExhausted,
        Error::NotFound(_) => tonic::Code::NotFound,
        Error::Forbidden(_) => tonic::Code::PermissionDenied,
        Error::Timeout(_) => tonic::Code::DeadlineExceeded,
        Error::Unavailable(_) => tonic::Code::Unavailable,
        Error::ClientGone(_) => tonic::Code::Cancelled,
        Error::Bundle(_) | Error::Runtime(_) | Error::Io(_) => tonic::Code::Internal,
    }
}

/// gRPC status of an error (the message carries the field, as in the JSON body).
pub fn grpc_status(e: &Error) -> tonic::Status {
    tonic::Status::new(grpc_code(e), e.to_string())
}

/// The `error` object of the JSON body.
pub fn detail(e: &Error) -> ErrorDetail {
    ErrorDetail::from(e)
}

/// An [`Error`] on its way out as an HTTP response: the error type lives in `posefuse_core`, which
/// knows nothing of HTTP, so the response is this wrapper's (`?` converts).
#[derive(Debug)]
pub struct HttpError(pub Error);

/// What an HTTP handler returns.
pub type HttpResult<T> = std::result::Result<T, HttpError>;

/// `e.into_response()` for an [`Error`] where a handler builds its response itself.
pub trait IntoHttpResponse {
    fn into_response(self) -> Response;
}

impl IntoHttpResponse for Error {
    fn into_response(self) -> Response {
        HttpError(self).into_response()
    }
}

impl From<Error> for HttpError {
    fn from(e: Error) -> Self {
        HttpError(e)
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let e = self.0;
        let status = http_status(&e);
        if status.is_server_error() {
            tracing::error!(code = e.code(), "{e}");
        }
        let mut resp = (status, axum::Json(ErrorBody { error: detail(&e) })).into_response();
        if matches!(e, Error::Overloaded) {
            resp.headers_mut().insert(axum::http::header::RETRY_AFTER, axum::http::HeaderValue::from_static("1"));
        }
        resp
    }
}

/// HTTP status of an error on the Open Inference Protocol routes (`/v2`): as [`http_status`],
/// except that an invalid field (a tensor) is 400, the status the protocol gives a bad request.
pub fn v2_http_status(e: &Error) -> StatusCode {
    match http_status(e) {
        StatusCode::UNPROCESSABLE_ENTITY => StatusCode::BAD_REQUEST,
        status => status,
    }
}

/// An error as the Open Inference Protocol's REST body: `{"error": "<message naming the field>"}`.
pub fn v2_response(e: &Error) -> Response {
    let status = v2_http_status(e);
    if status.is_server_error() {
        tracing::error!(code = e.code(), "{e}");
    }
    let mut resp = (status, axum::Json(serde_json::json!({ "error": e.to_string() }))).into_response();
    if matches!(e, Error::Overloaded) {
        resp.headers_mut().insert(axum::http::header::RETRY_AFTER, axum::http::HeaderValue::from_static("1"));
    }
    resp
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_class_maps_to_its_documented_codes() {
        let cases = [
            (Error::Malformed("x".into()), 400, tonic::Code::InvalidArgument),
            (Error::field("persons[0].box_3d", "bad"), 422, tonic::Code::InvalidArgument),
            (
                Error::InsufficientData { field: "persons[0].box_3d".into(), message: "no points".into() },
                422,
                tonic::Code::FailedPrecondition,
            ),
            (Error::PayloadTooLarge { limit: 1 }, 413, tonic::Code::ResourceExhausted),
            (Error::Overloaded, 429, tonic::Code::ResourceExhausted),
            (Error::Timeout(5), 504, tonic::Code::DeadlineExceeded),
            (Error::Forbidden("admin".into()), 403, tonic::Code::PermissionDenied),
            (Error::Unavailable("warming up".into()), 503, tonic::Code::Unavailable),
            (Error::ClientGone("hung up".into()), 499, tonic::Code::Cancelled),
            (Error::Runtime("x".into()), 500, tonic::Code::Internal),
        ];
        for (e, http, grpc) in cases {
            assert_eq!(http_status(&e).as_u16(), http, "{e}");
            assert_eq!(grpc_code(&e), grpc, "{e}");
        }
        assert_eq!(v2_http_status(&Error::field("points", "bad shape")).as_u16(), 400);
        assert_eq!(v2_http_status(&Error::NotFound("model".into())).as_u16(), 404);
        assert_eq!(v2_http_status(&Error::Overloaded).as_u16(), 429);
        let d = detail(&Error::field("points", "empty"));
        assert_eq!((d.code.as_str(), d.field.as_deref()), ("invalid_field", Some("points")));
        assert!(d.message.contains("points"));
    }
}
