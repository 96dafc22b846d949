//! `FieldReader`: reads the little-endian fields of a stored record (a hierarchy, a store's
//! regions), failing on a short record instead of panicking.

use super::error::LodError;

pub(super) struct FieldReader<'a> {
    bytes: &'a [u8],
    at: usize,
    /// The error's text when a field runs past the end, naming the record.
    truncated: &'static str,
}

impl<'a> FieldReader<'a> {
    pub(super) fn new(bytes: &'a [u8], truncated: &'static str) -> Self {
        Self {
            bytes,
            at: 0,
            truncated,
        }
    }

    /// Whether every byte has been read.
    pub(super) fn at_end(&self) -> bool {
        self.at == self.bytes.len()
    }

    /// Runs a decoder that reads from the whole record at the current position and moves it on.
    pub(super) fn decode_with<T>(&mut self, decode: impl FnOnce(&'a [u8], &mut usize) -> T) -> T {
        decode(self.bytes, &mut self.at)
    }

    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], LodError> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len());
        let end = end.ok_or_else(|| LodError::CorruptHierarchy(self.truncated.into()))?;
        let slice = &self.bytes[self.at..end];
        self.at = end;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], LodError> {
        let mut out = [0; N];
        out.copy_from_slice(self.take(N)?);
        Ok(out)
    }

    pub(super) fn u8(&mut self) -> Result<u8, LodError> {
        Ok(self.array::<1>()?[0])
    }

    pub(super) fn u16(&mut self) -> Result<u16, LodError> {
        self.array().map(u16::from_le_bytes)
    }

    pub(super) fn u32(&mut self) -> Result<u32, LodError> {
        self.array().map(u32::from_le_bytes)
    }

    pub(super) fn u64(&mut self) -> Result<u64, LodError> {
        self.array().map(u64::from_le_bytes)
    }

    pub(super) fn f64(&mut self) -> Result<f64, LodError> {
        self.array().map(f64::from_le_bytes)
    }
}
