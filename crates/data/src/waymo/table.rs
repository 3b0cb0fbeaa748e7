//! Arrow columns by meaning: whatever physical type a release stored (int8 or int32 or a string
//! for a name, float or double, list or fixed-size list), the reader asks for "integers",
//! "reals", "a camera name", "lists of reals" and gets them, or an error naming the component
//! and the column. The writer side builds the declared types, or the alternate ones other
//! releases use (to test the reader on both).

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::error::Context;
use crate::{bail, invalid};
use arrow_array::builder::{
    BooleanBuilder, FixedSizeListBuilder, Float32Builder, Float64Builder, Int32Builder, Int64Builder, Int8Builder,
    ListBuilder,
};
use arrow_array::cast::AsArray;
use arrow_array::types::{
    Float32Type, Float64Type, Int16Type, Int32Type, Int64Type, Int8Type, UInt16Type, UInt32Type, UInt64Type, UInt8Type,
};
use arrow_array::{Array, ArrayRef, BinaryArray, Int64Array, RecordBatch, StringArray};
use arrow_schema::DataType;
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::{ArrowWriter, ProjectionMask};
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;

/// One record batch of a component, with the component's name for error messages.
pub struct Table {
    pub component: String,
    pub batch: RecordBatch,
}

macro_rules! numeric {
    ($a:expr, $out:ty, $($dt:ident => $t:ty),*) => {
        match $a.data_type() {
            $(DataType::$dt => Some($a.as_primitive::<$t>().iter().map(|v| v.map(|x| x as $out)).collect::<Vec<Option<$out>>>()),)*
            _ => None,
        }
    };
}

/// Any integer array as i64 (nulls as `None`).
fn ints(a: &dyn Array) -> Option<Vec<Option<i64>>> {
    numeric!(a, i64, Int8 => Int8Type, Int16 => Int16Type, Int32 => Int32Type, Int64 => Int64Type,
        UInt8 => UInt8Type, UInt16 => UInt16Type, UInt32 => UInt32Type, UInt64 => UInt64Type)
}

/// Any float or integer array as f64 (nulls as `None`).
fn reals(a: &dyn Array) -> Option<Vec<Option<f64>>> {
    numeric!(a, f64, Float32 => Float32Type, Float64 => Float64Type, Int8 => Int8Type, Int16 => Int16Type,
        Int32 => Int32Type, Int64 => Int64Type, UInt8 => UInt8Type, UInt16 => UInt16Type, UInt32 => UInt32Type,
        UInt64 => UInt64Type)
}

/// Any float array as f32 (the range images: no copy through f64 when already f32).
fn reals32(a: &dyn Array) -> Option<Vec<f32>> {
    match a.data_type() {
        DataType::Float32 if a.null_count() == 0 => Some(a.as_primitive::<Float32Type>().values().to_vec()),
        _ => reals(a).map(|v| v.into_iter().map(|x| x.map_or(f32::NAN, |x| x as f32)).collect()),
    }
}

/// Booleans, or integers read as `!= 0`.
fn bools(a: &dyn Array) -> Option<Vec<bool>> {
    match a.data_type() {
        DataType::Boolean => Some(a.as_boolean().iter().map(|v| v.unwrap_or(false)).collect()),
        _ => ints(a).map(|v| v.into_iter().map(|x| x.unwrap_or(0) != 0).collect()),
    }
}

fn strings(a: &dyn Array) -> Option<Vec<Option<String>>> {
    match a.data_type() {
        DataType::Utf8 => Some(a.as_string::<i32>().iter().map(|s| s.map(str::to_owned)).collect()),
        DataType::LargeUtf8 => Some(a.as_string::<i64>().iter().map(|s| s.map(str::to_owned)).collect()),
        DataType::Utf8View => Some(a.as_string_view().iter().map(|s| s.map(str::to_owned)).collect()),
        DataType::Binary => {
            Some(a.as_binary::<i32>().iter().map(|s| s.map(|b| String::from_utf8_lossy(b).into_owned())).collect())
        }
        _ => None,
    }
}

/// The items of row `i` of a list column (list, large list or fixed-size list).
fn list_items(a: &dyn Array, i: usize) -> Option<ArrayRef> {
    match a.data_type() {
        DataType::List(_) => Some(a.as_list::<i32>().value(i)),
        DataType::LargeList(_) => Some(a.as_list::<i64>().value(i)),
        DataType::FixedSizeList(..) => Some(a.as_fixed_size_list().value(i)),
        _ => None,
    }
}

impl Table {
    /// A column by name, or an error naming the component and the column.
    pub fn column(&self, name: &str) -> crate::error::Result<&ArrayRef> {
        self.batch.column_by_name(name).ok_or_else(|| invalid!("component `{}`: no column `{name}`", self.component))
    }

    pub fn rows(&self) -> usize {
        self.batch.num_rows()
    }

    fn bad(&self, name: &str, what: &str) -> crate::error::DataError {
        let dt = self.batch.column_by_name(name).map(|c| c.data_type().to_string()).unwrap_or_default();
        invalid!("component `{}`: column `{name}` has type {dt}, not {what}", self.component)
    }

    fn no_nulls<T>(&self, name: &str, v: Vec<Option<T>>) -> crate::error::Result<Vec<T>> {
        v.into_iter()
            .enumerate()
            .map(|(i, x)| {
                x.ok_or_else(|| invalid!("component `{}`: column `{name}` is null in row {i}", self.component))
            })
            .collect()
    }

    /// Integers of any width.
    pub fn i64s(&self, name: &str) -> crate::error::Result<Vec<i64>> {
        let v = ints(self.column(name)?.as_ref()).ok_or_else(|| self.bad(name, "an integer"))?;
        self.no_nulls(name, v)
    }

    /// Reals (float, double or integer).
    pub fn f64s(&self, name: &str) -> crate::error::Result<Vec<f64>> {
        let v = reals(self.column(name)?.as_ref()).ok_or_else(|| self.bad(name, "a number"))?;
        self.no_nulls(name, v)
    }

    pub fn strings(&self, name: &str) -> crate::error::Result<Vec<String>> {
        let v = strings(self.column(name)?.as_ref()).ok_or_else(|| self.bad(name, "a string"))?;
        self.no_nulls(name, v)
    }

    /// An enum stored as an integer or as its name (`"FRONT"`); `names` in enum order from 1.
    pub fn enums(&self, name: &str, names: &[&str]) -> crate::error::Result<Vec<i64>> {
        let col = self.column(name)?.as_ref();
        if let Some(v) = ints(col) {
            return self.no_nulls(name, v);
        }
        let v = strings(col).ok_or_else(|| self.bad(name, "an enum (integer or name)"))?;
        self.no_nulls(name, v)?
            .iter()
            .map(|s| {
                super::schema::name_value(names, s).ok_or_else(|| {
                    invalid!("component `{}`: column `{name}`: unknown name {s:?} (one of {names:?})", self.component)
                })
            })
            .collect()
    }

    pub fn binaries(&self, name: &str) -> crate::error::Result<Vec<Vec<u8>>> {
        let a = self.column(name)?.as_ref();
        let v: Vec<Option<Vec<u8>>> = match a.data_type() {
            DataType::Binary => a.as_binary::<i32>().iter().map(|b| b.map(<[u8]>::to_vec)).collect(),
            DataType::LargeBinary => a.as_binary::<i64>().iter().map(|b| b.map(<[u8]>::to_vec)).collect(),
            DataType::BinaryView => a.as_binary_view().iter().map(|b| b.map(<[u8]>::to_vec)).collect(),
            _ => return Err(self.bad(name, "binary")),
        };
        self.no_nulls(name, v)
    }

    fn lists<T>(
        &self,
        name: &str,
        item: impl Fn(&dyn Array) -> Option<Vec<T>>,
        what: &str,
    ) -> crate::error::Result<Vec<Vec<T>>> {
        let a = self.column(name)?.as_ref();
        (0..a.len())
            .map(|i| {
                if a.is_null(i) {
                    return Ok(Vec::new());
                }
                let items = list_items(a, i).ok_or_else(|| self.bad(name, what))?;
                item(items.as_ref()).ok_or_else(|| self.bad(name, what))
            })
            .collect()
    }

    /// Lists of reals (null items as NaN).
    pub fn f64_lists(&self, name: &str) -> crate::error::Result<Vec<Vec<f64>>> {
        self.lists(
            name,
            |a| reals(a).map(|v| v.into_iter().map(|x| x.unwrap_or(f64::NAN)).collect()),
            "a list of numbers",
        )
    }

    /// Lists of reals as f32 (range images).
    pub fn f32_lists(&self, name: &str) -> crate::error::Result<Vec<Vec<f32>>> {
        self.lists(name, reals32, "a list of numbers")
    }

    pub fn i64_lists(&self, name: &str) -> crate::error::Result<Vec<Vec<i64>>> {
        self.lists(name, |a| ints(a).map(|v| v.into_iter().map(|x| x.unwrap_or(-1)).collect()), "a list of integers")
    }

    pub fn bool_lists(&self, name: &str) -> crate::error::Result<Vec<Vec<bool>>> {
        self.lists(name, bools, "a list of booleans")
    }
}

/// A component's parquet file of one segment: `ROOT/<component>/<segment>.parquet`.
pub fn component_path(root: &Path, component: &str, segment: &str) -> PathBuf {
    root.join(component).join(format!("{segment}.parquet"))
}

/// Reads the named columns of some row groups (all when `row_groups` is `None`) as one table.
/// A missing column is an error naming it.
pub fn read_columns(
    path: &Path,
    component: &str,
    columns: &[&str],
    row_groups: Option<Vec<usize>>,
) -> crate::error::Result<Table> {
    let file = File::open(path).with_context(|| format!("component `{component}`: {}", path.display()))?;
    let mut b = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("component `{component}`: reading {}", path.display()))?;
    let fields = b.schema().fields().clone();
    let mut roots = Vec::with_capacity(columns.len());
    for c in columns {
        let i = fields
            .iter()
            .position(|f| f.name() == c)
            .ok_or_else(|| invalid!("component `{component}` ({}): no column `{c}`", path.display()))?;
        roots.push(i);
    }
    let mask = ProjectionMask::roots(b.parquet_schema(), roots);
    b = b.with_projection(mask).with_batch_size(1 << 20);
    if let Some(rg) = row_groups {
        b = b.with_row_groups(rg);
    }
    let reader = b.build().with_context(|| format!("component `{component}`: {}", path.display()))?;
    let schema = arrow_array::RecordBatchReader::schema(&reader);
    let mut batches = Vec::new();
    for batch in reader {
        batches.push(batch.with_context(|| format!("component `{component}`: decoding {}", path.display()))?);
    }
    let batch = arrow_select_concat(&schema, &batches)?;
    Ok(Table { component: component.to_owned(), batch })
}

fn arrow_select_concat(schema: &arrow_schema::SchemaRef, batches: &[RecordBatch]) -> crate::error::Result<RecordBatch> {
    match batches {
        [] => Ok(RecordBatch::new_empty(schema.clone())),
        [one] => Ok(one.clone()),
        many => Ok(arrow_select::concat::concat_batches(schema, many)?),
    }
}

/// The number of row groups of a parquet file.
pub fn row_groups(path: &Path, component: &str) -> crate::error::Result<usize> {
    let file = File::open(path).with_context(|| format!("component `{component}`: {}", path.display()))?;
    let b = ParquetRecordBatchReaderBuilder::try_new(file)
        .with_context(|| format!("component `{component}`: reading {}", path.display()))?;
    Ok(b.metadata().num_row_groups())
}

/// Columns of a batch being built, in the declared physical types or (`alt`) the other ones
/// releases use: names as strings, int8 lists as int32, float as double and double as float,
/// fixed-size lists as lists.
pub struct Columns {
    cols: Vec<(String, ArrayRef)>,
    pub alt: bool,
}

impl Columns {
    pub fn new(alt: bool) -> Columns {
        Columns { cols: Vec::new(), alt }
    }

    fn push(&mut self, name: &str, a: ArrayRef) {
        self.cols.push((name.to_owned(), a));
    }

    pub fn string(&mut self, name: &str, v: &[String]) {
        self.push(name, Arc::new(StringArray::from_iter_values(v)));
    }

    pub fn int64(&mut self, name: &str, v: &[i64]) {
        self.push(name, Arc::new(Int64Array::from(v.to_vec())));
    }

    /// An int8 column (int32 in the alternate types).
    pub fn int8(&mut self, name: &str, v: &[i64]) {
        let a: ArrayRef = if self.alt {
            Arc::new(arrow_array::Int32Array::from_iter_values(v.iter().map(|&x| x as i32)))
        } else {
            Arc::new(arrow_array::Int8Array::from_iter_values(v.iter().map(|&x| x as i8)))
        };
        self.push(name, a);
    }

    /// An enum: int8, or its name in the alternate types.
    pub fn enum8(&mut self, name: &str, v: &[i64], names: &[&str]) {
        if self.alt {
            let s: Vec<String> =
                v.iter().map(|&x| names.get(x as usize - 1).copied().unwrap_or("UNKNOWN").to_owned()).collect();
            self.string(name, &s);
        } else {
            self.int8(name, v);
        }
    }

    /// A double column (float in the alternate types).
    pub fn double(&mut self, name: &str, v: &[f64]) {
        let a: ArrayRef = if self.alt {
            Arc::new(arrow_array::Float32Array::from_iter_values(v.iter().map(|&x| x as f32)))
        } else {
            Arc::new(arrow_array::Float64Array::from(v.to_vec()))
        };
        self.push(name, a);
    }

    pub fn int32(&mut self, name: &str, v: &[i64]) {
        self.push(name, Arc::new(arrow_array::Int32Array::from_iter_values(v.iter().map(|&x| x as i32))));
    }

    pub fn binary(&mut self, name: &str, v: &[Vec<u8>]) {
        self.push(name, Arc::new(BinaryArray::from_iter_values(v)));
    }

    /// `fixed_size_list<double>[n]` (a plain list in the alternate types). Transforms stay double.
    pub fn fixed_f64(&mut self, name: &str, v: &[Vec<f64>], n: i32) {
        let a: ArrayRef = if self.alt {
            let mut b = ListBuilder::new(Float64Builder::new());
            for row in v {
                b.values().append_slice(row);
                b.append(true);
            }
            Arc::new(b.finish())
        } else {
            let mut b = FixedSizeListBuilder::new(Float64Builder::new(), n);
            for row in v {
                b.values().append_slice(row);
                b.append(true);
            }
            Arc::new(b.finish())
        };
        self.push(name, a);
    }

    /// `fixed_size_list<int32>[n]` (a list of int64 in the alternate types).
    pub fn fixed_i32(&mut self, name: &str, v: &[Vec<i64>], n: i32) {
        let a: ArrayRef = if self.alt {
            let mut b = ListBuilder::new(Int64Builder::new());
            for row in v {
                b.values().append_slice(row);
                b.append(true);
            }
            Arc::new(b.finish())
        } else {
            let mut b = FixedSizeListBuilder::new(Int32Builder::new(), n);
            for row in v {
                b.values().extend(row.iter().map(|&x| Some(x as i32)));
                b.append(true);
            }
            Arc::new(b.finish())
        };
        self.push(name, a);
    }

    /// `list<float>` (double in the alternate types).
    pub fn list_f32(&mut self, name: &str, v: &[Vec<f32>]) {
        let a: ArrayRef = if self.alt {
            let mut b = ListBuilder::new(Float64Builder::new());
            for row in v {
                b.values().extend(row.iter().map(|&x| Some(x as f64)));
                b.append(true);
            }
            Arc::new(b.finish())
        } else {
            let mut b = ListBuilder::new(Float32Builder::new());
            for row in v {
                b.values().append_slice(row);
                b.append(true);
            }
            Arc::new(b.finish())
        };
        self.push(name, a);
    }

    /// `list<double>` (float in the alternate types).
    pub fn list_f64(&mut self, name: &str, v: &[Vec<f64>]) {
        let a: ArrayRef = if self.alt {
            let mut b = ListBuilder::new(Float32Builder::new());
            for row in v {
                b.values().extend(row.iter().map(|&x| Some(x as f32)));
                b.append(true);
            }
            Arc::new(b.finish())
        } else {
            let mut b = ListBuilder::new(Float64Builder::new());
            for row in v {
                b.values().append_slice(row);
                b.append(true);
            }
            Arc::new(b.finish())
        };
        self.push(name, a);
    }

    /// `list<int8>` (int32 in the alternate types).
    pub fn list_i8(&mut self, name: &str, v: &[Vec<i64>]) {
        let a: ArrayRef = if self.alt {
            let mut b = ListBuilder::new(Int32Builder::new());
            for row in v {
                b.values().extend(row.iter().map(|&x| Some(x as i32)));
                b.append(true);
            }
            Arc::new(b.finish())
        } else {
            let mut b = ListBuilder::new(Int8Builder::new());
            for row in v {
                b.values().extend(row.iter().map(|&x| Some(x as i8)));
                b.append(true);
            }
            Arc::new(b.finish())
        };
        self.push(name, a);
    }

    pub fn list_bool(&mut self, name: &str, v: &[Vec<bool>]) {
        let mut b = ListBuilder::new(BooleanBuilder::new());
        for row in v {
            b.values().extend(row.iter().map(|&x| Some(x)));
            b.append(true);
        }
        self.push(name, Arc::new(b.finish()));
    }

    pub fn finish(self) -> crate::error::Result<RecordBatch> {
        Ok(RecordBatch::try_from_iter(self.cols)?)
    }
}

/// Writes one component's file; each `write` becomes one row group (snappy pages).
pub struct ComponentWriter {
    path: PathBuf,
    writer: Option<ArrowWriter<File>>,
}

impl ComponentWriter {
    pub fn new(root: &Path, component: &str, segment: &str) -> crate::error::Result<ComponentWriter> {
        let path = component_path(root, component, segment);
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        Ok(ComponentWriter { path, writer: None })
    }

    pub fn write(&mut self, batch: &RecordBatch) -> crate::error::Result<()> {
        if self.writer.is_none() {
            let file = File::create(&self.path).with_context(|| format!("creating {}", self.path.display()))?;
            let props = WriterProperties::builder().set_compression(Compression::SNAPPY).build();
            self.writer = Some(ArrowWriter::try_new(file, batch.schema(), Some(props))?);
        }
        let w = self.writer.as_mut().ok_or_else(|| invalid!("writer"))?;
        if batch.num_rows() == 0 {
            return Ok(());
        }
        w.write(batch).with_context(|| format!("writing {}", self.path.display()))?;
        w.flush()?;
        Ok(())
    }

    pub fn finish(self) -> crate::error::Result<()> {
        match self.writer {
            Some(w) => {
                w.close().with_context(|| format!("closing {}", self.path.display()))?;
            }
            None => bail!("{}: nothing written", self.path.display()),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_every_codec_and_names_what_is_missing() {
        let dir = tempfile::tempdir().unwrap();
        for (i, codec) in [
            Compression::UNCOMPRESSED,
            Compression::SNAPPY,
            Compression::ZSTD(Default::default()),
            Compression::GZIP(Default::default()),
            Compression::LZ4_RAW,
        ]
        .into_iter()
        .enumerate()
        {
            let mut c = Columns::new(i % 2 == 1);
            c.enum8("key.camera_name", &[1, 5], &super::super::schema::CAMERA_NAMES);
            c.list_i8("types", &[vec![1, 19], vec![]]);
            c.double("x", &[0.5, -2.0]);
            let batch = c.finish().unwrap();
            let path = dir.path().join(format!("{i}.parquet"));
            let props = WriterProperties::builder().set_compression(codec).build();
            let mut w = ArrowWriter::try_new(File::create(&path).unwrap(), batch.schema(), Some(props)).unwrap();
            w.write(&batch).unwrap();
            w.close().unwrap();
            let t = read_columns(&path, "camera_box", &["key.camera_name", "types", "x"], None).unwrap();
            assert_eq!(
                t.enums("key.camera_name", &super::super::schema::CAMERA_NAMES).unwrap(),
                vec![1, 5],
                "{codec:?}"
            );
            assert_eq!(t.i64_lists("types").unwrap(), vec![vec![1, 19], vec![]]);
            assert_eq!(t.f64s("x").unwrap(), vec![0.5, -2.0]);
            let err = read_columns(&path, "camera_box", &["y"], None).err().unwrap().to_string();
            assert!(err.contains("camera_box") && err.contains("`y`"), "{err}");
            let err = t.strings("x").err().unwrap().to_string();
            assert!(err.contains("`x`") && err.contains("not a string"), "{err}");
        }
    }
}
