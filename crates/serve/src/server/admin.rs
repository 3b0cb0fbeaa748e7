//! Administration (model reload) is locked by default: the serving port refuses it (403) unless
//! the caller bears the admin token (`--admin-token-file`, `POSEFUSE_ADMIN_TOKEN`), and
//! `--admin-addr` serves it without a token on a separate listener meant for loopback. A reload
//! that names a bundle may only name one under the model repository (`--model-repository`), and
//! its errors never say whether a path outside it exists. SIGHUP reloads the serving bundle as
//! before (docs/OPERATIONS.md, "Administration").

use std::net::SocketAddr;
use std::path::{Component, Path, PathBuf};

use axum::http::{header, HeaderMap};

use posefuse_core::error::{Error, Result};

/// How administration is reached.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct AdminConfig {
    /// A listener serving the admin routes without a token (loopback is the intended use).
    pub addr: Option<SocketAddr>,
    /// A bearer token that admits the admin routes on the serving port.
    pub token: Option<String>,
    /// The directory every bundle a reload names must lie in; without it a reload can only
    /// reload the serving bundle.
    pub repository: Option<PathBuf>,
}

/// The token is a secret: the effective configuration is logged without it.
impl std::fmt::Debug for AdminConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AdminConfig")
            .field("addr", &self.addr)
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field("repository", &self.repository)
            .finish()
    }
}

/// The environment variable an admin token may come from.
pub const TOKEN_ENV: &str = "POSEFUSE_ADMIN_TOKEN";

/// Shortest admin token accepted: a guessable token is no lock.
const MIN_TOKEN_LEN: usize = 16;

/// The admin token: the first line of `file` when given, else `env` (the value of
/// [`TOKEN_ENV`]); `None` when neither is set. Refuses empty and short tokens.
pub fn read_token(file: Option<&Path>, env: Option<String>) -> Result<Option<String>> {
    let token = match (file, env) {
        (Some(f), _) => {
            let text = std::fs::read_to_string(f)
                .map_err(|e| Error::Io(format!("cannot read the admin token file {}: {e}", f.display())))?;
            text.lines().next().unwrap_or("").trim().to_string()
        }
        (None, Some(v)) => v.trim().to_string(),
        (None, None) => return Ok(None),
    };
    if token.len() < MIN_TOKEN_LEN {
        return Err(Error::field("admin token", format!("must be at least {MIN_TOKEN_LEN} characters")));
    }
    Ok(Some(token))
}

/// Whether a request on the serving port may administer: it bears `Authorization: Bearer
/// <token>` and a token is configured.
pub fn authorize(headers: &HeaderMap, token: Option<&str>) -> Result<()> {
    let refused = || {
        Error::Forbidden(
            "administration is not served on this port without the admin token (see --admin-addr, \
             --admin-token-file)"
                .into(),
        )
    };
    let Some(token) = token else { return Err(refused()) };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .ok_or_else(refused)?;
    if constant_time_eq(given.trim().as_bytes(), token.as_bytes()) {
        Ok(())
    } else {
        Err(refused())
    }
}

/// Compares secrets in time independent of where they differ (the length aside).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// The directory of the bundle `requested` names: a path relative to `repository` (or an
/// absolute one inside it) that, with every link resolved, stays inside it. Every refusal reads
/// the same whether or not the path exists, so a caller learns nothing outside the repository.
pub fn resolve_bundle(repository: Option<&Path>, requested: &str) -> Result<PathBuf> {
    let Some(root) = repository else {
        return Err(Error::field(
            "model_dir",
            "naming a bundle needs a model repository (--model-repository); without one only the serving \
             bundle reloads (send no model_dir)",
        ));
    };
    let not_there = || Error::field("model_dir", format!("no bundle `{requested}` in the model repository"));
    let asked = Path::new(requested);
    if requested.is_empty() || asked.components().any(|c| matches!(c, Component::ParentDir)) {
        return Err(not_there());
    }
    let root = root.canonicalize().map_err(|_| Error::Io("the model repository cannot be read".into()))?;
    let candidate = if asked.is_absolute() { asked.to_path_buf() } else { root.join(asked) };
    match candidate.canonicalize() {
        Ok(dir) if dir.starts_with(&root) && dir != root && dir.is_dir() => Ok(dir),
        _ => Err(not_there()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bearer(v: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(header::AUTHORIZATION, v.parse().unwrap());
        h
    }

    #[test]
    fn the_serving_port_administers_only_with_the_right_token() {
        let token = "0123456789abcdef-secret";
        assert!(authorize(&HeaderMap::new(), None).is_err());
        assert!(authorize(&bearer(&format!("Bearer {token}")), None).is_err(), "no token configured: refused");
        assert!(authorize(&HeaderMap::new(), Some(token)).is_err());
        assert!(authorize(&bearer("Bearer wrong"), Some(token)).is_err());
        assert!(authorize(&bearer(&format!("Bearer {token}x")), Some(token)).is_err());
        // same length, one byte or two bytes off (a fold that forgets a difference, or lets two
        // cancel, would admit them)
        assert!(authorize(&bearer("Bearer 0123456789abcdef-secreT"), Some(token)).is_err());
        assert!(authorize(&bearer("Bearer 1023456789abcdef-secret"), Some(token)).is_err());
        assert!(authorize(&bearer(token), Some(token)).is_err(), "the scheme is required");
        authorize(&bearer(&format!("Bearer {token}")), Some(token)).unwrap();
        let e = authorize(&HeaderMap::new(), Some(token)).unwrap_err();
        assert!(matches!(e, Error::Forbidden(_)) && e.to_string().contains("--admin-addr"), "{e}");
    }

    #[test]
    fn the_logged_configuration_holds_no_token() {
        let c = AdminConfig { token: Some("0123456789abcdef-secret".into()), ..AdminConfig::default() };
        let shown = format!("{c:?}");
        assert!(!shown.contains("secret") && shown.contains("<redacted>"), "{shown}");
    }

    #[test]
    fn tokens_come_from_a_file_or_the_environment_and_must_be_long() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("token");
        std::fs::write(&f, "file-token-0123456789\nignored\n").unwrap();
        assert_eq!(
            read_token(Some(&f), Some("env-token-0123456789".into())).unwrap().as_deref(),
            Some("file-token-0123456789")
        );
        assert_eq!(
            read_token(None, Some(" env-token-0123456789 ".into())).unwrap().as_deref(),
            Some("env-token-0123456789")
        );
        assert_eq!(read_token(None, None).unwrap(), None);
        assert!(read_token(None, Some("short".into())).is_err());
        // the bound: 16 characters are enough, 15 are not
        assert_eq!(read_token(None, Some("0123456789abcdef".into())).unwrap().as_deref(), Some("0123456789abcdef"));
        assert!(read_token(None, Some("0123456789abcde".into())).is_err());
        assert!(read_token(Some(&dir.path().join("missing")), None).is_err());
    }

    #[test]
    fn a_reload_names_only_bundles_inside_the_repository() {
        let top = tempfile::tempdir().unwrap();
        let repo = top.path().join("models");
        std::fs::create_dir_all(repo.join("v2")).unwrap();
        std::fs::create_dir_all(top.path().join("secret")).unwrap();
        std::os::unix::fs::symlink(top.path().join("secret"), repo.join("escape")).unwrap();
        let repo_canon = repo.canonicalize().unwrap();
        assert_eq!(resolve_bundle(Some(&repo), "v2").unwrap(), repo_canon.join("v2"));
        assert_eq!(resolve_bundle(Some(&repo), repo.join("v2").to_str().unwrap()).unwrap(), repo_canon.join("v2"));
        // outside, through `..`, through a link, the root itself, absent: one answer for all
        let outside = top.path().join("secret");
        for asked in ["../secret", "v2/../../secret", "escape", "", ".", "missing", "/etc", outside.to_str().unwrap()] {
            let e = resolve_bundle(Some(&repo), asked).unwrap_err();
            assert_eq!(e.field_name(), Some("model_dir"), "{asked}");
            assert_eq!(
                e.to_string(),
                format!("invalid field `model_dir`: no bundle `{asked}` in the model repository")
            );
        }
        // without a repository nothing can be named
        let e = resolve_bundle(None, "v2").unwrap_err();
        assert!(e.to_string().contains("--model-repository"), "{e}");
    }
}
