//! JSON into the service's types, naming the field of a data error by its path
//! (`persons[0].box_3d.height`). Used by the HTTP transport, the CLI and the evaluation.

use serde::de::DeserializeOwned;

use crate::error::{Error, Result};

/// Parses JSON; trailing data is a syntax error.
pub fn parse_json<T: DeserializeOwned>(bytes: &[u8]) -> Result<T> {
    let mut de = serde_json::Deserializer::from_slice(bytes);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        // serde_json reports some type errors (a number for an enum, a 4-number array for a
        // 3-number one) as syntax errors; in well-formed JSON they are the field's fault.
        let well_formed = serde_json::from_slice::<serde::de::IgnoredAny>(bytes).is_ok();
        if well_formed && e.inner().classify() != serde_json::error::Category::Data {
            let path = e.path().to_string();
            let field = if path == "." || path.is_empty() { "body".to_string() } else { path };
            return Error::field(field, e.into_inner().to_string());
        }
        path_error(e)
    })?;
    de.end().map_err(|e| Error::Malformed(format!("invalid JSON: {e}")))?;
    Ok(value)
}

/// A JSON value (one batch item) into a typed value, naming the field on error.
pub fn from_value<T: DeserializeOwned>(v: serde_json::Value) -> Result<T> {
    serde_path_to_error::deserialize(v).map_err(path_error)
}

fn path_error(e: serde_path_to_error::Error<serde_json::Error>) -> Error {
    let path = e.path().to_string();
    let inner = e.into_inner();
    match inner.classify() {
        serde_json::error::Category::Data => {
            let msg = inner.to_string();
            // serde reports a missing key at its parent; name the key itself.
            let key = msg.strip_prefix("missing field `").and_then(|rest| rest.split('`').next());
            let parent = if path == "." || path.is_empty() { None } else { Some(path) };
            let field = match (parent, key) {
                (Some(p), Some(k)) => format!("{p}.{k}"),
                (None, Some(k)) => k.to_string(),
                (Some(p), None) => p,
                (None, None) => "body".to_string(),
            };
            Error::field(field, msg)
        }
        _ => Error::Malformed(format!("invalid JSON: {inner}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field_of<T: DeserializeOwned + std::fmt::Debug>(json: &str) -> (String, String) {
        match parse_json::<T>(json.as_bytes()) {
            Err(e) => (e.code().to_string(), e.field_name().unwrap_or("").to_string()),
            Ok(v) => panic!("parsed: {v:?}"),
        }
    }

    #[test]
    fn json_errors_name_the_field() {
        let (code, field) = field_of::<crate::frame::Box2d>(r#"{"center_x": 1, "center_y": 2, "width": 3}"#);
        assert_eq!((code.as_str(), field.as_str()), ("invalid_field", "height"));
        let (_, field) = field_of::<Vec<crate::frame::Box2d>>(
            r#"[{"center_x": 1, "center_y": 2, "width": 3, "height": 4}, {"center_x": "a"}]"#,
        );
        assert_eq!(field, "[1].center_x");
        let (_, field) = field_of::<Vec<crate::frame::Box2d>>(
            r#"[{"center_x": 1, "center_y": 2, "width": 3, "height": 4, "x": 0}]"#,
        );
        assert_eq!(field, "[0].x");
        let (code, _) = field_of::<crate::frame::Box2d>("{oops");
        assert_eq!(code, "malformed_request");
        let (code, _) =
            field_of::<crate::frame::Box2d>(r#"{"center_x": 1, "center_y": 2, "width": 3, "height": 4} trailing"#);
        assert_eq!(code, "malformed_request");
    }
}
