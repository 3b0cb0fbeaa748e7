//! The serving loop gives freed heap memory back once it falls quiet after work
//! (docs/OPERATIONS.md, "Memory"). Its own test binary: the metrics recorder is per process, and
//! another test's server trimming would count here.

mod server_support;

use server_support::*;

async fn trims(http: &reqwest::Client, s: &TestServer) -> u64 {
    let page = http.get(s.url("/metrics")).send().await.unwrap().text().await.unwrap();
    let line = page.lines().find(|l| l.starts_with("posefuse_memory_trims_total ")).unwrap_or_else(|| panic!("{page}"));
    line.rsplit(' ').next().and_then(|v| v.parse().ok()).unwrap_or_else(|| panic!("{line}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_quiet_spell_after_frames_trims_once_and_other_requests_never() {
    let s = start(config()).await;
    let http = reqwest::Client::new();
    let look = posefuse::server::memory::LOOK_EVERY;
    // the start's readiness polls and these pages carry no frame: no trim, however long
    tokio::time::sleep(look * 3).await;
    assert_eq!(trims(&http, &s).await, 0, "a trim without a frame answered");
    assert_eq!(http.post(s.url("/v1/poses")).json(&fusion_frame()).send().await.unwrap().status(), 200);
    // no frame for a whole look, then the next look trims; reading the page meanwhile is no work
    for _ in 0..5 {
        tokio::time::sleep(look).await;
        let _ = trims(&http, &s).await;
    }
    assert_eq!(trims(&http, &s).await, 1, "one trim for the quiet spell after the frame");
    s.shutdown().await.unwrap();
}
