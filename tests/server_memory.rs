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
async fn a_quiet_spell_after_work_trims_once() {
    let s = start(config()).await;
    let http = reqwest::Client::new();
    // the start's readiness polls are work too; let their quiet spell pass first. The /metrics
    // requests are work as well, so the page is read only after a spell
    let look = posefuse::server::memory::LOOK_EVERY;
    tokio::time::sleep(look * 4).await;
    let before = trims(&http, &s).await;
    assert_eq!(http.post(s.url("/v1/poses")).json(&fusion_frame()).send().await.unwrap().status(), 200);
    // no request at all for a whole look, then the next look trims; reading the page earlier
    // would be work again and move the trim later
    tokio::time::sleep(look * 5).await;
    assert_eq!(trims(&http, &s).await, before + 1, "one trim for the quiet spell after the request");
    s.shutdown().await.unwrap();
}
