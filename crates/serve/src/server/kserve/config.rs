//! The model configuration as Triton's clients ask for it (`GET /v2/models/{m}/config`, gRPC
//! `ModelConfig`): Triton's extension of the protocol, which `tritonclient`'s
//! `get_model_config` reads. One description, rendered as Triton's JSON and as its message.

use serde_json::{json, Value};

use super::tensors::{DataType, TensorSpec, INPUTS, OUTPUTS, REQUIRED_INPUTS};

/// Triton's name and number for a protocol datatype (model_config.proto's `DataType`; BYTES is
/// `TYPE_STRING` there).
pub fn triton_type(dt: DataType) -> (&'static str, i32) {
    match dt {
        DataType::Bool => ("TYPE_BOOL", 1),
        DataType::U8 => ("TYPE_UINT8", 2),
        DataType::U16 => ("TYPE_UINT16", 3),
        DataType::U32 => ("TYPE_UINT32", 4),
        DataType::U64 => ("TYPE_UINT64", 5),
        DataType::I8 => ("TYPE_INT8", 6),
        DataType::I16 => ("TYPE_INT16", 7),
        DataType::I32 => ("TYPE_INT32", 8),
        DataType::I64 => ("TYPE_INT64", 9),
        DataType::F16 => ("TYPE_FP16", 10),
        DataType::F32 => ("TYPE_FP32", 11),
        DataType::F64 => ("TYPE_FP64", 12),
        DataType::Bytes => ("TYPE_STRING", 13),
        DataType::Bf16 => ("TYPE_BF16", 14),
    }
}

/// Whether an input may be left out of a request.
pub fn optional(spec: &TensorSpec) -> bool {
    !REQUIRED_INPUTS.contains(&spec.name)
}

/// The configuration in Triton's JSON form. `max_batch_size` 0: a request is one frame and its
/// shapes are whole (the server batches persons across requests itself).
pub fn config_json(name: &str) -> Value {
    let inputs: Vec<Value> = INPUTS
        .iter()
        .map(|s| {
            json!({
                "name": s.name,
                "data_type": triton_type(s.datatype).0,
                "format": "FORMAT_NONE",
                "dims": s.shape,
                "optional": optional(s),
            })
        })
        .collect();
    let outputs: Vec<Value> = OUTPUTS
        .iter()
        .map(|s| json!({ "name": s.name, "data_type": triton_type(s.datatype).0, "dims": s.shape }))
        .collect();
    json!({
        "name": name,
        "platform": super::PLATFORM,
        "backend": super::PLATFORM,
        "version_policy": { "latest": { "num_versions": 1 } },
        "max_batch_size": 0,
        "input": inputs,
        "output": outputs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_json_config_lists_every_tensor_with_tritons_types() {
        let c = config_json("pedestrians");
        assert_eq!(c["name"], "pedestrians");
        assert_eq!(c["max_batch_size"], 0);
        let inputs = c["input"].as_array().unwrap();
        assert_eq!(inputs.len(), INPUTS.len());
        let points = inputs.iter().find(|i| i["name"] == "points").unwrap();
        assert_eq!((points["data_type"].as_str(), points["optional"].as_bool()), (Some("TYPE_FP32"), Some(false)));
        assert_eq!(points["dims"], json!([-1, 3]));
        let image = inputs.iter().find(|i| i["name"] == "image").unwrap();
        assert_eq!((image["data_type"].as_str(), image["optional"].as_bool()), (Some("TYPE_STRING"), Some(true)));
        let outputs = c["output"].as_array().unwrap();
        assert_eq!(outputs.iter().map(|o| o["name"].as_str().unwrap()).collect::<Vec<_>>(), OUTPUTS.map(|o| o.name));
        assert_eq!(outputs[0]["dims"], json!([-1, 13, 3]));
    }

    #[test]
    fn triton_numbers_follow_model_config_proto() {
        assert_eq!(triton_type(DataType::F32), ("TYPE_FP32", 11));
        assert_eq!(triton_type(DataType::F64), ("TYPE_FP64", 12));
        assert_eq!(triton_type(DataType::I32), ("TYPE_INT32", 8));
        assert_eq!(triton_type(DataType::Bytes), ("TYPE_STRING", 13));
        assert_eq!(triton_type(DataType::Bool), ("TYPE_BOOL", 1));
        assert_eq!(triton_type(DataType::Bf16), ("TYPE_BF16", 14));
    }
}
