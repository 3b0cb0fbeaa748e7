//! `posefuse bench` against an in-process server: every image form is answered.

mod server_support;

use posefuse::loadbench::{run_bench, BenchOptions, ImageForm, Protocol};
use posefuse::runtime::RuntimeConfig;
use server_support::*;

#[test]
fn the_bench_loads_a_server_with_every_image_form() {
    let data = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(data.path().join("requests")).unwrap();
    let frames = vec![fusion_frame(), three_mode_frame()];
    std::fs::write(data.path().join("requests/frames.json"), serde_json::to_vec(&frames).unwrap()).unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let server = rt.block_on(start(config()));
    for protocol in [Protocol::Http, Protocol::Grpc] {
        let args = BenchOptions {
            url: Some(server.url("")),
            server_pid: Some(std::process::id()),
            data: data.path().to_path_buf(),
            concurrency: vec![1, 3],
            duration: 0.3,
            image: vec![ImageForm::AsIs, ImageForm::Jpeg420, ImageForm::Jpeg444, ImageForm::Rgb],
            protocol,
            frames: 2,
            timeout: 30.0,
            no_raw: false,
            model_dir: model_dir(),
            runtime: RuntimeConfig::DEFAULT,
            serve_args: Vec::new(),
        };
        // fails when a step gets no 200 answer, or the raw ceiling cannot run on the persons
        run_bench(args).unwrap();
    }
    rt.block_on(server.shutdown()).unwrap();
}
