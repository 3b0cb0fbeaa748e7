//! The data crate's error: reading or writing a dataset, a drive log or training shards failed,
//! with what was being done. Typed (the binary's edge alone uses `anyhow`): a caller can tell a
//! missing file from a malformed column from a refused frame.

use std::fmt::Display;

/// Every failure of the simulator, the Waymo reader and converter and the ROS 2 log reader.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The data is not what the format or the command promises (a missing column, a wrong shape).
    #[error("{0}")]
    Invalid(String),
    /// Another failure, with what was being done when it happened. The cause is in the message,
    /// not in `source()`: `anyhow`'s report at the binary's edge would print it twice.
    #[error("{context}: {cause}")]
    Context { context: String, cause: Box<dyn std::error::Error + Send + Sync> },
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Parquet(#[from] parquet::errors::ParquetError),
    #[error(transparent)]
    Arrow(#[from] arrow_schema::ArrowError),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    #[error(transparent)]
    Mcap(#[from] mcap::McapError),
    #[error(transparent)]
    Image(#[from] image::ImageError),
    /// A frame, a geometry or a sample refused by posefuse's core.
    #[error(transparent)]
    Core(#[from] posefuse_core::error::Error),
}

/// Result with the data crate's error.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

/// What was being done, added to a failure (`file.open().context("reading the index")`).
pub trait Context<T> {
    fn context(self, context: impl Display) -> Result<T>;
    fn with_context<C: Display>(self, context: impl FnOnce() -> C) -> Result<T>;
}

impl<T, E: std::error::Error + Send + Sync + 'static> Context<T> for std::result::Result<T, E> {
    fn context(self, context: impl Display) -> Result<T> {
        self.map_err(|e| DataError::Context { context: context.to_string(), cause: Box::new(e) })
    }

    fn with_context<C: Display>(self, context: impl FnOnce() -> C) -> Result<T> {
        self.map_err(|e| DataError::Context { context: context().to_string(), cause: Box::new(e) })
    }
}

impl<T> Context<T> for Option<T> {
    fn context(self, context: impl Display) -> Result<T> {
        self.ok_or_else(|| DataError::Invalid(context.to_string()))
    }

    fn with_context<C: Display>(self, context: impl FnOnce() -> C) -> Result<T> {
        self.ok_or_else(|| DataError::Invalid(context().to_string()))
    }
}

/// An [`DataError::Invalid`] from a format string.
#[macro_export]
macro_rules! invalid {
    ($($arg:tt)*) => { $crate::error::DataError::Invalid(format!($($arg)*)) };
}

/// Returns an [`DataError::Invalid`] from a format string.
#[macro_export]
macro_rules! bail {
    ($($arg:tt)*) => { return Err($crate::invalid!($($arg)*).into()) };
}

/// Returns an [`DataError::Invalid`] unless the condition holds.
#[macro_export]
macro_rules! ensure {
    ($cond:expr, $($arg:tt)*) => {
        if !$cond {
            $crate::bail!($($arg)*);
        }
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(ok: bool) -> Result<u8> {
        ensure!(ok, "the {} is {}", "shape", 3);
        Ok(1)
    }

    #[test]
    fn context_names_what_was_done_and_keeps_the_cause() {
        let e = std::fs::read("/nonexistent/posefuse").context("reading the index").unwrap_err();
        assert!(e.to_string().starts_with("reading the index: "), "{e}");
        assert_eq!(None::<u8>.with_context(|| "no row 4").unwrap_err().to_string(), "no row 4");
        assert_eq!(read(false).unwrap_err().to_string(), "the shape is 3");
        assert_eq!(read(true).unwrap(), 1);
    }
}
