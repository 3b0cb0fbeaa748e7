//! The one error type of posefuse. Transports map it to status codes in one place
//! (`server::errors`); everything else only constructs it.

use thiserror::Error;

/// Every failure a request, a bundle or a command can meet.
#[derive(Debug, Error)]
pub enum Error {
    /// The request body is not parseable (bad JSON syntax, wrong content type).
    #[error("malformed request: {0}")]
    Malformed(String),
    /// A field is missing, has the wrong type or an unusable value.
    #[error("invalid field `{field}`: {message}")]
    InvalidField { field: String, message: String },
    /// The request is valid but the sensors give a person too little to estimate a pose from
    /// (no LiDAR point in the box); reported per person, not for the frame.
    #[error("insufficient data in `{field}`: {message}")]
    InsufficientData { field: String, message: String },
    /// The request body is larger than the configured limit.
    #[error("request body exceeds the limit of {limit} bytes")]
    PayloadTooLarge { limit: usize },
    /// The work queue is full; the client should retry later.
    #[error("server overloaded: the request queue is full")]
    Overloaded,
    /// No such route or resource.
    #[error("not found: {0}")]
    NotFound(String),
    /// An administrative request where administration is not allowed (the serving port without
    /// the admin token, docs/OPERATIONS.md "Administration").
    #[error("forbidden: {0}")]
    Forbidden(String),
    /// The request did not finish within its deadline.
    #[error("request timed out after {0} ms")]
    Timeout(u64),
    /// The server is not ready (bundle not loaded or warming up) or is shutting down.
    #[error("not ready: {0}")]
    Unavailable(String),
    /// The client went away before its answer was ready; nobody reads what is sent, but the
    /// access log and the metrics tell it from the server's own failures.
    #[error("client closed the request: {0}")]
    ClientGone(String),
    /// A model bundle is missing, inconsistent or does not match its manifest.
    #[error("model bundle: {0}")]
    Bundle(String),
    /// ONNX Runtime failed.
    #[error("runtime: {0}")]
    Runtime(String),
    /// File-system or other I/O at the edges.
    #[error("io: {0}")]
    Io(String),
}

impl Error {
    /// Shorthand for an invalid-field error.
    pub fn field(field: impl Into<String>, message: impl Into<String>) -> Self {
        Error::InvalidField { field: field.into(), message: message.into() }
    }

    /// The same error with its field inside `parent` (`calibration.width` of `cameras[1]` becomes
    /// `cameras[1].calibration.width`): one camera's checks serve the single-camera form and each
    /// of a frame's `cameras`.
    pub fn within(self, parent: &str) -> Self {
        match self {
            _ if parent.is_empty() => self,
            Error::InvalidField { field, message } => {
                Error::InvalidField { field: format!("{parent}.{field}"), message }
            }
            Error::InsufficientData { field, message } => {
                Error::InsufficientData { field: format!("{parent}.{field}"), message }
            }
            other => other,
        }
    }

    /// The offending field, for errors about one.
    pub fn field_name(&self) -> Option<&str> {
        match self {
            Error::InvalidField { field, .. } | Error::InsufficientData { field, .. } => Some(field),
            _ => None,
        }
    }

    /// A stable, machine-readable code for the error (`{"error":{"code"}}`).
    pub fn code(&self) -> &'static str {
        match self {
            Error::Malformed(_) => "malformed_request",
            Error::InvalidField { .. } => "invalid_field",
            Error::InsufficientData { .. } => "insufficient_data",
            Error::PayloadTooLarge { .. } => "payload_too_large",
            Error::Overloaded => "overloaded",
            Error::NotFound(_) => "not_found",
            Error::Forbidden(_) => "forbidden",
            Error::Timeout(_) => "timeout",
            Error::Unavailable(_) => "unavailable",
            Error::ClientGone(_) => "client_closed_request",
            Error::Bundle(_) => "bundle_error",
            Error::Runtime(_) => "runtime_error",
            Error::Io(_) => "io_error",
        }
    }
}

impl From<std::io::Error> for Error {
    fn from(e: std::io::Error) -> Self {
        Error::Io(e.to_string())
    }
}

/// Result with posefuse's error.
pub type Result<T, E = Error> = std::result::Result<T, E>;
