//! A request's tensors that lie in system shared memory (`shared_memory`): inputs read when the
//! frame is built, in the request's pre-processing step (except the camera's pixels, which each
//! crop reads as the rectangle its window needs, [`SharedPixels`]), output regions held before
//! inference runs and written after it. The transports parse the `shared_memory_*` parameters
//! into [`ShmRef`]s; this is the one place that reads and writes the regions for a request.

use std::sync::Arc;

use posefuse_core::image_decode::PixelSource;
use posefuse_core::pipeline::PixelRect;

use super::shared_memory::{Region, ShmRef, SystemSharedMemory};
use super::tensors::{DataType, InputTensor, OutputTensor, Placement, RequestedOutput, TensorData};
use posefuse_core::error::{Error, Result};

/// An input whose data lies in a shared-memory region.
#[derive(Debug, Clone, PartialEq)]
pub struct SharedInput {
    pub name: String,
    pub datatype: DataType,
    pub shape: Vec<i64>,
    pub at: ShmRef,
}

/// The camera image's name among the inputs.
const IMAGE_RGB: &str = "image_rgb";

/// The camera's RGB8 pixels in a held region, read a crop's rectangle at a time.
pub struct SharedPixels {
    region: Arc<Region>,
    at: ShmRef,
    width: u32,
    height: u32,
}

impl SharedPixels {
    /// `image_rgb` ([H, W, 3] UINT8) at `input.at` of `region`, its size checked against its
    /// shape and its span against the region (no byte is read).
    fn new(region: Arc<Region>, input: &SharedInput) -> Result<SharedPixels> {
        let field = |m: String| Error::field(IMAGE_RGB, m);
        if input.datatype != DataType::U8 {
            return Err(field(format!("datatype {}, expected UINT8", input.datatype.as_str())));
        }
        let (height, width) = match input.shape[..] {
            [h, w, 3] => (u32::try_from(h).ok(), u32::try_from(w).ok()),
            _ => (None, None),
        };
        let (Some(height), Some(width)) = (height, width) else {
            return Err(field(format!("shape {:?}, expected [H, W, 3]", input.shape)));
        };
        let bytes = u64::from(width) * u64::from(height) * 3;
        if bytes != input.at.byte_size {
            return Err(field(format!(
                "shape {:?} holds {bytes} bytes but shared_memory_byte_size is {}",
                input.shape, input.at.byte_size
            )));
        }
        region.check_span(IMAGE_RGB, &input.at)?;
        Ok(SharedPixels { region, at: input.at.clone(), width, height })
    }
}

impl PixelSource for SharedPixels {
    fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The crops' pixels only, row by row from the mapping, rather than whole rows.
    fn read_rect_into(&self, r: PixelRect, out: &mut [u8]) -> std::result::Result<(), String> {
        if r.x0 > r.x1 || r.y0 > r.y1 || r.x1 > self.width || r.y1 > self.height {
            return Err(format!("rectangle {r:?} is not inside the {}×{} image", self.width, self.height));
        }
        if out.len() as u64 != r.area() * 3 {
            return Err(format!("{} bytes asked for rectangle {r:?}", out.len()));
        }
        let row = (r.x1 - r.x0) as usize * 3;
        let first = self.at.offset + (u64::from(r.y0) * u64::from(self.width) + u64::from(r.x0)) * 3;
        let read = self.region.read_rows(IMAGE_RGB, first, u64::from(self.width) * 3, row, out);
        read.map_err(|e| e.to_string())
    }
}

/// A request's inputs from shared memory.
#[derive(Debug)]
pub struct SharedInputs {
    /// Every input but the camera's pixels, read.
    pub tensors: Vec<InputTensor>,
    /// The camera's pixels (`image_rgb`), read by the crops.
    pub pixels: Option<Arc<dyn PixelSource>>,
}

/// The inputs in shared memory: the camera's pixels (`image_rgb`) as a source whose crops read
/// rows of it, the others read as tensors. Their sizes together are bounded by `limit` (the body
/// limit: a region is read into memory as a body would be) before any byte is read.
pub fn read_inputs(shm: &SystemSharedMemory, shared: Vec<SharedInput>, limit: usize) -> Result<SharedInputs> {
    let total = shared.iter().fold(0u64, |n, s| n.saturating_add(s.at.byte_size));
    if total > limit as u64 {
        return Err(Error::PayloadTooLarge { limit });
    }
    let regions = shared.iter().map(|s| shm.region(&s.name, &s.at)).collect::<Result<Vec<_>>>()?;
    let mut pixels: Option<Arc<dyn PixelSource>> = None;
    let mut tensors = Vec::with_capacity(shared.len());
    for (s, region) in shared.into_iter().zip(regions) {
        if s.name == IMAGE_RGB {
            if pixels.is_some() {
                return Err(Error::field(IMAGE_RGB, "given twice"));
            }
            pixels = Some(Arc::new(SharedPixels::new(region, &s)?));
            continue;
        }
        let raw = region.read(&s.name, &s.at)?;
        let data = match s.datatype {
            DataType::U8 => TensorData::U8(raw),
            dt => TensorData::from_raw(&s.name, dt, &raw)?,
        };
        tensors.push(InputTensor::new(s.name, s.datatype, s.shape, data, false)?);
    }
    Ok(SharedInputs { tensors, pixels })
}

/// The regions a request's outputs go to, held from before inference until they are written, so
/// that unregistering one meanwhile does not lose the answer.
#[derive(Debug, Default)]
pub struct OutputRegions(Vec<(String, Arc<Region>)>);

/// Holds the region of each requested output placed in shared memory, checking that it is
/// registered and that the requested span lies in it.
pub fn hold_output_regions(shm: &SystemSharedMemory, requested: Option<&[RequestedOutput]>) -> Result<OutputRegions> {
    let mut held = Vec::new();
    for r in requested.unwrap_or_default() {
        if let Some(at) = &r.shared_memory {
            let region = shm.region(&r.name, at)?;
            region.check_span(&r.name, at)?;
            held.push((r.name.clone(), region));
        }
    }
    Ok(OutputRegions(held))
}

/// Writes the outputs placed in shared memory to their held regions; each one's placement then
/// says how many bytes were written (`shared_memory_byte_size` in the response).
pub fn write_outputs(
    outputs: Vec<(OutputTensor, Placement)>,
    regions: &OutputRegions,
) -> Result<Vec<(OutputTensor, Placement)>> {
    outputs
        .into_iter()
        .map(|(t, placement)| {
            let Placement::SharedMemory(at) = placement else { return Ok((t, placement)) };
            let region =
                regions.0.iter().find(|(name, _)| name == t.name).map(|(_, r)| r).ok_or_else(|| {
                    Error::Runtime(format!("output `{}`: its shared memory region was not held", t.name))
                })?;
            let raw = t.data.to_raw(t.datatype);
            region.write(t.name, &at, &raw)?;
            let written = ShmRef { byte_size: raw.len() as u64, ..at };
            Ok((t, Placement::SharedMemory(written)))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::server::kserve::shared_memory::SharedMemoryConfig;

    /// The pixels of `r` as a new buffer.
    fn read(pixels: &dyn PixelSource, r: PixelRect) -> std::result::Result<Vec<u8>, String> {
        let mut out = vec![0u8; r.area() as usize * 3];
        pixels.read_rect_into(r, &mut out).map(|()| out)
    }

    fn memory(dir: &std::path::Path) -> SystemSharedMemory {
        let m = SystemSharedMemory::new(SharedMemoryConfig { enabled: true, dir: dir.into(), max_regions: 4 });
        let mut bytes = vec![9u8; 6];
        bytes.extend([1.5f32, -2.0, 3.25].iter().flat_map(|v| v.to_le_bytes()));
        bytes.extend([0u8; 16]);
        std::fs::write(dir.join("obj"), &bytes).unwrap();
        m.register("in", "/obj", 0, 18).unwrap();
        m.register("out", "/obj", 18, 16).unwrap();
        m
    }

    fn input(name: &str, datatype: DataType, shape: &[i64], offset: u64, byte_size: u64) -> SharedInput {
        SharedInput {
            name: name.into(),
            datatype,
            shape: shape.to_vec(),
            at: ShmRef { region: "in".into(), byte_size, offset },
        }
    }

    #[test]
    fn inputs_are_read_decoded_and_bounded_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let m = memory(dir.path());
        let shared =
            vec![input("image_rgb", DataType::U8, &[1, 2, 3], 0, 6), input("points", DataType::F32, &[1, 3], 6, 12)];
        let SharedInputs { tensors: got, pixels } = read_inputs(&m, shared.clone(), 18).unwrap();
        assert_eq!(got.len(), 1, "the pixels are not read as a tensor");
        assert_eq!(got[0].data, TensorData::F32(vec![1.5, -2.0, 3.25]));
        let pixels = pixels.unwrap();
        assert_eq!(pixels.size(), (2, 1));
        let rect = |x0, y0, x1, y1| PixelRect { x0, y0, x1, y1 };
        assert_eq!(read(pixels.as_ref(), rect(0, 0, 2, 1)).unwrap(), vec![9; 6]);
        assert_eq!(read(pixels.as_ref(), rect(1, 0, 2, 1)).unwrap(), vec![9; 3]);
        assert_eq!(read(pixels.as_ref(), rect(0, 1, 2, 1)).unwrap(), Vec::<u8>::new());
        assert!(matches!(read_inputs(&m, shared, 17), Err(Error::PayloadTooLarge { limit: 17 })));
        for bad in [
            input("image_rgb", DataType::U8, &[1, 2, 3], 0, 5),
            input("image_rgb", DataType::U8, &[2, 3], 0, 6),
            input("image_rgb", DataType::U16, &[1, 1, 3], 0, 6),
            input("image_rgb", DataType::U8, &[2, 2, 3], 8, 12),
        ] {
            assert_eq!(read_inputs(&m, vec![bad.clone()], 64).unwrap_err().field_name(), Some("image_rgb"), "{bad:?}");
        }
        let e = read_inputs(&m, vec![input("points", DataType::F32, &[2, 3], 6, 12)], 64).unwrap_err();
        assert_eq!(e.field_name(), Some("points"), "shape and bytes disagree");
        let mut gone = input("points", DataType::F32, &[1, 3], 6, 12);
        gone.at.region = "nope".into();
        assert_eq!(read_inputs(&m, vec![gone], 64).unwrap_err().field_name(), Some("points"));
    }

    #[test]
    fn pixel_rectangles_are_read_row_by_row_from_their_place() {
        let dir = tempfile::tempdir().unwrap();
        // a 4×3 image after 5 bytes of something else; pixel (x, y) is [10y + x, 100 + 10y + x, 200]
        let mut bytes = vec![7u8; 5];
        for y in 0..3u8 {
            for x in 0..4u8 {
                bytes.extend([10 * y + x, 100 + 10 * y + x, 200]);
            }
        }
        std::fs::write(dir.path().join("img"), &bytes).unwrap();
        let m = SystemSharedMemory::new(SharedMemoryConfig { enabled: true, dir: dir.path().into(), max_regions: 1 });
        m.register("px", "/img", 0, bytes.len() as u64).unwrap();
        let at = ShmRef { region: "px".into(), byte_size: 36, offset: 5 };
        let shared = SharedInput { name: "image_rgb".into(), datatype: DataType::U8, shape: vec![3, 4, 3], at };
        let pixels = read_inputs(&m, vec![shared], 64).unwrap().pixels.unwrap();
        let rect = |x0, y0, x1, y1| PixelRect { x0, y0, x1, y1 };
        let expect = |r: PixelRect| -> Vec<u8> {
            (r.y0..r.y1)
                .flat_map(|y| (r.x0..r.x1).flat_map(move |x| [(10 * y + x) as u8, (100 + 10 * y + x) as u8, 200]))
                .collect()
        };
        for r in [rect(1, 1, 3, 3), rect(0, 1, 4, 3), rect(2, 0, 3, 1), rect(0, 0, 4, 3), rect(3, 2, 4, 3)] {
            assert_eq!(read(pixels.as_ref(), r).unwrap(), expect(r), "{r:?}");
        }
        assert_eq!(read(pixels.as_ref(), rect(2, 1, 2, 3)).unwrap(), Vec::<u8>::new(), "no column");
        for outside in [rect(3, 0, 5, 1), rect(0, 2, 1, 4), rect(2, 0, 1, 1), rect(0, 2, 1, 1)] {
            assert!(read(pixels.as_ref(), outside).unwrap_err().contains("not inside"), "{outside:?}");
        }
        let mut short = vec![0u8; 5];
        assert!(pixels.read_rect_into(rect(0, 0, 2, 1), &mut short).unwrap_err().contains("5 bytes"));
    }

    #[test]
    fn outputs_are_written_to_held_regions_with_the_bytes_written() {
        let dir = tempfile::tempdir().unwrap();
        let m = memory(dir.path());
        let at = ShmRef { region: "out".into(), byte_size: 12, offset: 4 };
        let requested =
            [RequestedOutput { shared_memory: Some(at.clone()), ..RequestedOutput::named("num_points", None) }];
        let held = hold_output_regions(&m, Some(&requested)).unwrap();
        m.unregister("out").unwrap();
        let t = OutputTensor {
            name: "num_points",
            datatype: DataType::I32,
            shape: vec![2],
            data: TensorData::Int(vec![5, -1]),
        };
        let other = OutputTensor { name: "scores", ..t.clone() };
        let out =
            write_outputs(vec![(t.clone(), Placement::SharedMemory(at)), (other, Placement::Json)], &held).unwrap();
        assert_eq!(out[0].1, Placement::SharedMemory(ShmRef { region: "out".into(), byte_size: 8, offset: 4 }));
        assert_eq!(out[1].1, Placement::Json);
        let bytes = std::fs::read(dir.path().join("obj")).unwrap();
        assert_eq!(&bytes[22..30], &[5, 0, 0, 0, 255, 255, 255, 255]);

        m.register("out", "/obj", 18, 16).unwrap();
        let tight = ShmRef { region: "out".into(), byte_size: 4, offset: 0 };
        let requested =
            [RequestedOutput { shared_memory: Some(tight.clone()), ..RequestedOutput::named("num_points", None) }];
        let held = hold_output_regions(&m, Some(&requested)).unwrap();
        let e = write_outputs(vec![(t, Placement::SharedMemory(tight))], &held).unwrap_err();
        assert_eq!(e.field_name(), Some("num_points"), "8 bytes do not fit in 4");
        let outside = ShmRef { region: "out".into(), byte_size: 8, offset: 12 };
        let requested =
            [RequestedOutput { shared_memory: Some(outside), ..RequestedOutput::named("num_points", None) }];
        assert_eq!(hold_output_regions(&m, Some(&requested)).unwrap_err().field_name(), Some("num_points"));
    }
}
