//! ONNX Runtime sessions of one bundle, checked against the manifest. `Session::run` needs
//! `&mut self`, so each worker thread owns one `Models`.

use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::{TensorRef, ValueType};

use super::bundle::{Bundle, ModelIo, ModelKind};
use super::device::Device;
use posefuse_core::error::{Error, Result};

/// One session per network, with the I/O resolved from the manifest.
pub struct Models {
    camera: Loaded,
    point_fusion: Loaded,
    point_lidar: Loaded,
}

struct Loaded {
    session: Session,
    io: ModelIo,
    kind: ModelKind,
}

/// Builder errors carry the (non-`Send`) builder; keep them inside this function.
fn build_session(
    env: &ort::environment::Environment,
    io: &ModelIo,
    intra_threads: usize,
    device: Device,
) -> ort::Result<Session> {
    Session::builder(env)?
        .with_execution_providers(device.providers())?
        .with_optimization_level(GraphOptimizationLevel::Level3)?
        .with_intra_threads(intra_threads)?
        .with_inter_threads(1)?
        .commit_from_file(&io.path)
}

impl Models {
    /// Builds the three sessions on `device` and checks their tensors against the manifest.
    pub fn load(
        env: &ort::environment::Environment,
        bundle: &Bundle,
        intra_threads: usize,
        device: Device,
    ) -> Result<Models> {
        let load = |kind: ModelKind| -> Result<Loaded> {
            let io = bundle.io(kind).clone();
            let session = build_session(env, &io, intra_threads.max(1), device).map_err(|e| {
                let what = format!("models.{}: {} does not load", kind.key(), io.path.display());
                match device {
                    Device::Cpu => Error::Bundle(format!("{what}: {e}")),
                    // Mostly the device, not the model: CUDA's libraries, the driver, the GPU.
                    Device::Cuda(_) => Error::Runtime(format!(
                        "{what} on {device}: {e} (the CUDA execution provider needs a GPU, its driver, and \
                         CUDA 13 with cuDNN 9: `bash scripts/setup.sh --gpu` installs the libraries)"
                    )),
                }
            })?;
            check_session(&session, &io, kind)?;
            Ok(Loaded { session, io, kind })
        };
        Ok(Models {
            camera: load(ModelKind::Camera)?,
            point_fusion: load(ModelKind::PointFusion)?,
            point_lidar: load(ModelKind::PointLidar)?,
        })
    }

    /// The I/O of one network.
    pub fn io(&self, kind: ModelKind) -> &ModelIo {
        &self.get(kind).io
    }

    fn get(&self, kind: ModelKind) -> &Loaded {
        match kind {
            ModelKind::Camera => &self.camera,
            ModelKind::PointFusion => &self.point_fusion,
            ModelKind::PointLidar => &self.point_lidar,
        }
    }

    fn get_mut(&mut self, kind: ModelKind) -> &mut Loaded {
        match kind {
            ModelKind::Camera => &mut self.camera,
            ModelKind::PointFusion => &mut self.point_fusion,
            ModelKind::PointLidar => &mut self.point_lidar,
        }
    }

    /// Runs `batch` items stacked in `input` (each `io.input_len()` floats) and returns the
    /// stacked outputs (each `io.output_len()` floats).
    pub fn run(&mut self, kind: ModelKind, batch: usize, input: &[f32]) -> Result<Vec<f32>> {
        self.get_mut(kind).run(batch, input)
    }
}

impl Loaded {
    fn run(&mut self, batch: usize, input: &[f32]) -> Result<Vec<f32>> {
        let key = self.kind.key();
        if batch == 0 || input.len() != batch * self.io.input_len() {
            return Err(Error::Runtime(format!(
                "{key}: {} input floats for a batch of {batch} (expected {} each)",
                input.len(),
                self.io.input_len()
            )));
        }
        let mut shape = vec![batch];
        shape.extend_from_slice(&self.io.input_shape);
        let tensor = TensorRef::from_array_view((shape, input)).map_err(|e| Error::Runtime(format!("{key}: {e}")))?;
        let outputs = self
            .session
            .run(ort::inputs![self.io.input.as_str() => tensor])
            .map_err(|e| Error::Runtime(format!("{key}: inference failed: {e}")))?;
        let value = outputs
            .get(&self.io.output)
            .ok_or_else(|| Error::Runtime(format!("{key}: output `{}` missing", self.io.output)))?;
        let (out_shape, data) =
            value.try_extract_tensor::<f32>().map_err(|e| Error::Runtime(format!("{key}: output: {e}")))?;
        let mut want = vec![batch as i64];
        want.extend(self.io.output_shape.iter().map(|&d| d as i64));
        if out_shape[..] != want[..] {
            return Err(Error::Runtime(format!("{key}: output shape {out_shape:?}, expected {want:?}")));
        }
        Ok(data.to_vec())
    }
}

/// Dimension from the session: negative means dynamic (ONNX Runtime reports -1).
fn dims_agree(session: &[i64], declared: &[i64]) -> bool {
    session.len() == declared.len()
        && session.iter().zip(declared).all(|(&s, &d)| if d < 0 { s < 0 } else { s == d || s < 0 })
}

fn check_side(
    kind: ModelKind,
    side: &str,
    outlets: &[ort::value::Outlet],
    declared: &std::collections::BTreeMap<String, Vec<i64>>,
) -> Result<()> {
    let key = kind.key();
    let names: Vec<&str> = outlets.iter().map(|o| o.name()).collect();
    for (name, shape) in declared {
        let Some(outlet) = outlets.iter().find(|o| o.name() == name) else {
            return Err(Error::Bundle(format!(
                "models.{key}.{side}.{name}: the ONNX file has no such tensor (it has {names:?})"
            )));
        };
        match outlet.dtype() {
            ValueType::Tensor { ty, shape: got, .. } => {
                if *ty != ort::value::TensorElementType::Float32 {
                    return Err(Error::Bundle(format!(
                        "models.{key}.{side}.{name}: element type {ty:?}, expected float32"
                    )));
                }
                if !dims_agree(got, shape) {
                    return Err(Error::Bundle(format!(
                        "models.{key}.{side}.{name}: the ONNX file says shape {:?}, the manifest says {shape:?}",
                        &got[..]
                    )));
                }
            }
            other => {
                return Err(Error::Bundle(format!("models.{key}.{side}.{name}: not a tensor ({other:?})")));
            }
        }
    }
    if side == "inputs" {
        if let Some(extra) = names.iter().find(|n| !declared.contains_key(**n)) {
            return Err(Error::Bundle(format!(
                "models.{key}.inputs: the ONNX file has input `{extra}` that the manifest does not declare"
            )));
        }
    }
    Ok(())
}

fn check_session(session: &Session, io: &ModelIo, kind: ModelKind) -> Result<()> {
    check_side(kind, "inputs", session.inputs(), &io.declared_inputs)?;
    check_side(kind, "outputs", session.outputs(), &io.declared_outputs)
}

#[cfg(test)]
mod tests {
    use super::dims_agree;

    #[test]
    fn dynamic_axes_must_stay_dynamic_and_fixed_ones_must_match() {
        assert!(dims_agree(&[-1, 3, 64, 64], &[-1, 3, 64, 64]));
        assert!(!dims_agree(&[1, 3, 64, 64], &[-1, 3, 64, 64]));
        assert!(!dims_agree(&[-1, 3, 32, 32], &[-1, 3, 64, 64]));
        assert!(!dims_agree(&[-1, 3, 64], &[-1, 3, 64, 64]));
        // An exporter may leave a fixed axis symbolic; it still accepts the declared size.
        assert!(dims_agree(&[-1, 13, -1], &[-1, 13, 3]));
    }
}
