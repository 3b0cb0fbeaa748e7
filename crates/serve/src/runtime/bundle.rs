//! The model bundle: `manifest.json` plus three ONNX files (and optional variants of them in
//! another precision). Loading checks everything that can be checked without ONNX Runtime (files,
//! hashes, declared shapes against the pre-processing config); `models` checks the sessions
//! against the same declarations.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use posefuse_core::error::{Error, Result};
use posefuse_core::keypoints::{K, NAMES, WAYMO_TYPES};
use posefuse_core::pipeline::PipelineConfig;

use super::precision::Precision;

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
    /// The precision served when none is asked for (absent: float32).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub precision: Option<Precision>,
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
    /// The same network in another precision (key: `int8`), with the same tensors.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub variants: BTreeMap<String, VariantSpec>,
}

/// Another file of a network (e.g. its INT8 quantization), declaring the same tensors.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct VariantSpec {
    pub file: String,
    pub sha256: String,
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
    /// The camera network's precision (its file is `camera.path`).
    pub precision: Precision,
}

impl Bundle {
    /// Reads and validates `dir/manifest.json` and the files it names, the camera network at the
    /// manifest's precision.
    pub fn load(dir: &Path) -> Result<Bundle> {
        Bundle::load_at(dir, None)
    }

    /// As [`Bundle::load`], the camera network at `precision` (None: the manifest's, else fp32).
    pub fn load_at(dir: &Path, precision: Option<Precision>) -> Result<Bundle> {
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
        let bundle = Bundle::from_manifest(dir, manifest, raw)?.at_precision(precision)?;
        for kind in ModelKind::ALL {
            check_sha256(&bundle.io(kind).path, bundle.sha256(kind), &bundle.sha256_field(kind))?;
        }
        Ok(bundle)
    }

    /// The camera network switched to `precision` (None: the manifest's): its variant's file, with
    /// the same tensors. A precision the bundle has no file for is refused, naming the way to make one.
    pub fn at_precision(mut self, precision: Option<Precision>) -> Result<Bundle> {
        let p = precision.or(self.manifest.precision).unwrap_or_default();
        if p != Precision::Fp32 {
            let v = self.manifest.models.camera.variants.get(p.key()).ok_or_else(|| {
                Error::Bundle(format!(
                    "models.camera.variants.{p}: the bundle in {} has no {p} camera network (make one with \
                     `python -m posefuse_train.quantize --bundle DIR --calibration DATA`, or serve with \
                     --precision fp32)",
                    self.dir.display()
                ))
            })?;
            let path = self.dir.join(&v.file);
            if !path.is_file() {
                return Err(Error::Bundle(format!(
                    "models.camera.variants.{p}.file: {} does not exist",
                    path.display()
                )));
            }
            self.camera.path = path;
        }
        self.precision = p;
        Ok(self)
    }

    /// Where that hash is declared in the manifest.
    fn sha256_field(&self, kind: ModelKind) -> String {
        match (kind, self.precision) {
            (ModelKind::Camera, p) if p != Precision::Fp32 => format!("models.camera.variants.{p}.sha256"),
            (k, _) => format!("models.{}.sha256", k.key()),
        }
    }

    /// The hash a model's file must have at the bundle's precision.
    fn sha256(&self, kind: ModelKind) -> &str {
        match kind {
            // `at_precision` made sure the variant exists
            ModelKind::Camera if self.precision != Precision::Fp32 => {
                let variants = &self.manifest.models.camera.variants;
                variants.get(self.precision.key()).map_or("", |v| v.sha256.as_str())
            }
            other => &self.spec(other).sha256,
        }
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
        Ok(Bundle {
            dir: dir.to_path_buf(),
            manifest,
            raw,
            camera,
            point_fusion,
            point_lidar,
            precision: Precision::Fp32,
        })
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

fn check_sha256(path: &Path, want: &str, field: &str) -> Result<()> {
    let bytes = std::fs::read(path).map_err(|e| Error::Bundle(format!("cannot read {}: {e}", path.display())))?;
    let got = hex::encode(Sha256::digest(&bytes));
    if !got.eq_ignore_ascii_case(want) {
        return Err(Error::Bundle(format!("{field}: {} hashes to {got}, the manifest says {want}", path.display())));
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
            variants: BTreeMap::new(),
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
            precision: None,
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
        let e = check_sha256(&d.path().join("c.onnx"), "00", "models.camera.sha256").unwrap_err().to_string();
        assert!(e.contains("models.camera.sha256") && e.contains("the manifest says 00"), "{e}");
        // sha256("x")
        let good = "2d711642b726b04401627ca9fbac32f5c8530fb1903cc4db02258717921a4881";
        check_sha256(&d.path().join("c.onnx"), good, "models.camera.sha256").unwrap();
    }

    /// sha256 of "x" and of "y".
    const SHA_X: &str = "2d711642b726b04401627ca9fbac32f5c8530fb1903cc4db02258717921a4881";
    const SHA_Y: &str = "a1fce4363854ff888cff4b8e7875d600c2682390412a8cf79b37d0b11148b0fa";

    /// A bundle on disk whose camera has an INT8 variant `c8.onnx` (contents "y").
    fn bundle_with_variant(precision: Option<Precision>) -> tempfile::TempDir {
        let d = dir_with_files();
        std::fs::write(d.path().join("c8.onnx"), b"y").unwrap();
        let mut m = manifest();
        for s in [&mut m.models.camera, &mut m.models.point_fusion, &mut m.models.point_lidar] {
            s.sha256 = SHA_X.into();
        }
        m.models.camera.variants.insert("int8".into(), VariantSpec { file: "c8.onnx".into(), sha256: SHA_Y.into() });
        m.precision = precision;
        std::fs::write(d.path().join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
        d
    }

    #[test]
    fn the_camera_runs_from_the_variant_of_the_asked_or_the_manifests_precision() {
        let d = bundle_with_variant(None);
        let b = Bundle::load(d.path()).unwrap();
        assert_eq!((b.precision, b.camera.path.file_name().unwrap().to_str()), (Precision::Fp32, Some("c.onnx")));
        let b = Bundle::load_at(d.path(), Some(Precision::Int8)).unwrap();
        assert_eq!((b.precision, b.camera.path.file_name().unwrap().to_str()), (Precision::Int8, Some("c8.onnx")));
        // the point networks keep their files; the variant declares the same tensors
        assert!(b.point_fusion.path.ends_with("f.onnx") && b.camera.input == "image");
        let d = bundle_with_variant(Some(Precision::Int8));
        assert_eq!(Bundle::load(d.path()).unwrap().precision, Precision::Int8);
        let b = Bundle::load_at(d.path(), Some(Precision::Fp32)).unwrap();
        assert!(b.camera.path.ends_with("c.onnx"));
    }

    #[test]
    fn a_missing_or_altered_variant_is_refused_with_its_field() {
        let d = dir_with_files();
        let mut m = manifest();
        for s in [&mut m.models.camera, &mut m.models.point_fusion, &mut m.models.point_lidar] {
            s.sha256 = SHA_X.into();
        }
        std::fs::write(d.path().join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
        let e = Bundle::load_at(d.path(), Some(Precision::Int8)).unwrap_err().to_string();
        assert!(e.contains("models.camera.variants.int8") && e.contains("posefuse_train.quantize"), "{e}");
        let d = bundle_with_variant(None);
        std::fs::write(d.path().join("c8.onnx"), b"z").unwrap();
        let e = Bundle::load_at(d.path(), Some(Precision::Int8)).unwrap_err().to_string();
        assert!(e.contains("models.camera.variants.int8.sha256"), "{e}");
        assert!(Bundle::load(d.path()).is_ok(), "fp32 does not read the variant");
        std::fs::write(d.path().join("c.onnx"), b"z").unwrap();
        let e = Bundle::load(d.path()).unwrap_err().to_string();
        assert!(e.starts_with("models.camera.sha256") || e.contains(": models.camera.sha256:"), "{e}");
        std::fs::write(d.path().join("c.onnx"), b"x").unwrap();
        std::fs::remove_file(d.path().join("c8.onnx")).unwrap();
        let e = Bundle::load_at(d.path(), Some(Precision::Int8)).unwrap_err().to_string();
        assert!(e.contains("models.camera.variants.int8.file"), "{e}");
    }
}
