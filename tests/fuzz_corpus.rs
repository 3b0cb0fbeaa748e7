//! The fuzz targets (fuzz/targets.rs) over their kept corpus and findings: every input the
//! fuzzer kept, and every input that once crashed a target (fuzz/regressions/<target>/), must
//! still be answered without a panic. Runs in the test command; the fuzzing itself is
//! `cargo fuzz run TARGET` (docs/TESTING.md).

#[path = "../fuzz/targets.rs"]
mod targets;

use std::path::Path;

fn run(target: &str, f: fn(&[u8])) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut inputs = 0;
    for dir in [root.join("corpus").join(target), root.join("regressions").join(target)] {
        let Ok(entries) = std::fs::read_dir(&dir) else { continue };
        for e in entries {
            let path = e.unwrap().path();
            let data = std::fs::read(&path).unwrap();
            if std::panic::catch_unwind(|| f(&data)).is_err() {
                panic!("{target} panics on {}", path.display());
            }
            inputs += 1;
        }
    }
    assert!(inputs > 0, "no corpus for {target} under {}", root.display());
}

#[test]
fn frame_json() {
    run("frame_json", targets::frame_json);
}

#[test]
fn kserve_request() {
    run("kserve_request", targets::kserve_request);
}

#[test]
fn proto_frame() {
    run("proto_frame", targets::proto_frame);
}

#[test]
fn points_b64() {
    run("points_b64", targets::points_b64);
}

#[test]
fn jpeg_decode() {
    run("jpeg_decode", targets::jpeg_decode);
}
