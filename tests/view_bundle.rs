//! The view-frame bundle (`models/view`, docs/BUNDLE.md "Point frame") needs no box heading: a
//! box turned end for end (the same box, its heading off by 180°) gives the same answer, while the
//! default bundle, which reads the facing from the heading, answers with left and right exchanged.

mod server_support;

use std::path::PathBuf;
use std::time::Duration;

use posefuse::frame::Frame;
use posefuse::runtime::{Runtime, RuntimeConfig};
use posefuse::service::Predictor;
use server_support::*;

async fn predictor(dir: PathBuf) -> Predictor {
    let runtime =
        tokio::task::spawn_blocking(move || Runtime::load(&dir, &RuntimeConfig::DEFAULT)).await.unwrap().unwrap();
    assert!(runtime.wait_ready(Duration::from_secs(60)));
    Predictor::new(runtime)
}

/// Keypoints and facing yaw of the frame's persons.
async fn answer(p: &Predictor, frame: Frame) -> Vec<(Vec<[f64; 3]>, f64)> {
    let resp = p.answer(frame, None, Duration::from_secs(30)).await.unwrap();
    resp.persons
        .iter()
        .map(|q| (q.keypoints.iter().map(|k| k.xyz).collect(), q.facing.as_ref().map_or(f64::NAN, |f| f.yaw)))
        .collect()
}

fn turned_end_for_end(mut frame: Frame) -> Frame {
    for p in &mut frame.persons {
        p.box_3d.heading += std::f64::consts::PI;
    }
    frame
}

fn max_distance(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt())
        .fold(0.0, f64::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_view_bundle_answers_the_same_whatever_the_heading() {
    let view_dir = model_dir().with_file_name("view");
    let view = predictor(view_dir).await;
    let default = predictor(model_dir()).await;
    for frame in [fusion_frame(), three_mode_frame()] {
        let (a, b) = (answer(&view, frame.clone()).await, answer(&view, turned_end_for_end(frame.clone())).await);
        assert_eq!(a.len(), b.len());
        for ((ka, fa), (kb, fb)) in a.iter().zip(&b) {
            assert!(max_distance(ka, kb) < 1e-4, "view bundle moved by {} m", max_distance(ka, kb));
            assert!((fa - fb).abs() < 1e-6 || (fa.is_nan() && fb.is_nan()));
        }
    }
    // The default bundle turns its answer with the box: far from its first answer.
    let frame = fusion_frame();
    let (a, b) = (answer(&default, frame.clone()).await, answer(&default, turned_end_for_end(frame)).await);
    assert!(max_distance(&a[0].0, &b[0].0) > 0.1, "the default bundle ignored the heading");
}
