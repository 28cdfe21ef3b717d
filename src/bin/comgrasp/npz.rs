//! A minimal NPZ writer: `.npy` arrays in an uncompressed ("stored") zip, which is what
//! `numpy.savez` writes and `numpy.load` reads. Written by hand (a CRC-32 and three zip
//! headers) instead of pulling in a zip crate with its compression back ends.
use std::io::{self, Write};

use crate::checksum::crc32;

/// One array: its `.npy` dtype descriptor (`<f4`, `<f8`, `|u1`), shape and raw
/// little-endian C-order data.
pub struct Array {
    pub name: String,
    pub descr: &'static str,
    pub shape: Vec<usize>,
    pub data: Vec<u8>,
}

impl Array {
    /// A float32 array from values in C order.
    pub fn f32(name: &str, shape: &[usize], values: impl IntoIterator<Item = f32>) -> Array {
        let data = values.into_iter().flat_map(f32::to_le_bytes).collect();
        Array { name: name.into(), descr: "<f4", shape: shape.to_vec(), data }
    }

    /// A uint8 array from values in C order.
    pub fn u8(name: &str, shape: &[usize], values: impl IntoIterator<Item = u8>) -> Array {
        Array { name: name.into(), descr: "|u1", shape: shape.to_vec(), data: values.into_iter().collect() }
    }

    /// A 0-d float64 array (a scalar, e.g. `fps`).
    pub fn scalar_f64(name: &str, v: f64) -> Array {
        Array { name: name.into(), descr: "<f8", shape: Vec::new(), data: v.to_le_bytes().to_vec() }
    }

    /// The array as a `.npy` file (format 1.0, header padded to a multiple of 64 bytes).
    pub fn to_npy(&self) -> Vec<u8> {
        comgrasp::bundle::npy::encode(self.descr, &self.shape, &self.data)
    }
}

/// Writes the arrays as `NAME.npy` entries of a stored zip. Fails (instead of writing a
/// broken file) if anything exceeds the 4 GiB / 65535-entry limits of a zip without ZIP64.
pub fn write(mut w: impl Write, arrays: &[Array]) -> io::Result<()> {
    let too_big = || io::Error::new(io::ErrorKind::InvalidInput, "motion too large for an NPZ without ZIP64");
    let mut central = Vec::new();
    let mut offset = 0u64;
    for a in arrays {
        let name = format!("{}.npy", a.name);
        let data = a.to_npy();
        let size = u32::try_from(data.len()).map_err(|_| too_big())?;
        let at = u32::try_from(offset).map_err(|_| too_big())?;
        let crc = crc32(&data);
        // Local file header, then the data.
        let mut h = Vec::with_capacity(30 + name.len());
        put32(&mut h, 0x0403_4b50);
        entry_fields(&mut h, crc, size, name.len());
        h.extend_from_slice(name.as_bytes());
        w.write_all(&h)?;
        w.write_all(&data)?;
        offset += (h.len() + data.len()) as u64;
        // Its central directory record, written after all entries.
        put32(&mut central, 0x0201_4b50);
        put16(&mut central, 20); // version made by: 2.0
        entry_fields(&mut central, crc, size, name.len());
        put16(&mut central, 0); // comment length
        put16(&mut central, 0); // disk number
        put16(&mut central, 0); // internal attributes
        put32(&mut central, 0); // external attributes
        put32(&mut central, at);
        central.extend_from_slice(name.as_bytes());
    }
    let count = u16::try_from(arrays.len()).map_err(|_| too_big())?;
    let cd_size = u32::try_from(central.len()).map_err(|_| too_big())?;
    let cd_at = u32::try_from(offset).map_err(|_| too_big())?;
    w.write_all(&central)?;
    let mut end = Vec::with_capacity(22);
    put32(&mut end, 0x0605_4b50);
    put16(&mut end, 0); // this disk
    put16(&mut end, 0); // disk with the central directory
    put16(&mut end, count);
    put16(&mut end, count);
    put32(&mut end, cd_size);
    put32(&mut end, cd_at);
    put16(&mut end, 0); // comment length
    w.write_all(&end)
}

/// The fields local and central headers share, from "version needed" to "extra length".
fn entry_fields(out: &mut Vec<u8>, crc: u32, size: u32, name_len: usize) {
    put16(out, 20); // version needed: 2.0
    put16(out, 0); // flags
    put16(out, 0); // method: stored
    put16(out, 0); // time 00:00:00
    put16(out, (1 << 5) | 1); // date 1980-01-01 (fixed, so output is reproducible)
    put32(out, crc);
    put32(out, size); // compressed
    put32(out, size); // uncompressed
    put16(out, name_len as u16);
    put16(out, 0); // extra length
}

fn put16(out: &mut Vec<u8>, v: u16) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_aligned() {
        for shape in [vec![], vec![7], vec![7, 21, 4]] {
            let n: usize = shape.iter().product();
            let npy = Array::f32("a", &shape, vec![0.0; n]).to_npy();
            let hlen = u16::from_le_bytes([npy[8], npy[9]]) as usize;
            assert_eq!((10 + hlen) % 64, 0);
            assert_eq!(npy[10 + hlen - 1], b'\n');
            assert_eq!(npy.len(), 10 + hlen + 4 * n);
        }
    }
}
