//! Writing an MCAP log: zstd chunks with message indexes and a summary, so viewers seek in it;
//! written under a temporary name and renamed when complete, so a log that exists is whole.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use crate::error::Context;

use super::msgs::ros2msg;

/// Chunks of about this many bytes before compression (the `mcap` CLI's default is 4 MiB).
const CHUNK_BYTES: u64 = 4 << 20;

/// An MCAP log being written.
pub struct LogWriter {
    writer: mcap::Writer<BufWriter<File>>,
    channels: HashMap<String, u16>,
    sequence: u32,
    partial: PathBuf,
    dest: PathBuf,
}

/// The temporary name of a log being written.
pub fn partial_path(dest: &Path) -> PathBuf {
    let name = dest.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    dest.with_file_name(format!(".{name}.partial"))
}

impl LogWriter {
    pub fn create(dest: &Path, profile: &str) -> crate::error::Result<LogWriter> {
        let partial = partial_path(dest);
        if let Some(dir) = dest.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let file = File::create(&partial).with_context(|| format!("creating {}", partial.display()))?;
        let writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(CHUNK_BYTES))
            .profile(profile)
            .library(concat!("posefuse/", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))?;
        Ok(LogWriter { writer, channels: HashMap::new(), sequence: 0, partial, dest: dest.to_owned() })
    }

    /// The channel of a topic, made on first use with its schema.
    pub fn channel(
        &mut self,
        topic: &str,
        schema: (&str, &str, &[u8]),
        message_encoding: &str,
    ) -> crate::error::Result<u16> {
        if let Some(id) = self.channels.get(topic) {
            return Ok(*id);
        }
        let (name, encoding, data) = schema;
        let schema_id = self.writer.add_schema(name, encoding, data)?;
        let id = self.writer.add_channel(schema_id, topic, message_encoding, &BTreeMap::new())?;
        self.channels.insert(topic.to_owned(), id);
        Ok(id)
    }

    /// A ROS 2 message (CDR) on `topic`, logged at `time_ns`.
    pub fn ros(&mut self, topic: &str, schema_name: &str, time_ns: i64, data: &[u8]) -> crate::error::Result<()> {
        let definition = ros2msg(schema_name).ok_or_else(|| crate::invalid!("no definition of {schema_name}"))?;
        let id = self.channel(topic, (schema_name, "ros2msg", definition.as_bytes()), "cdr")?;
        self.write(id, time_ns, data)
    }

    /// A Foxglove schema's message (protobuf) on `topic`.
    pub fn foxglove<T: foxglove::Encode>(&mut self, topic: &str, time_ns: i64, msg: &T) -> crate::error::Result<()> {
        let schema = T::get_schema().ok_or_else(|| crate::invalid!("{topic}: a message without a schema"))?;
        let id = self.channel(topic, (&schema.name, &schema.encoding, &schema.data), &T::get_message_encoding())?;
        let mut buf = Vec::with_capacity(msg.encoded_len().unwrap_or(1024));
        msg.encode(&mut buf).map_err(|e| crate::invalid!("{topic}: {e}"))?;
        self.write(id, time_ns, &buf)
    }

    pub fn write(&mut self, channel: u16, time_ns: i64, data: &[u8]) -> crate::error::Result<()> {
        let t = time_ns.max(0) as u64;
        self.sequence = self.sequence.wrapping_add(1);
        let header =
            mcap::records::MessageHeader { channel_id: channel, sequence: self.sequence, log_time: t, publish_time: t };
        Ok(self.writer.write_to_known_channel(&header, data)?)
    }

    /// Writes the summary and gives the log its name.
    pub fn finish(mut self) -> crate::error::Result<PathBuf> {
        self.writer.finish()?;
        let file = self.writer.into_inner().into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&self.partial, &self.dest)
            .with_context(|| format!("renaming {} to {}", self.partial.display(), self.dest.display()))?;
        Ok(self.dest)
    }
}
