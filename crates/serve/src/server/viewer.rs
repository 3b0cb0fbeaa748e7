//! `GET /viewer`: a browser page that sends a frame to the API and draws the answer (the camera
//! image with each person's 2D pose, the LiDAR points with the 3D pose, ground truth and errors
//! when the frame has them). Everything it loads is embedded in the binary; it makes no request
//! outside this server.

use axum::extract::Path;
use axum::http::{header, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use serde::Serialize;

use super::errors::IntoHttpResponse as _;
use posefuse_core::error::Error;
use posefuse_core::keypoints;

/// The page's files: (name under `/viewer/`, content type, content).
const ASSETS: [(&str, &str, &str); 3] = [
    ("index.html", "text/html; charset=utf-8", include_str!("../../../../assets/viewer/index.html")),
    ("viewer.css", "text/css; charset=utf-8", include_str!("../../../../assets/viewer/viewer.css")),
    ("viewer.js", "text/javascript; charset=utf-8", include_str!("../../../../assets/viewer/viewer.js")),
];

/// Frames the page offers to open (`examples/`), by file name.
pub const EXAMPLES: [(&str, &str); 1] = [("frame.json", include_str!("../../../../examples/frame.json"))];

/// The page may load only from this server; images are decoded from the frame (blob URLs).
const CSP: &str = "default-src 'self'; img-src 'self' blob: data:; style-src 'self'; script-src 'self'; \
                   connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'";

/// Routes under `/viewer`, merged into the HTTP router.
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/viewer", get(|| async { asset("index.html") }))
        .route("/viewer/", get(|| async { asset("index.html") }))
        .route("/viewer/keypoints.json", get(keypoint_table))
        .route("/viewer/examples", get(example_list))
        .route("/viewer/examples/{name}", get(example))
        .route("/viewer/{file}", get(|Path(file): Path<String>| async move { asset(&file) }))
}

fn asset(name: &str) -> Response {
    match ASSETS.iter().find(|(n, _, _)| *n == name) {
        Some((_, content_type, body)) => {
            let mut resp = (*body).into_response();
            let h = resp.headers_mut();
            h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
            h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
            h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
            h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
            resp
        }
        None => Error::NotFound(format!("no viewer file `{name}`")).into_response(),
    }
}

/// The keypoint order, skeleton and OKS scales, so the page draws what the server defines.
#[derive(Serialize)]
struct KeypointTable {
    names: [&'static str; keypoints::K],
    skeleton: Vec<[usize; 2]>,
    oks_scales: [f64; keypoints::K],
}

async fn keypoint_table() -> Json<KeypointTable> {
    Json(KeypointTable {
        names: keypoints::NAMES,
        skeleton: keypoints::SKELETON.iter().map(|&(a, b)| [a, b]).collect(),
        oks_scales: keypoints::OKS_SCALES,
    })
}

async fn example_list() -> Json<Vec<&'static str>> {
    Json(EXAMPLES.iter().map(|(n, _)| *n).collect())
}

async fn example(Path(name): Path<String>) -> Response {
    match EXAMPLES.iter().find(|(n, _)| *n == name) {
        Some((_, body)) => ([(header::CONTENT_TYPE, "application/json")], *body).into_response(),
        None => Error::NotFound(format!("no example `{name}`")).into_response(),
    }
}

#[cfg(test)]
mod tests {
    use axum::body::{to_bytes, Body};
    use axum::http::{Request, StatusCode};
    use tower::ServiceExt;

    use super::*;
    use posefuse_core::frame::Frame;

    async fn get_path(path: &str) -> (StatusCode, String, String) {
        let app: Router = routes();
        let resp = app.oneshot(Request::get(path).body(Body::empty()).unwrap()).await.unwrap();
        let status = resp.status();
        let ct = resp.headers().get(header::CONTENT_TYPE).map_or("", |v| v.to_str().unwrap()).to_string();
        let body = to_bytes(resp.into_body(), 1 << 24).await.unwrap();
        (status, ct, String::from_utf8(body.to_vec()).unwrap())
    }

    /// Values of `attr="..."` in an HTML text.
    fn attribute_values<'a>(html: &'a str, attr: &str) -> Vec<&'a str> {
        let pat = format!(" {attr}=\"");
        html.match_indices(&pat).filter_map(|(i, _)| html[i + pat.len()..].split('"').next()).collect()
    }

    #[tokio::test]
    async fn the_page_and_every_file_it_references_are_served_from_the_binary() {
        for path in ["/viewer", "/viewer/"] {
            let (status, ct, html) = get_path(path).await;
            assert_eq!(status, StatusCode::OK);
            assert!(ct.starts_with("text/html"), "{ct}");
            assert!(html.contains("<title>"));
        }
        let (_, _, html) = get_path("/viewer").await;
        let refs: Vec<&str> =
            attribute_values(&html, "src").into_iter().chain(attribute_values(&html, "href")).collect();
        assert!(refs.len() >= 2, "the page references its script and style sheet: {refs:?}");
        for r in refs {
            // `data:` (the empty icon) and `#` anchors load nothing; everything else is ours.
            if r.starts_with('#') || r.starts_with("data:") {
                continue;
            }
            assert!(r.starts_with("/viewer/"), "reference outside the server: {r}");
            let (status, ct, body) = get_path(r).await;
            assert_eq!(status, StatusCode::OK, "{r}");
            assert!(!body.is_empty() && (ct.starts_with("text/css") || ct.starts_with("text/javascript")), "{r}: {ct}");
        }
        let (_, _, js) = get_path("/viewer/viewer.js").await;
        assert!(!js.contains("http://") && !js.contains("https://"), "the script must not reach other hosts");
    }

    #[tokio::test]
    async fn every_example_is_a_valid_frame_and_unknown_names_are_404() {
        let (status, _, list) = get_path("/viewer/examples").await;
        assert_eq!(status, StatusCode::OK);
        let names: Vec<String> = serde_json::from_str(&list).unwrap();
        assert!(names.contains(&"frame.json".to_string()));
        for name in names {
            let (status, ct, body) = get_path(&format!("/viewer/examples/{name}")).await;
            assert_eq!((status, ct.as_str()), (StatusCode::OK, "application/json"), "{name}");
            let frame: Frame = serde_json::from_str(&body).unwrap();
            frame.validate().unwrap();
        }
        let (status, _, body) = get_path("/viewer/examples/nope.json").await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(body.contains("\"not_found\"") && body.contains("nope.json"), "{body}");
        let (status, _, _) = get_path("/viewer/nope.js").await;
        assert_eq!(status, StatusCode::NOT_FOUND);
    }

    #[tokio::test]
    async fn the_keypoint_table_is_the_servers() {
        let (_, _, body) = get_path("/viewer/keypoints.json").await;
        let v: serde_json::Value = serde_json::from_str(&body).unwrap();
        assert_eq!(v["names"].as_array().unwrap().len(), keypoints::K);
        assert_eq!(v["names"][10], keypoints::NAMES[10]);
        let edges = v["skeleton"].as_array().unwrap();
        assert_eq!(edges.len(), keypoints::SKELETON.len());
        for (e, (a, b)) in edges.iter().zip(keypoints::SKELETON) {
            assert_eq!((e[0].as_u64(), e[1].as_u64()), (Some(a as u64), Some(b as u64)));
        }
        assert_eq!(v["oks_scales"][0].as_f64(), Some(keypoints::OKS_SCALES[0]));
    }
}
