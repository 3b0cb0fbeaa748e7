//! ROS 2's wire format (OMG CDR, XCDR1 as rmw's Fast-CDR writes it): a 4-byte encapsulation
//! header, then fields aligned to their size relative to the end of the header. Every length
//! read is checked against the bytes left before anything is allocated, so a malformed message
//! costs at most its own size.

use std::fmt;

/// What is wrong with a message's bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CdrError(pub String);

impl fmt::Display for CdrError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CdrError {}

pub type CdrResult<T> = std::result::Result<T, CdrError>;

fn err<T>(what: impl Into<String>) -> CdrResult<T> {
    Err(CdrError(what.into()))
}

/// Reads one CDR message.
pub struct CdrReader<'a> {
    body: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Checks the encapsulation header: plain CDR, either byte order.
    pub fn new(data: &'a [u8]) -> CdrResult<CdrReader<'a>> {
        if data.len() < 4 {
            return err(format!("{} bytes: shorter than the CDR header", data.len()));
        }
        let big_endian = match (data[0], data[1]) {
            (0, 0) => true,
            (0, 1) => false,
            (a, b) => return err(format!("encapsulation {a:#04x}{b:02x} is not plain CDR (ROS 2's default)")),
        };
        Ok(CdrReader { body: &data[4..], pos: 0, big_endian })
    }

    fn align(&mut self, n: usize) -> CdrResult<()> {
        let pad = (n - self.pos % n) % n;
        self.take(pad).map(|_| ())
    }

    fn take(&mut self, n: usize) -> CdrResult<&'a [u8]> {
        let left = self.body.len() - self.pos;
        if n > left {
            return err(format!("needs {n} more bytes at offset {}, {left} left", self.pos + 4));
        }
        let s = &self.body[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn fixed<const N: usize>(&mut self) -> CdrResult<[u8; N]> {
        self.align(N)?;
        let mut b = [0u8; N];
        b.copy_from_slice(self.take(N)?);
        if self.big_endian {
            b.reverse();
        }
        Ok(b)
    }

    pub fn u8(&mut self) -> CdrResult<u8> {
        Ok(self.take(1)?[0])
    }

    pub fn bool(&mut self) -> CdrResult<bool> {
        Ok(self.u8()? != 0)
    }

    pub fn u32(&mut self) -> CdrResult<u32> {
        Ok(u32::from_le_bytes(self.fixed()?))
    }

    pub fn i32(&mut self) -> CdrResult<i32> {
        Ok(i32::from_le_bytes(self.fixed()?))
    }

    pub fn f64(&mut self) -> CdrResult<f64> {
        Ok(f64::from_le_bytes(self.fixed()?))
    }

    /// A sequence's length, checked against the bytes left (each element takes at least
    /// `min_element_bytes`).
    pub fn len(&mut self, min_element_bytes: usize) -> CdrResult<usize> {
        let n = self.u32()? as usize;
        let left = self.body.len() - self.pos;
        if n.saturating_mul(min_element_bytes.max(1)) > left {
            return err(format!("a sequence of {n} elements at offset {}: only {left} bytes left", self.pos));
        }
        Ok(n)
    }

    /// `uint8[]`, borrowed.
    pub fn bytes(&mut self) -> CdrResult<&'a [u8]> {
        let n = self.len(1)?;
        self.take(n)
    }

    /// `string`: length with its terminating NUL.
    pub fn string(&mut self) -> CdrResult<String> {
        let raw = self.bytes()?;
        let text = match raw.split_last() {
            Some((0, text)) => text,
            Some(_) => return err("a string without its terminating NUL"),
            None => &[][..],
        };
        String::from_utf8(text.to_vec()).map_err(|_| CdrError("a string that is not UTF-8".into()))
    }

    pub fn f64s<const N: usize>(&mut self) -> CdrResult<[f64; N]> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64()?;
        }
        Ok(out)
    }

    /// `float64[]`.
    pub fn f64_seq(&mut self) -> CdrResult<Vec<f64>> {
        let n = self.len(8)?;
        (0..n).map(|_| self.f64()).collect()
    }
}

/// Writes one little-endian CDR message.
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        CdrWriter { buf: vec![0, 1, 0, 0] }
    }
}

impl CdrWriter {
    fn align(&mut self, n: usize) {
        while !(self.buf.len() - 4).is_multiple_of(n) {
            self.buf.push(0);
        }
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub fn bool(&mut self, v: bool) {
        self.buf.push(u8::from(v));
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64s(&mut self, v: &[f64]) {
        for x in v {
            self.f64(*x);
        }
    }

    pub fn f64_seq(&mut self, v: &[f64]) {
        self.u32(v.len() as u32);
        self.f64s(v);
    }

    pub fn bytes(&mut self, v: &[u8]) {
        self.u32(v.len() as u32);
        self.buf.extend_from_slice(v);
    }

    pub fn string(&mut self, v: &str) {
        self.u32(v.len() as u32 + 1);
        self.buf.extend_from_slice(v.as_bytes());
        self.buf.push(0);
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_align_to_their_size_after_the_header() {
        let mut w = CdrWriter::default();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.u32(9);
        let b = w.finish();
        // header, u8, 7 pad, f64, len 3, "ab\0", 1 pad, u32
        assert_eq!(b.len(), 4 + 1 + 7 + 8 + 4 + 3 + 1 + 4);
        assert_eq!(&b[4..6], &[7, 0]);
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.f64().unwrap(), 1.5);
        assert_eq!(r.string().unwrap(), "ab");
        assert_eq!(r.u32().unwrap(), 9);
        assert!(r.u8().is_err());
    }

    #[test]
    fn big_endian_messages_read_the_same() {
        // header CDR_BE, u32 258, f64 -2.0 (after 4 bytes of padding)
        let mut b = vec![0, 0, 0, 0, 0, 0, 1, 2, 0, 0, 0, 0];
        b.extend_from_slice(&(-2.0f64).to_be_bytes());
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.u32().unwrap(), 258);
        assert_eq!(r.f64().unwrap(), -2.0);
    }

    #[test]
    fn lengths_beyond_the_message_are_refused_before_allocating() {
        let mut w = CdrWriter::default();
        w.u32(u32::MAX);
        let b = w.finish();
        assert!(CdrReader::new(&b).unwrap().bytes().unwrap_err().0.contains("only 0 bytes left"));
        assert!(CdrReader::new(&b).unwrap().f64_seq().is_err());
        let mut w = CdrWriter::default();
        w.u32(3);
        w.u8(1);
        w.u8(2);
        w.u8(3);
        assert_eq!(CdrReader::new(&w.finish()).unwrap().bytes().unwrap(), &[1, 2, 3]);
    }

    #[test]
    fn strings_need_their_nul_and_utf8() {
        let mut w = CdrWriter::default();
        w.bytes(b"ab");
        assert!(CdrReader::new(&w.finish()).unwrap().string().is_err());
        let mut w = CdrWriter::default();
        w.bytes(&[0xff, 0]);
        assert!(CdrReader::new(&w.finish()).unwrap().string().is_err());
        let mut w = CdrWriter::default();
        w.u32(0);
        assert_eq!(CdrReader::new(&w.finish()).unwrap().string().unwrap(), "");
    }

    #[test]
    fn other_encapsulations_are_named() {
        assert!(CdrReader::new(&[0, 1]).is_err());
        let e = CdrReader::new(&[0, 7, 0, 0]).err().unwrap();
        assert!(e.0.contains("not plain CDR"), "{e}");
        assert!(CdrReader::new(&[0, 0, 0, 0]).is_ok());
    }
}
