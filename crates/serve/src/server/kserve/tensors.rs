//! The tensor contract of the Open Inference Protocol endpoints (docs/KSERVE.md): datatypes,
//! tensor data in the protocol's encodings (JSON arrays, raw little-endian bytes, gRPC typed
//! contents), the declared inputs and outputs, and the conversions inputs → [`Frame`] and
//! [`PoseResponse`] → outputs. Pure code: the transports only move bytes in and out.

use base64::Engine;

use super::shared_memory::ShmRef;
use crate::service::api::PoseResponse;
use posefuse_core::error::{Error, Result};
use posefuse_core::frame::{Box2d, Box3d, CameraCalibration, Frame, Person, Points, RequestedMode, RgbPixels};
use posefuse_core::keypoints::K;

/// A tensor element type, by its protocol name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DataType {
    Bool,
    U8,
    U16,
    U32,
    U64,
    I8,
    I16,
    I32,
    I64,
    F16,
    Bf16,
    F32,
    F64,
    Bytes,
}

impl DataType {
    /// The protocol's name (`FP32`, `BYTES`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            DataType::Bool => "BOOL",
            DataType::U8 => "UINT8",
            DataType::U16 => "UINT16",
            DataType::U32 => "UINT32",
            DataType::U64 => "UINT64",
            DataType::I8 => "INT8",
            DataType::I16 => "INT16",
            DataType::I32 => "INT32",
            DataType::I64 => "INT64",
            DataType::F16 => "FP16",
            DataType::Bf16 => "BF16",
            DataType::F32 => "FP32",
            DataType::F64 => "FP64",
            DataType::Bytes => "BYTES",
        }
    }

    /// Parses a protocol name; `tensor` names the tensor in the error.
    pub fn parse(tensor: &str, s: &str) -> Result<DataType> {
        Ok(match s {
            "BOOL" => DataType::Bool,
            "UINT8" => DataType::U8,
            "UINT16" => DataType::U16,
            "UINT32" => DataType::U32,
            "UINT64" => DataType::U64,
            "INT8" => DataType::I8,
            "INT16" => DataType::I16,
            "INT32" => DataType::I32,
            "INT64" => DataType::I64,
            "FP16" => DataType::F16,
            "BF16" => DataType::Bf16,
            "FP32" => DataType::F32,
            "FP64" => DataType::F64,
            "BYTES" => DataType::Bytes,
            other => return Err(Error::field(tensor, format!("unknown datatype `{other}`"))),
        })
    }

    /// Bytes per element in raw form (`None` for BYTES, whose elements are length-prefixed).
    fn size(self) -> Option<usize> {
        match self {
            DataType::Bool | DataType::U8 | DataType::I8 => Some(1),
            DataType::U16 | DataType::I16 | DataType::F16 | DataType::Bf16 => Some(2),
            DataType::U32 | DataType::I32 | DataType::F32 => Some(4),
            DataType::U64 | DataType::I64 | DataType::F64 => Some(8),
            DataType::Bytes => None,
        }
    }

    fn is_signed(self) -> bool {
        matches!(self, DataType::I8 | DataType::I16 | DataType::I32 | DataType::I64)
    }

    fn is_unsigned(self) -> bool {
        matches!(self, DataType::U8 | DataType::U16 | DataType::U32 | DataType::U64)
    }
}

/// Tensor elements, flattened in row-major order (integers widened to 64 bits).
#[derive(Debug, Clone, PartialEq)]
pub enum TensorData {
    Bool(Vec<bool>),
    Int(Vec<i64>),
    UInt(Vec<u64>),
    /// UINT8 elements as they are (camera pixels: not widened).
    U8(Vec<u8>),
    F32(Vec<f32>),
    F64(Vec<f64>),
    Bytes(Vec<Vec<u8>>),
}

impl TensorData {
    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            TensorData::Bool(v) => v.len(),
            TensorData::Int(v) => v.len(),
            TensorData::UInt(v) => v.len(),
            TensorData::U8(v) => v.len(),
            TensorData::F32(v) => v.len(),
            TensorData::F64(v) => v.len(),
            TensorData::Bytes(v) => v.len(),
        }
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Raw little-endian bytes; BYTES elements each prefixed by a 4-byte little-endian length.
    /// Integers are written at the width of `dt`.
    pub fn to_raw(&self, dt: DataType) -> Vec<u8> {
        let mut out = Vec::new();
        match self {
            TensorData::Bool(v) => out.extend(v.iter().map(|b| u8::from(*b))),
            TensorData::Int(v) => {
                for x in v {
                    match dt {
                        DataType::I8 => out.extend((*x as i8).to_le_bytes()),
                        DataType::I16 => out.extend((*x as i16).to_le_bytes()),
                        DataType::I32 => out.extend((*x as i32).to_le_bytes()),
                        _ => out.extend(x.to_le_bytes()),
                    }
                }
            }
            TensorData::UInt(v) => {
                for x in v {
                    match dt {
                        DataType::U8 => out.push(*x as u8),
                        DataType::U16 => out.extend((*x as u16).to_le_bytes()),
                        DataType::U32 => out.extend((*x as u32).to_le_bytes()),
                        _ => out.extend(x.to_le_bytes()),
                    }
                }
            }
            TensorData::U8(v) => out.extend_from_slice(v),
            TensorData::F32(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            TensorData::F64(v) => out.extend(v.iter().flat_map(|x| x.to_le_bytes())),
            TensorData::Bytes(v) => {
                for b in v {
                    out.extend((b.len() as u32).to_le_bytes());
                    out.extend_from_slice(b);
                }
            }
        }
        out
    }

    /// The elements as a flat JSON array: non-finite numbers become `null` (JSON has no NaN);
    /// BYTES elements become strings.
    pub fn to_json(&self) -> serde_json::Value {
        use serde_json::Value;
        let num = |x: f64| serde_json::Number::from_f64(x).map_or(Value::Null, Value::Number);
        Value::Array(match self {
            TensorData::Bool(v) => v.iter().map(|b| Value::Bool(*b)).collect(),
            TensorData::Int(v) => v.iter().map(|x| Value::from(*x)).collect(),
            TensorData::UInt(v) => v.iter().map(|x| Value::from(*x)).collect(),
            TensorData::U8(v) => v.iter().map(|x| Value::from(*x)).collect(),
            TensorData::F32(v) => v.iter().map(|x| num(f64::from(*x))).collect(),
            TensorData::F64(v) => v.iter().map(|x| num(*x)).collect(),
            TensorData::Bytes(v) => v.iter().map(|b| Value::String(String::from_utf8_lossy(b).into_owned())).collect(),
        })
    }

    /// Decodes raw bytes of `dt` elements (the binary extension, gRPC `raw_input_contents`).
    pub fn from_raw(tensor: &str, dt: DataType, raw: &[u8]) -> Result<TensorData> {
        if dt == DataType::Bytes {
            let mut items = Vec::new();
            let mut rest = raw;
            while !rest.is_empty() {
                if rest.len() < 4 {
                    return Err(Error::field(tensor, "BYTES data ends inside an element's 4-byte length prefix"));
                }
                let n = u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize;
                if rest.len() - 4 < n {
                    return Err(Error::field(
                        tensor,
                        format!("BYTES element {} declares {n} bytes but {} remain", items.len(), rest.len() - 4),
                    ));
                }
                items.push(rest[4..4 + n].to_vec());
                rest = &rest[4 + n..];
            }
            return Ok(TensorData::Bytes(items));
        }
        let size = dt.size().unwrap_or(1);
        if !raw.len().is_multiple_of(size) {
            return Err(Error::field(
                tensor,
                format!("{} bytes of raw data is not a whole number of {} elements", raw.len(), dt.as_str()),
            ));
        }
        let chunks = raw.chunks_exact(size);
        let le8 = |c: &[u8]| [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
        Ok(match dt {
            DataType::Bool => TensorData::Bool(raw.iter().map(|b| *b != 0).collect()),
            DataType::I8 => TensorData::Int(raw.iter().map(|b| i64::from(*b as i8)).collect()),
            DataType::I16 => TensorData::Int(chunks.map(|c| i64::from(i16::from_le_bytes([c[0], c[1]]))).collect()),
            DataType::I32 => {
                TensorData::Int(chunks.map(|c| i64::from(i32::from_le_bytes([c[0], c[1], c[2], c[3]]))).collect())
            }
            DataType::I64 => TensorData::Int(chunks.map(|c| i64::from_le_bytes(le8(c))).collect()),
            DataType::U8 => TensorData::U8(raw.to_vec()),
            DataType::U16 => TensorData::UInt(chunks.map(|c| u64::from(u16::from_le_bytes([c[0], c[1]]))).collect()),
            DataType::U32 => {
                TensorData::UInt(chunks.map(|c| u64::from(u32::from_le_bytes([c[0], c[1], c[2], c[3]]))).collect())
            }
            DataType::U64 => TensorData::UInt(chunks.map(|c| u64::from_le_bytes(le8(c))).collect()),
            DataType::F32 => TensorData::F32(chunks.map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()),
            DataType::F64 => TensorData::F64(chunks.map(|c| f64::from_le_bytes(le8(c))).collect()),
            DataType::F16 | DataType::Bf16 | DataType::Bytes => return Err(unsupported(tensor, dt)),
        })
    }

    /// Decodes a JSON `data` value: a flat or nested array of `dt` elements (numbers, booleans,
    /// or strings for BYTES; `null` reads as NaN in floating-point tensors).
    pub fn from_json(tensor: &str, dt: DataType, data: &serde_json::Value) -> Result<TensorData> {
        let mut leaves = Vec::new();
        flatten(data, &mut leaves);
        let bad = |i: usize, what: &str| Error::field(tensor, format!("element {i} is not {what}"));
        Ok(match dt {
            DataType::Bool => TensorData::Bool(
                leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v.as_bool().ok_or_else(|| bad(i, "a boolean")))
                    .collect::<Result<_>>()?,
            ),
            dt if dt.is_signed() => TensorData::Int(
                leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v.as_i64().ok_or_else(|| bad(i, "an integer")))
                    .collect::<Result<_>>()?,
            ),
            DataType::U8 => TensorData::U8(
                leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| {
                        v.as_u64().and_then(|x| u8::try_from(x).ok()).ok_or_else(|| bad(i, "an integer 0..=255"))
                    })
                    .collect::<Result<_>>()?,
            ),
            dt if dt.is_unsigned() => TensorData::UInt(
                leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v.as_u64().ok_or_else(|| bad(i, "a non-negative integer")))
                    .collect::<Result<_>>()?,
            ),
            DataType::F32 | DataType::F64 => {
                let vals: Vec<f64> = leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| match v {
                        serde_json::Value::Null => Ok(f64::NAN),
                        // `NaN`, `Infinity`, `-Infinity` as Python's json writes them (`non_finite`)
                        serde_json::Value::String(s) => {
                            super::non_finite::value_of(s).ok_or_else(|| bad(i, "a number"))
                        }
                        _ => v.as_f64().ok_or_else(|| bad(i, "a number")),
                    })
                    .collect::<Result<_>>()?;
                if dt == DataType::F32 {
                    TensorData::F32(vals.into_iter().map(|x| x as f32).collect())
                } else {
                    TensorData::F64(vals)
                }
            }
            DataType::Bytes => TensorData::Bytes(
                leaves
                    .iter()
                    .enumerate()
                    .map(|(i, v)| v.as_str().map(|s| s.as_bytes().to_vec()).ok_or_else(|| bad(i, "a string")))
                    .collect::<Result<_>>()?,
            ),
            _ => return Err(unsupported(tensor, dt)),
        })
    }
}

fn flatten<'a>(v: &'a serde_json::Value, out: &mut Vec<&'a serde_json::Value>) {
    match v {
        serde_json::Value::Array(items) => items.iter().for_each(|x| flatten(x, out)),
        leaf => out.push(leaf),
    }
}

fn unsupported(tensor: &str, dt: DataType) -> Error {
    Error::field(tensor, format!("datatype {} is not supported by this model", dt.as_str()))
}

/// One input tensor as received, its element count checked against its shape.
#[derive(Debug, Clone, PartialEq)]
pub struct InputTensor {
    pub name: String,
    pub datatype: DataType,
    pub shape: Vec<i64>,
    pub data: TensorData,
    /// BYTES elements arrived as JSON strings (then the `image` element is base64 text).
    pub text: bool,
}

impl InputTensor {
    /// Checks that the shape has no negative dimension and holds as many elements as `data`.
    pub fn new(name: String, datatype: DataType, shape: Vec<i64>, data: TensorData, text: bool) -> Result<Self> {
        let count = element_count(&name, &shape)?;
        if count != data.len() {
            return Err(Error::field(
                name.as_str(),
                format!("shape {shape:?} holds {count} elements but the data has {}", data.len()),
            ));
        }
        Ok(InputTensor { name, datatype, shape, data, text })
    }
}

/// Elements a shape holds; a negative dimension is an error naming the tensor.
pub fn element_count(tensor: &str, shape: &[i64]) -> Result<usize> {
    let mut n: usize = 1;
    for d in shape {
        let d = usize::try_from(*d)
            .map_err(|_| Error::field(tensor, format!("shape {shape:?} has a negative dimension")))?;
        n = n.checked_mul(d).ok_or_else(|| Error::field(tensor, format!("shape {shape:?} is too large")))?;
    }
    Ok(n)
}

/// A declared tensor: name, datatype and shape (`-1`: any size), for model metadata.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorSpec {
    pub name: &'static str,
    pub datatype: DataType,
    pub shape: &'static [i64],
}

const fn spec(name: &'static str, datatype: DataType, shape: &'static [i64]) -> TensorSpec {
    TensorSpec { name, datatype, shape }
}

/// The model's inputs (docs/KSERVE.md; `points`, the calibration, `image_size` and `boxes_3d` are
/// required).
pub const INPUTS: [TensorSpec; 10] = [
    spec("image", DataType::Bytes, &[1]),
    spec("image_rgb", DataType::U8, &[-1, -1, 3]),
    spec("points", DataType::F32, &[-1, 3]),
    spec("calibration_intrinsic", DataType::F64, &[9]),
    spec("calibration_extrinsic", DataType::F64, &[16]),
    spec("image_size", DataType::I32, &[2]),
    spec("boxes_3d", DataType::F64, &[-1, 7]),
    spec("boxes_2d", DataType::F64, &[-1, 4]),
    spec("person_ids", DataType::Bytes, &[-1]),
    spec("mode", DataType::Bytes, &[1]),
];

/// The inputs a request must carry.
pub const REQUIRED_INPUTS: [&str; 5] =
    ["points", "calibration_intrinsic", "calibration_extrinsic", "image_size", "boxes_3d"];

/// The model's outputs, in the order they are returned (docs/KSERVE.md).
pub const OUTPUTS: [TensorSpec; 6] = [
    spec("keypoints_3d", DataType::F32, &[-1, K as i64, 3]),
    spec("keypoints_2d", DataType::F32, &[-1, K as i64, 2]),
    spec("scores", DataType::F32, &[-1, K as i64]),
    spec("mode", DataType::Bytes, &[-1]),
    spec("status", DataType::Bytes, &[-1]),
    spec("num_points", DataType::I32, &[-1]),
];

/// `mode` of a person that got no pose.
pub const MODE_NONE: &str = "none";
/// `status` of a person that got a pose.
pub const STATUS_OK: &str = "ok";

fn names(specs: &[TensorSpec]) -> String {
    specs.iter().map(|s| s.name).collect::<Vec<_>>().join(", ")
}

/// Checks a shape against the accepted ones (`-1`: any size).
fn check_shape(t: &InputTensor, accepted: &[&[i64]]) -> Result<()> {
    let fits = |want: &[i64]| want.len() == t.shape.len() && want.iter().zip(&t.shape).all(|(w, s)| *w == -1 || w == s);
    if accepted.iter().any(|a| fits(a)) {
        return Ok(());
    }
    let want: Vec<String> = accepted
        .iter()
        .map(|a| {
            format!(
                "[{}]",
                a.iter().map(|d| if *d < 0 { "N".into() } else { d.to_string() }).collect::<Vec<_>>().join(", ")
            )
        })
        .collect();
    Err(Error::field(t.name.as_str(), format!("shape {:?}, expected {}", t.shape, want.join(" or "))))
}

fn floats(t: &InputTensor) -> Result<Vec<f64>> {
    match &t.data {
        TensorData::F32(v) => Ok(v.iter().map(|x| f64::from(*x)).collect()),
        TensorData::F64(v) => Ok(v.clone()),
        _ => Err(Error::field(t.name.as_str(), format!("datatype {}, expected FP32 or FP64", t.datatype.as_str()))),
    }
}

fn integers(t: &InputTensor) -> Result<Vec<i128>> {
    match &t.data {
        TensorData::Int(v) => Ok(v.iter().map(|x| i128::from(*x)).collect()),
        TensorData::UInt(v) => Ok(v.iter().map(|x| i128::from(*x)).collect()),
        TensorData::U8(v) => Ok(v.iter().map(|x| i128::from(*x)).collect()),
        _ => Err(Error::field(
            t.name.as_str(),
            format!("datatype {}, expected an integer type (INT32, INT64, UINT32, ...)", t.datatype.as_str()),
        )),
    }
}

fn byte_items(t: &InputTensor) -> Result<&[Vec<u8>]> {
    match &t.data {
        TensorData::Bytes(v) => Ok(v),
        _ => Err(Error::field(t.name.as_str(), format!("datatype {}, expected BYTES", t.datatype.as_str()))),
    }
}

fn text_items(t: &InputTensor) -> Result<Vec<String>> {
    byte_items(t)?
        .iter()
        .enumerate()
        .map(|(i, b)| {
            String::from_utf8(b.clone()).map_err(|_| Error::field(format!("{}[{i}]", t.name), "is not UTF-8 text"))
        })
        .collect()
}

/// `image_rgb` ([H, W, 3] UINT8) as the frame's pixels, moved rather than copied when they
/// arrived as raw bytes. Their size is checked against `image_size` with the frame.
fn rgb_pixels(t: InputTensor) -> Result<RgbPixels> {
    check_shape(&t, &[&[-1, -1, 3]])?;
    let dim =
        |d: i64| u32::try_from(d).map_err(|_| Error::field("image_rgb", format!("shape {:?} is too large", t.shape)));
    let (height, width) = (dim(t.shape[0])?, dim(t.shape[1])?);
    let pixels = match t.data {
        TensorData::U8(v) => v,
        TensorData::UInt(v) => v
            .into_iter()
            .map(|x| u8::try_from(x).map_err(|_| Error::field("image_rgb", format!("element {x} is not 0..=255"))))
            .collect::<Result<_>>()?,
        _ => return Err(Error::field("image_rgb", format!("datatype {}, expected UINT8", t.datatype.as_str()))),
    };
    Ok(RgbPixels { width, height, pixels })
}

/// The request's tensors as a frame plus the raw image bytes (for `Predictor::predict`). The
/// request `id` becomes the frame id. Errors name the tensor.
pub fn frame_from_inputs(inputs: Vec<InputTensor>, frame_id: Option<String>) -> Result<(Frame, Option<Vec<u8>>)> {
    let mut slots: [Option<InputTensor>; INPUTS.len()] = Default::default();
    for t in inputs {
        let Some(k) = INPUTS.iter().position(|s| s.name == t.name) else {
            return Err(Error::field(t.name.as_str(), format!("unknown input; the inputs are: {}", names(&INPUTS))));
        };
        if slots[k].is_some() {
            return Err(Error::field(t.name.as_str(), "given twice"));
        }
        slots[k] = Some(t);
    }
    for name in REQUIRED_INPUTS {
        if let Some(k) = INPUTS.iter().position(|s| s.name == name) {
            if slots[k].is_none() {
                return Err(Error::field(name, "required input is missing"));
            }
        }
    }
    let [image, image_rgb, points, intrinsic, extrinsic, size, boxes_3d, boxes_2d, ids, mode] = slots;
    let missing = |name: &str| Error::field(name, "required input is missing");

    let image = match image {
        None => None,
        Some(t) => {
            check_shape(&t, &[&[1]])?;
            let bytes = byte_items(&t)?[0].clone();
            if t.text {
                // JSON strings carry text, so the image travels as base64 there.
                let decoded = base64::engine::general_purpose::STANDARD
                    .decode(&bytes)
                    .map_err(|e| Error::field("image", format!("a JSON image element must be base64 text: {e}")))?;
                Some(decoded)
            } else {
                Some(bytes)
            }
        }
    };

    let image_rgb = match image_rgb {
        None => None,
        Some(t) if image.is_some() => {
            return Err(Error::field(
                t.name.as_str(),
                "send either `image` (file bytes) or `image_rgb` (pixels), not both",
            ))
        }
        Some(t) => Some(rgb_pixels(t)?),
    };

    let points = points.ok_or_else(|| missing("points"))?;
    check_shape(&points, &[&[-1, 3]])?;
    let flat: Vec<f32> = match &points.data {
        TensorData::F32(v) => v.clone(),
        _ => floats(&points)?.into_iter().map(|x| x as f32).collect(),
    };

    let intrinsic = intrinsic.ok_or_else(|| missing("calibration_intrinsic"))?;
    check_shape(&intrinsic, &[&[9]])?;
    let extrinsic = extrinsic.ok_or_else(|| missing("calibration_extrinsic"))?;
    check_shape(&extrinsic, &[&[16], &[4, 4]])?;
    let size = size.ok_or_else(|| missing("image_size"))?;
    check_shape(&size, &[&[2]])?;
    let wh = integers(&size)?;
    let dim = |v: i128| u32::try_from(v).ok().filter(|d| *d > 0);
    let (Some(width), Some(height)) = (dim(wh[0]), dim(wh[1])) else {
        return Err(Error::field(
            "image_size",
            format!("[width, height] must be positive, got [{}, {}]", wh[0], wh[1]),
        ));
    };
    if let Some(px) = &image_rgb {
        if (px.width, px.height) != (width, height) {
            return Err(Error::field(
                "image_rgb",
                format!("shape [{}, {}, 3] but image_size is [{width}, {height}]", px.height, px.width),
            ));
        }
    }
    let calibration =
        CameraCalibration { intrinsic: floats(&intrinsic)?, extrinsic: floats(&extrinsic)?, width, height };

    let boxes_3d = boxes_3d.ok_or_else(|| missing("boxes_3d"))?;
    check_shape(&boxes_3d, &[&[-1, 7]])?;
    let b3 = floats(&boxes_3d)?;
    let m = b3.len() / 7;
    if m == 0 {
        return Err(Error::field("boxes_3d", "at least one person (one row) is required"));
    }
    let b2: Option<Vec<f64>> = match boxes_2d {
        None => None,
        Some(t) => {
            check_shape(&t, &[&[-1, 4]])?;
            if t.shape[0] as usize != m {
                return Err(Error::field(
                    "boxes_2d",
                    format!("{} rows but boxes_3d has {m}: one row per person (NaN row: none)", t.shape[0]),
                ));
            }
            Some(floats(&t)?)
        }
    };
    let ids: Vec<String> = match ids {
        None => (0..m).map(|i| i.to_string()).collect(),
        Some(t) => {
            check_shape(&t, &[&[-1]])?;
            if t.shape[0] as usize != m {
                return Err(Error::field("person_ids", format!("{} ids but boxes_3d has {m} rows", t.shape[0])));
            }
            text_items(&t)?
        }
    };
    let mode = match mode {
        None => RequestedMode::Auto,
        Some(t) => {
            check_shape(&t, &[&[1]])?;
            match text_items(&t)?[0].as_str() {
                "auto" => RequestedMode::Auto,
                "fusion" => RequestedMode::Fusion,
                "lidar" => RequestedMode::Lidar,
                "camera" => RequestedMode::Camera,
                other => {
                    return Err(Error::field("mode", format!("`{other}`; expected auto, fusion, lidar or camera")))
                }
            }
        }
    };

    let mut persons = Vec::with_capacity(m);
    for (i, (r, id)) in b3.chunks_exact(7).zip(ids).enumerate() {
        let box_2d = match &b2 {
            None => None,
            Some(b2) => {
                let q = &b2[i * 4..i * 4 + 4];
                if q.iter().all(|v| v.is_nan()) {
                    None
                } else if q.iter().any(|v| v.is_nan()) {
                    return Err(Error::field(
                        format!("boxes_2d[{i}]"),
                        "either four numbers or four NaN (no 2D box), not a mix",
                    ));
                } else {
                    Some(Box2d { center_x: q[0], center_y: q[1], width: q[2], height: q[3] })
                }
            }
        };
        let box_3d = Box3d {
            center_x: r[0],
            center_y: r[1],
            center_z: r[2],
            length: r[3],
            width: r[4],
            height: r[5],
            heading: r[6],
        };
        persons.push(Person { id, camera: None, box_2d, box_3d, ground_truth: None });
    }
    let frame = Frame {
        frame_id,
        image: None,
        image_rgb,
        calibration: Some(calibration),
        cameras: Vec::new(),
        points: Points::Flat(flat),
        persons,
        mode,
    };
    // Checked here so that errors name the tensor rather than the frame's field.
    frame.validate().map_err(rename_error)?;
    Ok((frame, image))
}

/// The tensor that a frame field comes from (`persons[2].box_3d.height` → `boxes_3d[2].height`).
pub fn tensor_field(field: &str) -> String {
    const PREFIXES: [(&str, &str); 5] = [
        ("calibration.intrinsic", "calibration_intrinsic"),
        ("calibration.extrinsic", "calibration_extrinsic"),
        ("calibration.width/height", "image_size"),
        ("image_rgb.width/height", "image_rgb"),
        ("image_rgb.b64", "image_rgb"),
    ];
    for (from, to) in PREFIXES {
        if let Some(rest) = field.strip_prefix(from) {
            return format!("{to}{rest}");
        }
    }
    if field == "persons" {
        return "boxes_3d".into();
    }
    if let Some(rest) = field.strip_prefix("persons[") {
        if let Some((index, tail)) = rest.split_once(']') {
            for (from, to) in [(".box_3d", "boxes_3d"), (".box_2d", "boxes_2d"), (".id", "person_ids")] {
                if let Some(t) = tail.strip_prefix(from) {
                    return format!("{to}[{index}]{t}");
                }
            }
        }
    }
    field.to_string()
}

/// The error with its field renamed to the tensor it comes from.
pub fn rename_error(e: Error) -> Error {
    match e {
        Error::InvalidField { field, message } => Error::InvalidField { field: tensor_field(&field), message },
        Error::InsufficientData { field, message } => Error::InsufficientData { field: tensor_field(&field), message },
        other => other,
    }
}

/// One output tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputTensor {
    pub name: &'static str,
    pub datatype: DataType,
    pub shape: Vec<i64>,
    pub data: TensorData,
}

/// An output the client asked for, and whether it wants it in binary form (`None`: the
/// request's default) or written to a shared-memory region.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestedOutput {
    pub name: String,
    pub binary: Option<bool>,
    pub shared_memory: Option<ShmRef>,
}

impl RequestedOutput {
    /// An output asked for by name, in the form `binary` says.
    pub fn named(name: impl Into<String>, binary: Option<bool>) -> Self {
        RequestedOutput { name: name.into(), binary, shared_memory: None }
    }
}

/// Where an output's data goes in the response.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Placement {
    /// JSON `data` (REST without the binary extension).
    Json,
    /// Raw bytes after the JSON (REST) or in `raw_output_contents` (gRPC).
    Binary,
    /// Written to a shared-memory region; the response names it and the bytes written.
    SharedMemory(ShmRef),
}

impl Placement {
    fn of(binary: bool) -> Placement {
        if binary {
            Placement::Binary
        } else {
            Placement::Json
        }
    }
}

/// Checks the requested outputs exist and are asked once (before any work is done).
pub fn check_requested(requested: Option<&[RequestedOutput]>) -> Result<()> {
    let Some(req) = requested else { return Ok(()) };
    for (i, r) in req.iter().enumerate() {
        if !OUTPUTS.iter().any(|s| s.name == r.name) {
            return Err(Error::field(r.name.as_str(), format!("unknown output; the outputs are: {}", names(&OUTPUTS))));
        }
        if req[..i].iter().any(|p| p.name == r.name) {
            return Err(Error::field(r.name.as_str(), "output requested twice"));
        }
    }
    Ok(())
}

/// The outputs for a response to a request of `m` persons: one row per requested person, in
/// request order; a skipped person's row is NaN with `mode` `none` and `status` its error code.
pub fn outputs_from_response(resp: &PoseResponse, m: usize) -> Result<Vec<OutputTensor>> {
    let mut kp3 = Vec::with_capacity(m * K * 3);
    let mut kp2 = Vec::with_capacity(m * K * 2);
    let mut scores = Vec::with_capacity(m * K);
    let (mut modes, mut status, mut num_points) = (Vec::with_capacity(m), Vec::with_capacity(m), Vec::with_capacity(m));
    let mut poses = resp.persons.iter();
    for i in 0..m {
        if let Some(s) = resp.skipped.iter().find(|s| s.index == i) {
            kp3.extend([f32::NAN; K * 3]);
            kp2.extend([f32::NAN; K * 2]);
            scores.extend([f32::NAN; K]);
            modes.push(MODE_NONE.as_bytes().to_vec());
            status.push(s.error.code.as_bytes().to_vec());
            num_points.push(-1);
            continue;
        }
        let p = poses.next().ok_or_else(|| Error::Runtime(format!("no pose and no skip entry for person {i}")))?;
        if p.keypoints.len() != K {
            return Err(Error::Runtime(format!("person {i} has {} keypoints, not {K}", p.keypoints.len())));
        }
        for k in &p.keypoints {
            kp3.extend(k.xyz.map(|v| v as f32));
            kp2.extend(k.uv.map_or([f32::NAN; 2], |uv| uv.map(|v| v as f32)));
            scores.push(k.score.unwrap_or(f32::NAN));
        }
        modes.push(p.mode.as_str().as_bytes().to_vec());
        status.push(STATUS_OK.as_bytes().to_vec());
        num_points.push(i64::try_from(p.num_points).unwrap_or(i64::MAX).min(i64::from(i32::MAX)));
    }
    if poses.next().is_some() {
        return Err(Error::Runtime(format!("more poses than the {m} requested persons")));
    }
    let (m, k) = (m as i64, K as i64);
    let out = |i: usize, shape: Vec<i64>, data: TensorData| OutputTensor {
        name: OUTPUTS[i].name,
        datatype: OUTPUTS[i].datatype,
        shape,
        data,
    };
    Ok(vec![
        out(0, vec![m, k, 3], TensorData::F32(kp3)),
        out(1, vec![m, k, 2], TensorData::F32(kp2)),
        out(2, vec![m, k], TensorData::F32(scores)),
        out(3, vec![m], TensorData::Bytes(modes)),
        out(4, vec![m], TensorData::Bytes(status)),
        out(5, vec![m], TensorData::Int(num_points)),
    ])
}

/// The outputs the client asked for (all, in declared order, when it named none), each with
/// where it goes.
pub fn select_outputs(
    all: Vec<OutputTensor>,
    requested: Option<&[RequestedOutput]>,
    binary_default: bool,
) -> Result<Vec<(OutputTensor, Placement)>> {
    let Some(req) = requested.filter(|r| !r.is_empty()) else {
        return Ok(all.into_iter().map(|t| (t, Placement::of(binary_default))).collect());
    };
    check_requested(Some(req))?;
    let mut all: Vec<Option<OutputTensor>> = all.into_iter().map(Some).collect();
    req.iter()
        .map(|r| {
            let slot = all.iter_mut().find(|t| t.as_ref().is_some_and(|t| t.name == r.name));
            let t = slot
                .and_then(Option::take)
                .ok_or_else(|| Error::Runtime(format!("output `{}` was not produced", r.name)))?;
            let placement = match &r.shared_memory {
                Some(at) => Placement::SharedMemory(at.clone()),
                None => Placement::of(r.binary.unwrap_or(binary_default)),
            };
            Ok((t, placement))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::api::{ErrorDetail, KeypointPose, Mode, ModelRef, PersonPose, SkippedPerson, Timings};

    fn t(name: &str, dt: DataType, shape: &[i64], data: TensorData) -> InputTensor {
        InputTensor::new(name.into(), dt, shape.to_vec(), data, false).unwrap()
    }

    fn identity() -> Vec<f64> {
        let mut e = vec![0.0; 16];
        for i in 0..4 {
            e[i * 5] = 1.0;
        }
        e
    }

    fn valid() -> Vec<InputTensor> {
        vec![
            t("points", DataType::F32, &[2, 3], TensorData::F32(vec![8.0, 0.5, 0.9, 8.1, 0.4, 1.0])),
            t(
                "calibration_intrinsic",
                DataType::F64,
                &[9],
                TensorData::F64(vec![500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
            ),
            t("calibration_extrinsic", DataType::F64, &[16], TensorData::F64(identity())),
            t("image_size", DataType::I32, &[2], TensorData::Int(vec![640, 480])),
            t(
                "boxes_3d",
                DataType::F64,
                &[2, 7],
                TensorData::F64(vec![8.0, 0.5, 0.9, 0.5, 0.7, 1.8, 0.3, 12.0, -1.5, 0.9, 0.5, 0.7, 1.8, 0.0]),
            ),
        ]
    }

    fn replace(mut inputs: Vec<InputTensor>, x: InputTensor) -> Vec<InputTensor> {
        inputs.retain(|i| i.name != x.name);
        inputs.push(x);
        inputs
    }

    fn field_of<T: std::fmt::Debug>(r: Result<T>) -> String {
        match r {
            Err(Error::InvalidField { field, .. }) => field,
            other => panic!("expected an invalid-field error, got {other:?}"),
        }
    }

    #[test]
    fn valid_tensors_become_the_frame_they_describe() {
        let (f, image) = frame_from_inputs(valid(), Some("req-1".into())).unwrap();
        assert_eq!(image, None);
        assert_eq!(f.frame_id.as_deref(), Some("req-1"));
        assert_eq!(f.points.decode().unwrap(), vec![[8.0, 0.5, 0.9], [8.1, 0.4, 1.0]]);
        let c = f.calibration.as_ref().unwrap();
        assert_eq!((c.width, c.height), (640, 480));
        assert_eq!(c.extrinsic, identity());
        assert_eq!(f.persons.len(), 2);
        assert_eq!((f.persons[0].id.as_str(), f.persons[1].id.as_str()), ("0", "1"));
        assert_eq!(f.persons[1].box_3d.center_y, -1.5);
        assert_eq!(f.persons[0].box_3d.heading, 0.3);
        assert_eq!(f.persons[0].box_2d, None);
        assert_eq!(f.mode, RequestedMode::Auto);
    }

    #[test]
    fn optional_tensors_fill_ids_boxes_image_and_mode() {
        let mut inputs = valid();
        inputs.push(t(
            "boxes_2d",
            DataType::F32,
            &[2, 4],
            TensorData::F32(vec![320.0, 200.0, 40.0, 120.0, f32::NAN, f32::NAN, f32::NAN, f32::NAN]),
        ));
        inputs.push(t("person_ids", DataType::Bytes, &[2], TensorData::Bytes(vec![b"a".to_vec(), b"b".to_vec()])));
        inputs.push(t("mode", DataType::Bytes, &[1], TensorData::Bytes(vec![b"lidar".to_vec()])));
        inputs.push(t("image", DataType::Bytes, &[1], TensorData::Bytes(vec![vec![0x89, b'P', b'N', b'G']])));
        let (f, image) = frame_from_inputs(inputs, None).unwrap();
        assert_eq!(image.as_deref(), Some(&[0x89, b'P', b'N', b'G'][..]));
        assert_eq!(f.persons[0].box_2d, Some(Box2d { center_x: 320.0, center_y: 200.0, width: 40.0, height: 120.0 }));
        assert_eq!(f.persons[1].box_2d, None);
        assert_eq!((f.persons[0].id.as_str(), f.persons[1].id.as_str()), ("a", "b"));
        assert_eq!(f.mode, RequestedMode::Lidar);
        // A JSON string element is base64 text of the file.
        let json_image = InputTensor::new(
            "image".into(),
            DataType::Bytes,
            vec![1],
            TensorData::Bytes(vec![b"iVBORw==".to_vec()]),
            true,
        )
        .unwrap();
        let (_, image) = frame_from_inputs(replace(valid(), json_image), None).unwrap();
        assert_eq!(image.as_deref(), Some(&[0x89, b'P', b'N', b'G'][..]));
    }

    #[test]
    fn bad_tensors_are_errors_naming_the_tensor() {
        let cases: Vec<(Vec<InputTensor>, &str)> = vec![
            (replace(valid(), t("points", DataType::F32, &[3, 2], TensorData::F32(vec![0.0; 6]))), "points"),
            (replace(valid(), t("points", DataType::I32, &[1, 3], TensorData::Int(vec![0; 3]))), "points"),
            (
                replace(valid(), t("calibration_intrinsic", DataType::F64, &[8], TensorData::F64(vec![1.0; 8]))),
                "calibration_intrinsic",
            ),
            (
                replace(valid(), t("calibration_extrinsic", DataType::F64, &[3, 4], TensorData::F64(vec![0.0; 12]))),
                "calibration_extrinsic",
            ),
            (replace(valid(), t("image_size", DataType::I32, &[2], TensorData::Int(vec![640, 0]))), "image_size"),
            (replace(valid(), t("image_size", DataType::F32, &[2], TensorData::F32(vec![640.0, 480.0]))), "image_size"),
            (replace(valid(), t("boxes_3d", DataType::F64, &[1, 6], TensorData::F64(vec![1.0; 6]))), "boxes_3d"),
            (replace(valid(), t("boxes_3d", DataType::F64, &[0, 7], TensorData::F64(vec![]))), "boxes_3d"),
            (replace(valid(), t("boxes_2d", DataType::F64, &[1, 4], TensorData::F64(vec![1.0; 4]))), "boxes_2d"),
            (
                replace(
                    valid(),
                    t(
                        "boxes_2d",
                        DataType::F64,
                        &[2, 4],
                        TensorData::F64(vec![1.0, 1.0, 1.0, f64::NAN, 1.0, 1.0, 1.0, 1.0]),
                    ),
                ),
                "boxes_2d[0]",
            ),
            (replace(valid(), t("mode", DataType::Bytes, &[1], TensorData::Bytes(vec![b"psychic".to_vec()]))), "mode"),
            (
                replace(valid(), t("person_ids", DataType::Bytes, &[1], TensorData::Bytes(vec![b"x".to_vec()]))),
                "person_ids",
            ),
            (
                replace(
                    valid(),
                    t("person_ids", DataType::Bytes, &[2], TensorData::Bytes(vec![b"x".to_vec(), b"x".to_vec()])),
                ),
                "person_ids[1]",
            ),
            (replace(valid(), t("telemetry", DataType::F32, &[1], TensorData::F32(vec![0.0]))), "telemetry"),
            (replace(valid(), t("image", DataType::Bytes, &[2], TensorData::Bytes(vec![vec![1], vec![2]]))), "image"),
        ];
        for (inputs, want) in cases {
            assert_eq!(field_of(frame_from_inputs(inputs, None)), want);
        }
        // Values checked by the frame's validation still name the tensor.
        let b = vec![8.0, 0.5, 0.9, 0.5, 0.7, -1.8, 0.3, 12.0, -1.5, 0.9, 0.5, 0.7, 1.8, 0.0];
        let bad_height = replace(valid(), t("boxes_3d", DataType::F64, &[2, 7], TensorData::F64(b)));
        assert_eq!(field_of(frame_from_inputs(bad_height, None)), "boxes_3d[0].height");
        let mut intr = vec![500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        intr[1] = 0.0;
        let bad_f = replace(valid(), t("calibration_intrinsic", DataType::F64, &[9], TensorData::F64(intr)));
        assert_eq!(field_of(frame_from_inputs(bad_f, None)), "calibration_intrinsic[1] (f_v)");
        // Missing and doubled inputs.
        let mut no_points = valid();
        no_points.retain(|i| i.name != "points");
        assert_eq!(field_of(frame_from_inputs(no_points, None)), "points");
        let mut twice = valid();
        twice.push(twice[0].clone());
        assert_eq!(field_of(frame_from_inputs(twice, None)), "points");
        // The shape must hold the data.
        let e = InputTensor::new("points".into(), DataType::F32, vec![2, 3], TensorData::F32(vec![0.0; 3]), false);
        assert_eq!(field_of(e), "points");
        let e = InputTensor::new("points".into(), DataType::F32, vec![-1, 3], TensorData::F32(vec![0.0; 3]), false);
        assert_eq!(field_of(e), "points");
        let e =
            InputTensor::new("image".into(), DataType::Bytes, vec![1], TensorData::Bytes(vec![b"@@".to_vec()]), true)
                .unwrap();
        assert_eq!(field_of(frame_from_inputs(replace(valid(), e), None)), "image");
    }

    #[test]
    fn raw_and_json_encodings_decode_alike_and_raw_round_trips() {
        let f = [1.5f32, -2.25, f32::NAN];
        let raw: Vec<u8> = f.iter().flat_map(|x| x.to_le_bytes()).collect();
        let TensorData::F32(back) = TensorData::from_raw("x", DataType::F32, &raw).unwrap() else { panic!() };
        assert_eq!((back[0], back[1]), (1.5, -2.25));
        assert!(back[2].is_nan());
        let json = serde_json::json!([[1.5, -2.25], [null]]);
        let TensorData::F32(j) = TensorData::from_json("x", DataType::F32, &json).unwrap() else { panic!() };
        assert_eq!(&j[..2], &[1.5, -2.25]);
        assert!(j[2].is_nan());
        let ints = TensorData::Int(vec![640, -480]);
        assert_eq!(TensorData::from_raw("x", DataType::I32, &ints.to_raw(DataType::I32)).unwrap(), ints);
        assert_eq!(TensorData::from_raw("x", DataType::I64, &ints.to_raw(DataType::I64)).unwrap(), ints);
        let u = TensorData::UInt(vec![7, 65535]);
        assert_eq!(TensorData::from_raw("x", DataType::U16, &u.to_raw(DataType::U16)).unwrap(), u);
        let b = TensorData::Bytes(vec![b"fusion".to_vec(), vec![], vec![0xff, 0xd8]]);
        let raw = b.to_raw(DataType::Bytes);
        assert_eq!(&raw[..4], &6u32.to_le_bytes());
        assert_eq!(TensorData::from_raw("x", DataType::Bytes, &raw).unwrap(), b);
        assert_eq!(
            TensorData::from_json("x", DataType::Bytes, &serde_json::json!(["auto"])).unwrap(),
            TensorData::Bytes(vec![b"auto".to_vec()])
        );
        assert_eq!(TensorData::F32(vec![f32::NAN, 2.0]).to_json(), serde_json::json!([null, 2.0]));
    }

    #[test]
    fn malformed_data_is_an_error_naming_the_tensor() {
        assert_eq!(field_of(TensorData::from_raw("points", DataType::F32, &[0; 7])), "points");
        assert_eq!(field_of(TensorData::from_raw("image", DataType::Bytes, &[9, 0, 0, 0, 1])), "image");
        assert_eq!(field_of(TensorData::from_raw("image", DataType::Bytes, &[9, 0])), "image");
        assert_eq!(field_of(TensorData::from_raw("points", DataType::F16, &[0; 2])), "points");
        assert_eq!(field_of(TensorData::from_json("points", DataType::F32, &serde_json::json!([1, "a"]))), "points");
        assert_eq!(
            field_of(TensorData::from_json("image_size", DataType::I32, &serde_json::json!([1.5]))),
            "image_size"
        );
        assert_eq!(field_of(TensorData::from_json("mode", DataType::Bytes, &serde_json::json!([1]))), "mode");
        assert_eq!(field_of(DataType::parse("points", "FLOAT")), "points");
    }

    fn pose(id: &str, mode: Mode, behind: bool) -> PersonPose {
        PersonPose {
            id: id.into(),
            camera: None,
            mode,
            mode_reason: String::new(),
            num_points: 42,
            box_2d: None,
            facing: None,
            keypoints: (0..K)
                .map(|k| KeypointPose {
                    name: posefuse_core::keypoints::NAMES[k].into(),
                    waymo_type: posefuse_core::keypoints::WAYMO_TYPES[k],
                    xyz: [k as f64, 1.0, 2.0],
                    uv: (!behind).then_some([10.0 + k as f64, 20.0]),
                    score: (mode != Mode::Lidar).then_some(0.5),
                })
                .collect(),
        }
    }

    fn response() -> PoseResponse {
        PoseResponse {
            frame_id: None,
            model: ModelRef { name: "default".into(), version: "1".into() },
            persons: vec![pose("a", Mode::Fusion, false), pose("c", Mode::Lidar, true)],
            skipped: vec![SkippedPerson {
                index: 1,
                id: "b".into(),
                error: ErrorDetail { code: "insufficient_data".into(), message: String::new(), field: None },
            }],
            timings: Timings::default(),
        }
    }

    #[test]
    fn outputs_keep_request_rows_with_nan_for_skipped_and_missing_values() {
        let out = outputs_from_response(&response(), 3).unwrap();
        let names: Vec<&str> = out.iter().map(|o| o.name).collect();
        assert_eq!(names, OUTPUTS.iter().map(|s| s.name).collect::<Vec<_>>());
        assert_eq!(out[0].shape, vec![3, 13, 3]);
        let TensorData::F32(kp3) = &out[0].data else { panic!() };
        assert_eq!(&kp3[..6], &[0.0, 1.0, 2.0, 1.0, 1.0, 2.0]);
        assert!(kp3[39..78].iter().all(|v| v.is_nan()));
        assert_eq!(kp3[78 + 3], 1.0);
        let TensorData::F32(kp2) = &out[1].data else { panic!() };
        assert_eq!(&kp2[..2], &[10.0, 20.0]);
        assert!(kp2[26..].iter().all(|v| v.is_nan()), "skipped, then behind the camera");
        let TensorData::F32(sc) = &out[2].data else { panic!() };
        assert_eq!(sc[0], 0.5);
        assert!(sc[13..].iter().all(|v| v.is_nan()), "skipped, then LiDAR-only");
        assert_eq!(out[3].data, TensorData::Bytes(vec![b"fusion".to_vec(), b"none".to_vec(), b"lidar".to_vec()]));
        assert_eq!(out[4].data, TensorData::Bytes(vec![b"ok".to_vec(), b"insufficient_data".to_vec(), b"ok".to_vec()]));
        assert_eq!(out[5].data, TensorData::Int(vec![42, -1, 42]));
        assert!(outputs_from_response(&response(), 2).is_err(), "more poses than persons");
        assert!(outputs_from_response(&response(), 4).is_err(), "fewer poses than persons");
    }

    #[test]
    fn requested_outputs_are_selected_in_order_with_their_encoding() {
        let all = outputs_from_response(&response(), 3).unwrap();
        let every = select_outputs(all.clone(), None, true).unwrap();
        assert_eq!(every.len(), OUTPUTS.len());
        assert!(every.iter().all(|(_, p)| *p == Placement::Binary));
        let at = ShmRef { region: "out".into(), byte_size: 12, offset: 4 };
        let req = [
            RequestedOutput::named("mode", Some(false)),
            RequestedOutput::named("keypoints_3d", None),
            RequestedOutput { shared_memory: Some(at.clone()), ..RequestedOutput::named("num_points", Some(false)) },
        ];
        let three = select_outputs(all.clone(), Some(&req), true).unwrap();
        let got: Vec<_> = three.iter().map(|(t, p)| (t.name, p.clone())).collect();
        assert_eq!(
            got,
            [
                ("mode", Placement::Json),
                ("keypoints_3d", Placement::Binary),
                ("num_points", Placement::SharedMemory(at))
            ]
        );
        let unknown = [RequestedOutput::named("heatmaps", None)];
        assert_eq!(field_of(check_requested(Some(&unknown))), "heatmaps");
        let twice = [req[0].clone(), req[0].clone()];
        assert_eq!(field_of(select_outputs(all, Some(&twice), false)), "mode");
    }

    #[test]
    fn image_rgb_pixels_become_the_frames_pixels() {
        let px: Vec<u8> = (0..2 * 3 * 3).map(|v| v as u8).collect();
        let raw = TensorData::from_raw("image_rgb", DataType::U8, &px).unwrap();
        assert_eq!(raw, TensorData::U8(px.clone()), "UINT8 stays one byte per element");
        let json = TensorData::from_json("image_rgb", DataType::U8, &serde_json::json!(px)).unwrap();
        assert_eq!(json, raw);
        assert_eq!(json.to_raw(DataType::U8), px);
        assert_eq!(field_of(TensorData::from_json("image_rgb", DataType::U8, &serde_json::json!([256]))), "image_rgb");
        let rgb = |shape: &[i64], data: TensorData| {
            InputTensor::new("image_rgb".into(), DataType::U8, shape.to_vec(), data, false).unwrap()
        };
        let small = |inputs| replace(inputs, t("image_size", DataType::I32, &[2], TensorData::Int(vec![3, 2])));
        let (f, image) = frame_from_inputs(small(replace(valid(), rgb(&[2, 3, 3], raw))), None).unwrap();
        assert_eq!(image, None);
        assert_eq!(f.image_rgb, Some(RgbPixels { width: 3, height: 2, pixels: px.clone() }));
        // Widened integers (gRPC's uint_contents of another type, JSON UINT16) are narrowed, checked.
        let wide = TensorData::UInt(px.iter().map(|v| u64::from(*v)).collect());
        let (f, _) = frame_from_inputs(small(replace(valid(), rgb(&[2, 3, 3], wide))), None).unwrap();
        assert_eq!(f.image_rgb.map(|p| p.pixels), Some(px.clone()));
        let over = TensorData::UInt(vec![300; 18]);
        assert_eq!(field_of(frame_from_inputs(small(replace(valid(), rgb(&[2, 3, 3], over))), None)), "image_rgb");
        assert_eq!(
            field_of(frame_from_inputs(small(replace(valid(), rgb(&[3, 2, 3], TensorData::U8(px.clone())))), None))
                .as_str(),
            "image_rgb"
        );
        assert_eq!(
            field_of(frame_from_inputs(small(replace(valid(), rgb(&[6, 3], TensorData::U8(px.clone())))), None)),
            "image_rgb"
        );
        let floats =
            InputTensor::new("image_rgb".into(), DataType::F32, vec![2, 3, 3], TensorData::F32(vec![0.0; 18]), false)
                .unwrap();
        assert_eq!(field_of(frame_from_inputs(small(replace(valid(), floats)), None)), "image_rgb");
        let mut both = small(replace(valid(), rgb(&[2, 3, 3], TensorData::U8(px))));
        both.push(t("image", DataType::Bytes, &[1], TensorData::Bytes(vec![vec![0xFF, 0xD8]])));
        assert_eq!(field_of(frame_from_inputs(both, None)), "image_rgb");
        assert_eq!(integers(&t("image_size", DataType::U8, &[2], TensorData::U8(vec![3, 2]))).unwrap(), vec![3, 2]);
        assert_eq!(tensor_field("image_rgb.width/height"), "image_rgb");
        assert_eq!(tensor_field("image_rgb.b64"), "image_rgb");
    }

    #[test]
    fn frame_fields_map_to_their_tensors() {
        assert_eq!(tensor_field("persons[3].box_2d"), "boxes_2d[3]");
        assert_eq!(tensor_field("persons[0].box_3d.width"), "boxes_3d[0].width");
        assert_eq!(tensor_field("persons[1].id"), "person_ids[1]");
        assert_eq!(tensor_field("persons"), "boxes_3d");
        assert_eq!(tensor_field("calibration.extrinsic"), "calibration_extrinsic");
        assert_eq!(tensor_field("calibration.width/height"), "image_size");
        assert_eq!(tensor_field("points[4]"), "points[4]");
        assert_eq!(tensor_field("image"), "image");
    }
}
