//! Administration is locked: model reload is refused on the serving port unless the caller bears
//! the admin token, is served without one on the admin listener, and may only name bundles in
//! the model repository, with errors that say nothing about paths outside it.

mod server_support;

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{json, Value};
use server_support::*;

const TOKEN: &str = "an-admin-token-of-some-length";

async fn reload_at(url: &str, token: Option<&str>, body: Option<Value>) -> (u16, Value) {
    let mut r = reqwest::Client::new().post(format!("{url}/v1/models:reload"));
    if let Some(t) = token {
        r = r.bearer_auth(t);
    }
    if let Some(b) = body {
        r = r.json(&b);
    }
    let r = r.send().await.unwrap();
    let status = r.status().as_u16();
    (status, r.json().await.unwrap_or(Value::Null))
}

/// `repository/name`: a copy of the default bundle with version `name`.
fn bundle_in(repository: &Path, name: &str) -> PathBuf {
    let d = repository.join(name);
    std::fs::create_dir_all(&d).unwrap();
    for e in std::fs::read_dir(model_dir()).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, d.join(p.file_name().unwrap())).unwrap();
    }
    let m = d.join("manifest.json");
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&m).unwrap()).unwrap();
    v["version"] = json!(name);
    std::fs::write(m, serde_json::to_string(&v).unwrap()).unwrap();
    d
}

async fn serving_version(s: &TestServer) -> String {
    let m: Value = reqwest::get(s.url("/v1/models")).await.unwrap().json().await.unwrap();
    m["version"].as_str().unwrap().to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_serving_port_refuses_reload_by_default_and_says_nothing_of_the_path() {
    let s = start(config()).await;
    let base = format!("http://{}", s.addr);
    for body in [None, Some(json!({"model_dir": "/etc"})), Some(json!({"model_dir": "/no/such/dir"}))] {
        let (status, r) = reload_at(&base, None, body.clone()).await;
        assert_eq!(status, 403, "{body:?}: {r}");
        assert_eq!(r["error"]["code"], "forbidden");
        let msg = r["error"]["message"].as_str().unwrap();
        assert!(!msg.contains("/etc") && !msg.contains("manifest"), "{msg}");
    }
    // a token sent to a server that has none is refused as well
    assert_eq!(reload_at(&base, Some(TOKEN), None).await.0, 403);
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_admin_token_admits_reload_on_the_serving_port_within_the_repository() {
    let repository = tempfile::tempdir().unwrap();
    bundle_in(repository.path(), "v2");
    let outside = tempfile::tempdir().unwrap();
    let elsewhere = bundle_in(outside.path(), "elsewhere");
    let mut c = config();
    c.admin.token = Some(TOKEN.into());
    c.admin.repository = Some(repository.path().to_path_buf());
    let s = start(c).await;
    let base = format!("http://{}", s.addr);
    assert_eq!(reload_at(&base, Some("wrong-token-of-some-length"), None).await.0, 403);
    assert_eq!(reload_at(&base, None, Some(json!({"model_dir": "v2"}))).await.0, 403);
    // a loadable bundle outside the repository and a path that does not exist read alike
    for asked in [elsewhere.to_str().unwrap(), "../elsewhere", "/etc", "missing"] {
        let (status, r) = reload_at(&base, Some(TOKEN), Some(json!({"model_dir": asked}))).await;
        assert_eq!(status, 422, "{asked}: {r}");
        assert_eq!(r["error"]["field"], "model_dir");
        assert_eq!(
            r["error"]["message"].as_str().unwrap(),
            format!("invalid field `model_dir`: no bundle `{asked}` in the model repository")
        );
    }
    assert_ne!(serving_version(&s).await, "v2");
    let (status, r) = reload_at(&base, Some(TOKEN), Some(json!({"model_dir": "v2"}))).await;
    assert_eq!(status, 200, "{r}");
    assert_eq!(r["model"]["version"], "v2");
    assert_eq!(serving_version(&s).await, "v2");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_repository_only_the_serving_bundle_reloads() {
    let (s, admin) = start_with_admin(config(), true).await;
    let admin = admin.unwrap();
    let (status, r) = reload_at(&admin, None, Some(json!({"model_dir": model_dir()}))).await;
    assert_eq!(status, 422, "{r}");
    assert!(r["error"]["message"].as_str().unwrap().contains("--model-repository"), "{r}");
    let (status, r) = reload_at(&admin, None, None).await;
    assert_eq!(status, 200, "{r}");
    s.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_admin_listener_serves_reload_and_nothing_else() {
    let repository = tempfile::tempdir().unwrap();
    bundle_in(repository.path(), "v3");
    let mut c = config();
    c.admin.repository = Some(repository.path().to_path_buf());
    let (s, admin) = start_with_admin(c, true).await;
    let admin = admin.unwrap();
    let (status, r) = reload_at(&admin, None, Some(json!({"model_dir": "v3"}))).await;
    assert_eq!(status, 200, "{r}");
    assert_eq!(serving_version(&s).await, "v3");
    // the serving port still refuses, and the admin port serves no inference
    assert_eq!(reload_at(&format!("http://{}", s.addr), None, None).await.0, 403);
    let r = reqwest::Client::new().post(format!("{admin}/v1/poses")).json(&json!({})).send().await.unwrap();
    assert_eq!(r.status(), 404);
    s.shutdown().await.unwrap();
}

/// `posefuse serve` reads the flags: a token file admits the serving port, `--admin-addr` opens
/// the admin listener, and the logged configuration does not show the token.
#[test]
fn serve_flags_open_the_admin_listener_and_read_the_token_file() {
    let free = || std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    let (addr, admin) = (free(), free());
    let dir = tempfile::tempdir().unwrap();
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, format!("{TOKEN}\n")).unwrap();
    let log = std::fs::File::create(dir.path().join("log")).unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_posefuse"))
        .args(["serve", "--addr", &addr.to_string(), "--admin-addr", &admin.to_string(), "--model-dir"])
        .arg(model_dir())
        .arg("--admin-token-file")
        .arg(&token_file)
        .env_remove(posefuse::server::admin::TOKEN_ENV)
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .spawn()
        .unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let outcome = rt.block_on(async {
        let base = format!("http://{addr}");
        let client = reqwest::Client::new();
        for _ in 0..1500 {
            if client.get(format!("{base}/readyz")).send().await.is_ok_and(|r| r.status() == 200) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let public = reload_at(&base, None, None).await.0;
        let with_token = reload_at(&base, Some(TOKEN), None).await.0;
        let on_admin = reload_at(&format!("http://{admin}"), None, None).await.0;
        (public, with_token, on_admin)
    });
    let _ = child.kill();
    let _ = child.wait();
    let log = std::fs::read_to_string(dir.path().join("log")).unwrap();
    assert_eq!(outcome, (403, 200, 200), "{log}");
    assert!(log.contains("<redacted>") && !log.contains(TOKEN), "the token must not be logged:\n{log}");
}
