//! The model bundle: `manifest.json` plus three ONNX files. Loading checks everything that can be
//! checked without ONNX Runtime (files, hashes, declared shapes against the pre-processing
//! config); `models` checks the sessions against the same declarations.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use posefuse_core::error::{Error, Result};
use posefuse_core::keypoints::{K, NAMES, WAYMO_TYPES};
use posefuse_core::pipeline::PipelineConfig;

/// The manifest format this server reads.
pub const FORMAT_VERSION: u32 = 1;

/// `manifest.json`, the parts the server relies on (the rest is kept in [`Bundle::raw`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    pub name: String,
    pub version: String,
    pub keypoints: ManifestKeypoints,
    pub preprocessing: PipelineConfig,
    pub models: ManifestModels,
}

/// Keypoint order the networks were trained with.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ManifestKeypoints {
    pub names: Vec<String>,
    pub waymo_types: Vec<u32>,
}

/// The three networks.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ManifestModels {
    pub camera: ModelSpec,
    pub point_fusion: ModelSpec,
    pub point_lidar: ModelSpec,
}

/// One ONNX file and its declared tensors (`-1` = dynamic axis).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelSpec {
    pub file: String,
    pub sha256: String,
    pub inputs: BTreeMap<String, Vec<i64>>,
    pub outputs: BTreeMap<String, Vec<i64>>,
}

/// Which network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ModelKind {
    Camera,
    PointFusion,
    PointLidar,
}

impl ModelKind {
    /// All kinds, in a fixed order.
    pub const ALL: [ModelKind; 3] = [ModelKind::Camera, ModelKind::PointFusion, ModelKind::PointLidar];

    /// The manifest key (`models.<key>`), also used as a metrics label.
    pub fn key(self) -> &'static str {
        match self {
            ModelKind::Camera => "camera",
            ModelKind::PointFusion => "point_fusion",
            ModelKind::PointLidar => "point_lidar",
        }
    }
}

/// A model's resolved I/O: the tensor names the server feeds and reads, and per-item shapes.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelIo {
    pub path: PathBuf,
    pub input: String,
    /// Input shape without the batch axis.
    pub input_shape: Vec<usize>,
    pub output: String,
    /// Output shape without the batch axis.
    pub output_shape: Vec<usize>,
    /// Every declared tensor, for checking the session (name → full shape with the batch axis).
    pub declared_inputs: BTreeMap<String, Vec<i64>>,
    pub declared_outputs: BTreeMap<String, Vec<i64>>,
}

impl ModelIo {
    /// Floats of one item's input.
    pub fn input_len(&self) -> usize {
        self.input_shape.iter().product()
    }

    /// Floats of one item's output.
    pub fn output_len(&self) -> usize {
        self.output_shape.iter().product()
    }
}

/// A validated bundle.
#[derive(Debug, Clone)]
pub struct Bundle {
    pub dir: PathBuf,
    pub manifest: Manifest,
    /// `manifest.json` as written, served by `GET /v1/models`.
    pub raw: serde_json::Value,
    pub camera: ModelIo,
    pub point_fusion: ModelIo,
    pub point_lidar: ModelIo,
}

impl Bundle {
    /// Reads and validates `dir/manifest.json` and the files it names.
    pub fn load(dir: &Path) -> Result<Bundle> {
        let manifest_path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&manifest_path).map_err(|e| {
            Error::Bundle(format!(
                "cannot read {}: {e} (export a bundle with `python -m posefuse_train.export` or pass --model-dir)",
                manifest_path.display()
            ))
        })?;
        let raw: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::Bundle(format!("{}: not valid JSON: {e}", manifest_path.display())))?;
        let manifest: Manifest = serde_path_to_error::deserialize(&raw)
            .map_err(|e| Error::Bundle(format!("{}: field `{}`: {}", manifest_path.display(), e.path(), e.inner())))?;
        let bundle = Bundle::from_manifest(dir, manifest, raw)?;
        for kind in ModelKind::ALL {
            let spec = bundle.spec(kind);
            check_sha256(&bundle.io(kind).path, &spec.sha256, kind)?;
        }
        Ok(bundle)
    }

    /// Validates a parsed manifest (no file access except existence checks).
    pub fn from_manifest(dir: &Path, manifest: Manifest, raw: serde_json::Value) -> Result<Bundle> {
        if manifest.format_version != FORMAT_VERSION {
            return Err(Error::Bundle(format!(
                "manifest format_version is {}, this server reads {FORMAT_VERSION}",
                manifest.format_version
            )));
        }
        let names: Vec<&str> = manifest.keypoints.names.iter().map(String::as_str).collect();
        if names != NAMES || manifest.keypoints.waymo_types != WAYMO_TYPES {
            return Err(Error::Bundle(format!(
                "manifest keypoints {names:?} / {:?} differ from the server's order {NAMES:?} / {WAYMO_TYPES:?}",
                manifest.keypoints.waymo_types
            )));
        }
        let cfg = &manifest.preprocessing;
        cfg.validate().map_err(|e| Error::Bundle(format!("manifest preprocessing: {e}")))?;
        let (s, h, n) = (cfg.image_size as usize, cfg.heatmap_size as usize, cfg.num_points as usize);
        let camera = resolve(dir, ModelKind::Camera, &manifest.models.camera, &[3, s, s], &[K, h, h])?;
        let point_fusion = resolve(dir, ModelKind::PointFusion, &manifest.models.point_fusion, &[n, 3 + K], &[K, 3])?;
        let point_lidar = resolve(dir, ModelKind::PointLidar, &manifest.models.point_lidar, &[n, 3], &[K, 3])?;
        Ok(Bundle { dir: dir.to_path_buf(), manifest, raw, camera, point_fusion, point_lidar })
    }

    /// The pre-processing configuration every request is prepared with.
    pub fn config(&self) -> &PipelineConfig {
        &self.manifest.preprocessing
    }

    /// A model's manifest entry.
    pub fn spec(&self, kind: ModelKind) -> &ModelSpec {
        match kind {
            ModelKind::Camera => &self.manifest.models.camera,
            ModelKind::PointFusion => &self.manifest.models.point_fusion,
            ModelKind::PointLidar => &self.manifest.models.point_lidar,
        }
    }

    /// A model's resolved I/O.
    pub fn io(&self, kind: ModelKind) -> &ModelIo {
        match kind {
            ModelKind::Camera => &self.camera,
            ModelKind::PointFusion => &self.point_fusion,
            ModelKind::PointLidar => &self.point_lidar,
        }
    }

    /// Whether the bundle was exported without training (tests only).
    pub fn trained(&self) -> Option<bool> {
        self.raw.pointer("/training/trained").and_then(serde_json::Value::as_bool)
    }
}

fn shape_text(s: &[i64]) -> String {
    format!("{s:?}")
}

/// Picks the fed input and the read output of one model and checks the declared shapes against
/// the pre-processing config: a bundle exported for another S or N must not load.
fn resolve(dir: &Path, kind: ModelKind, spec: &ModelSpec, input: &[usize], output: &[usize]) -> Result<ModelIo> {
    let key = kind.key();
    let path = dir.join(&spec.file);
    if !path.is_file() {
        return Err(Error::Bundle(format!("models.{key}.file: {} does not exist", path.display())));
    }
    let want_in: Vec<i64> = std::iter::once(-1).chain(input.iter().map(|&d| d as i64)).collect();
    let want_out: Vec<i64> = std::iter::once(-1).chain(output.iter().map(|&d| d as i64)).collect();
    if spec.inputs.len() != 1 {
        return Err(Error::Bundle(format!(
            "models.{key}.inputs: expected exactly one input, the manifest declares {:?}",
            spec.inputs.keys().collect::<Vec<_>>()
        )));
    }
    let (in_name, in_shape) = spec.inputs.iter().next().map(|(n, s)| (n.clone(), s.clone())).unwrap_or_default();
    if in_shape != want_in {
        return Err(Error::Bundle(format!(
            "models.{key}.inputs.{in_name}: declared shape {} but the preprocessing config needs {}",
            shape_text(&in_shape),
            shape_text(&want_in)
        )));
    }
    let matching: Vec<&String> = spec.outputs.iter().filter(|(_, s)| **s == want_out).map(|(n, _)| n).collect();
    let out_name = match matching.as_slice() {
        [one] => (*one).clone(),
        [] => {
            return Err(Error::Bundle(format!(
                "models.{key}.outputs: no output has shape {} (declared: {:?})",
                shape_text(&want_out),
                spec.outputs
            )))
        }
        many => {
            return Err(Error::Bundle(format!(
                "models.{key}.outputs: several outputs have shape {}: {many:?}",
                shape_text(&want_out)
            )))
        }
    };
    Ok(ModelIo {
        path,
        input: in_name,
        input_shape: input.to_vec(),
        output: out_name,
        output_shape: output.to_vec(),
        declared_inputs: spec.inputs.clone(),
        declared_outputs: spec.outputs.clone(),
    })
}

fn check_sha256(path: &Path, want: &str, kind: ModelKind) -> Result<()> {
    let bytes = std::fs::read(path).map_err(|e| Error::Bundle(format!("cannot read {}: {e}", path.display())))?;
    let got = hex::encode(Sha256::digest(&bytes));
    if !got.eq_ignore_ascii_case(want) {
        return Err(Error::Bundle(format!(
            "models.{}.sha256: {} hashes to {got}, the manifest says {want}",
            kind.key(),
            path.display()
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(file: &str, inputs: &[(&str, Vec<i64>)], outputs: &[(&str, Vec<i64>)]) -> ModelSpec {
        ModelSpec {
            file: file.into(),
            sha256: String::new(),
            inputs: inputs.iter().map(|(n, s)| (n.to_string(), s.clone())).collect(),
            outputs: outputs.iter().map(|(n, s)| (n.to_string(), s.clone())).collect(),
        }
    }

    fn manifest() -> Manifest {
        let cfg = PipelineConfig::with_image_size(64);
        let n = cfg.num_points as i64;
        let k = K as i64;
        Manifest {
            format_version: 1,
            name: "t".into(),
            version: "0".into(),
            keypoints: ManifestKeypoints {
                names: NAMES.iter().map(|s| s.to_string()).collect(),
                waymo_types: WAYMO_TYPES.to_vec(),
            },
            preprocessing: cfg,
            models: ManifestModels {
                camera: spec("c.onnx", &[("image", vec![-1, 3, 64, 64])], &[("heatmaps", vec![-1, k, 16, 16])]),
                point_fusion: spec(
                    "f.onnx",
                    &[("points", vec![-1, n, 3 + k])],
                    &[("keypoints", vec![-1, k, 3]), ("segmentation", vec![-1, n, k])],
                ),
                point_lidar: spec(
                    "l.onnx",
                    &[("points", vec![-1, n, 3])],
                    &[("keypoints", vec![-1, k, 3]), ("segmentation", vec![-1, n, k])],
                ),
            },
        }
    }

    fn dir_with_files() -> tempfile::TempDir {
        let d = tempfile::tempdir().unwrap();
        for f in ["c.onnx", "f.onnx", "l.onnx"] {
            std::fs::write(d.path().join(f), b"x").unwrap();
        }
        d
    }

    fn err(m: Manifest, dir: &Path) -> String {
        Bundle::from_manifest(dir, m, serde_json::Value::Null).unwrap_err().to_string()
    }

    #[test]
    fn a_consistent_manifest_resolves_the_tensor_names() {
        let d = dir_with_files();
        let b = Bundle::from_manifest(d.path(), manifest(), serde_json::Value::Null).unwrap();
        assert_eq!(b.camera.input, "image");
        assert_eq!(b.camera.output, "heatmaps");
        assert_eq!(b.camera.input_len(), 3 * 64 * 64);
        assert_eq!(b.point_fusion.output, "keypoints");
        assert_eq!(b.point_fusion.input_shape, vec![256, 16]);
        assert_eq!(b.point_lidar.output_len(), K * 3);
    }

    #[test]
    fn inconsistent_manifests_are_refused_with_the_field() {
        let d = dir_with_files();
        let mut m = manifest();
        m.models.camera.inputs.insert("image".into(), vec![-1, 3, 128, 128]);
        assert!(err(m, d.path()).contains("models.camera.inputs.image"));
        let mut m = manifest();
        m.models.point_lidar.outputs.remove("keypoints");
        assert!(err(m, d.path()).contains("models.point_lidar.outputs: no output has shape"));
        let mut m = manifest();
        m.models.point_fusion.inputs.insert("extra".into(), vec![1]);
        assert!(err(m, d.path()).contains("exactly one input"));
        let mut m = manifest();
        m.keypoints.names.swap(1, 2);
        assert!(err(m, d.path()).contains("keypoints"));
        let mut m = manifest();
        m.format_version = 2;
        assert!(err(m, d.path()).contains("format_version"));
        let mut m = manifest();
        m.models.camera.file = "missing.onnx".into();
        assert!(err(m, d.path()).contains("models.camera.file"));
    }

    #[test]
    fn a_wrong_hash_is_refused() {
        let d = dir_with_files();
        let e = check_sha256(&d.path().join("c.onnx"), "00", ModelKind::Camera).unwrap_err().to_string();
        assert!(e.contains("models.camera.sha256") && e.contains("the manifest says 00"), "{e}");
        // sha256("x")
        let good = "2d711642b726b04401627ca9fbac32f5c8530fb1903cc4db02258717921a4881";
        check_sha256(&d.path().join("c.onnx"), good, ModelKind::Camera).unwrap();
    }
}
