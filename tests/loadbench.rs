//! `posefuse bench` against an in-process server: every image form and concurrency is answered,
//! only with 200, with every fixture person in the answers, and the raw reference is measured.

mod server_support;

use posefuse::loadbench::{run_bench, BenchOptions, ImageForm, LoadOptions, Protocol};
use std::time::Duration;

use posefuse::runtime::RuntimeConfig;
use server_support::*;

#[test]
fn the_bench_loads_a_server_with_every_image_form() {
    let data = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(data.path().join("requests")).unwrap();
    let frames = vec![fusion_frame(), three_mode_frame()];
    std::fs::write(data.path().join("requests/frames.json"), serde_json::to_vec(&frames).unwrap()).unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let mut shm_on = config();
    shm_on.shared_memory.enabled = true;
    let server = rt.block_on(start(shm_on));
    let forms = [ImageForm::AsIs, ImageForm::Jpeg420, ImageForm::Jpeg444, ImageForm::Rgb, ImageForm::RgbShm];
    let persons_per_frame: Vec<usize> = frames.iter().map(|f| f.persons.len()).collect();
    for protocol in [Protocol::Http, Protocol::Grpc] {
        // Shared memory travels in Open Inference Protocol requests over HTTP only.
        let forms: Vec<ImageForm> =
            forms.iter().copied().filter(|f| protocol == Protocol::Http || *f != ImageForm::RgbShm).collect();
        let load = LoadOptions {
            url: Some(server.url("")),
            server_pid: Some(std::process::id()),
            data: data.path().to_path_buf(),
            concurrency: vec![1, 3],
            duration: 0.3,
            image: forms.to_vec(),
            protocol,
            frames: 2,
            timeout: 30.0,
            no_raw: false,
            json: Some(data.path().join(format!("bench-{protocol:?}.json"))),
        };
        let args =
            BenchOptions { load, model_dir: model_dir(), runtime: RuntimeConfig::DEFAULT, serve_args: Vec::new() };
        let report = run_bench(args.clone()).unwrap();
        assert!(report.raw_frame_p50.is_some_and(|p| p > Duration::ZERO), "{report:?}");
        assert!(report.raw_persons_per_s.is_some_and(|p| p > 0.0), "{report:?}");
        // Both frames have fusion persons: the p50 is taken over three rounds of them at least,
        // and over a step's duration of inference (shorter than the 3 s cap here).
        assert!(report.raw_frames_timed >= 3 * frames.len(), "{report:?}");
        assert!(report.raw_timed >= Duration::from_secs_f64(0.3), "{report:?}");
        // The ceiling (batches of 16 on the same one worker) is of the order of one frame at a
        // time, counted here with all of a frame's persons (raw runs only its fusion ones): 0.46×
        // that on a quiet machine, as these tiny nets gain nothing from batching. An eighth leaves
        // room for a busy machine and still fails a count multiplied by the 0.3 s run (0.04×).
        let persons: usize = persons_per_frame.iter().sum();
        let one_at_a_time = persons as f64 / frames.len() as f64 / report.raw_frame_p50.unwrap().as_secs_f64();
        assert!(report.raw_persons_per_s.unwrap() >= one_at_a_time / 8.0, "{one_at_a_time} persons/s: {report:?}");
        let steps: Vec<(ImageForm, usize)> = report.steps.iter().map(|s| (s.form, s.clients)).collect();
        let want: Vec<(ImageForm, usize)> = forms.iter().flat_map(|&f| [(f, 1), (f, 3)]).collect();
        assert_eq!(steps, want, "{protocol:?}: one step per form and concurrency, in order");
        for s in &report.steps {
            let what = format!("{protocol:?} {:?} at {} clients", s.form, s.clients);
            assert!(s.answered > 0, "{what}: nothing answered");
            assert_eq!(s.statuses.keys().collect::<Vec<_>>(), ["200"], "{what}: {:?}", s.statuses);
            assert_eq!(s.statuses["200"], s.answered, "{what}");
            assert_eq!(s.clients_answered, s.clients, "{what}: every client was answered");
            // Clients cycle through the frames: every answer holds one frame's persons.
            let (lo, hi) = (persons_per_frame.iter().min().unwrap(), persons_per_frame.iter().max().unwrap());
            assert!(s.persons >= lo * s.answered && s.persons <= hi * s.answered, "{what}: {} persons", s.persons);
            assert!(s.frames_per_s > 0.0 && s.p50 > Duration::ZERO && s.p50 <= s.p99, "{what}: {s:?}");
        }
        // The JSON holds what the table shows, the same numbers as the report returned.
        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(args.load.json.as_ref().unwrap()).unwrap()).unwrap();
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        // serde_json reads floats back to within an ulp or so, not always bit for bit.
        let same = |j: &serde_json::Value, v: f64| j.as_f64().is_some_and(|j| (j - v).abs() <= 1e-12 * v.abs());
        assert_eq!(json["setup"]["frames"], 2);
        assert_eq!(json["setup"]["persons"], persons);
        assert_eq!(json["setup"]["device"], "cpu");
        assert_eq!(json["setup"]["protocol"], format!("{protocol:?}").to_lowercase());
        assert_eq!(json["setup"]["max_batch"], RuntimeConfig::DEFAULT.max_batch);
        assert!(same(&json["raw_frame_p50_ms"], ms(report.raw_frame_p50.unwrap())), "{json}");
        assert!(same(&json["raw_persons_per_s"], report.raw_persons_per_s.unwrap()), "{json}");
        assert_eq!(json["raw_frames_timed"], report.raw_frames_timed);
        // The server runs in this process: its peak is this process's, read a moment later.
        let own_peak_mb = std::fs::read_to_string("/proc/self/status")
            .unwrap()
            .lines()
            .find_map(|l| l.strip_prefix("VmHWM:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
            .unwrap()
            / 1024.0;
        let peak_mb = json["server_peak_rss_mb"].as_f64().unwrap();
        assert!(
            peak_mb > 1.0 && peak_mb <= own_peak_mb && peak_mb > 0.5 * own_peak_mb,
            "{peak_mb} of {own_peak_mb} MB"
        );
        let steps = json["steps"].as_array().unwrap();
        assert_eq!(steps.len(), report.steps.len());
        for (j, s) in steps.iter().zip(&report.steps) {
            let image = serde_json::to_value(s.form).unwrap();
            assert_eq!(j["image"], image);
            assert_eq!(
                (j["clients"].as_u64(), j["clients_answered"].as_u64()),
                (Some(s.clients as u64), Some(s.clients_answered as u64))
            );
            assert_eq!(
                (j["answered"].as_u64(), j["persons"].as_u64()),
                (Some(s.answered as u64), Some(s.persons as u64))
            );
            assert!(same(&j["p50_ms"], ms(s.p50)) && same(&j["p99_ms"], ms(s.p99)), "{j}");
            assert!(same(&j["frames_per_s"], s.frames_per_s) && same(&j["persons_per_s"], s.persons_per_s), "{j}");
            let per_frame = s.persons_per_s / s.frames_per_s;
            assert!((per_frame - s.persons as f64 / s.answered as f64).abs() < 1e-9, "{j}");
            assert_eq!(j["statuses"]["200"].as_u64(), Some(s.answered as u64));
            assert!(j["peak_rss_mb"].as_f64().is_some_and(|mb| mb > 1.0), "{j}");
        }
        let names: Vec<&str> = steps.iter().map(|s| s["image"].as_str().unwrap()).collect();
        assert!(names.contains(&"as-is") && names.contains(&"jpeg420"), "{names:?}");
        if protocol == Protocol::Grpc {
            let mut shm_grpc = args;
            shm_grpc.load.image = vec![ImageForm::RgbShm];
            let e = run_bench(shm_grpc).unwrap_err();
            assert!(e.to_string().contains("--protocol http"), "{e}");
        }
    }
    // The shared-memory form left no region registered and no object behind.
    let status: serde_json::Value =
        rt.block_on(async { reqwest::get(server.url("/v2/systemsharedmemory/status")).await?.json().await }).unwrap();
    assert_eq!(status, serde_json::json!([]));
    let left = std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with(&format!("posefuse-bench-{}-", std::process::id()))
        })
        .count();
    assert_eq!(left, 0);
    rt.block_on(server.shutdown()).unwrap();
}

#[test]
fn with_the_waiting_line_every_closed_loop_client_of_a_full_server_is_answered() {
    let data = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(data.path().join("requests")).unwrap();
    std::fs::write(data.path().join("requests/frames.json"), serde_json::to_vec(&[fusion_frame()]).unwrap()).unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    // One place for six clients: five always wait, so without the line they would be refused.
    let mut cfg = config();
    (cfg.decode_permits, cfg.admission_queue) = (1, 0);
    cfg.admission_line = posefuse::service::admission::Line { wait: Duration::from_secs(20), max: 8 };
    let server = rt.block_on(start(cfg));
    let load = LoadOptions {
        url: Some(server.url("")),
        server_pid: Some(std::process::id()),
        data: data.path().to_path_buf(),
        concurrency: vec![6],
        duration: 1.0,
        image: vec![ImageForm::AsIs],
        protocol: Protocol::Http,
        frames: 1,
        timeout: 30.0,
        no_raw: true,
        json: Some(data.path().join("bench.json")),
    };
    let report = run_bench(BenchOptions {
        load,
        model_dir: model_dir(),
        runtime: RuntimeConfig::DEFAULT,
        serve_args: Vec::new(),
    })
    .unwrap();
    // Without the raw reference, the JSON says so rather than leaving it out.
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.path().join("bench.json")).unwrap()).unwrap();
    assert!(json["raw_frame_p50_ms"].is_null() && json["raw_persons_per_s"].is_null(), "{json}");
    assert_eq!(json["steps"][0]["clients_answered"], 6);
    let s = &report.steps[0];
    assert_eq!(s.statuses.keys().collect::<Vec<_>>(), ["200"], "{:?}", s.statuses);
    assert_eq!(s.clients_answered, 6, "{s:?}");
    rt.block_on(server.shutdown()).unwrap();
}
