//! Evaluation metrics (Waymo definitions; the paper's OKS/ACC on top): OKS, OKS/ACC, MPJPE, PCK,
//! PEM and OKS@2D, as pure functions plus a mergeable accumulator.
//!
//! `tests/golden/metrics.json` pins these numbers for the trainer's Python copy.

mod accumulator;
mod person;

pub use accumulator::{KeypointOks, MetricsAccumulator, MetricsReport, PCK_THRESHOLDS_3D_M};
pub use person::{
    box_scale_2d, box_scale_3d, evaluate_person, evaluate_person_partial, evaluate_projected, keypoint_oks, mpjpe,
    oks_acc, oks_threshold, pck, pem, pem_cost, PersonEval, OKS_THRESHOLD_COUNT, PEM_CLIP_M,
};
