//! NPZ output: `.npy` arrays in an uncompressed ("stored") zip, which is what `numpy.savez`
//! writes and `numpy.load` reads (the `zip` crate writes the container).
use std::io::{self, Seek, Write};

use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, DateTime, ZipWriter};

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

/// Writes the arrays as `NAME.npy` entries of a stored zip, every entry dated 1980-01-01 so
/// the same motion gives the same bytes. Fails (instead of writing a broken file) if anything
/// exceeds the 4 GiB limit of a zip without ZIP64.
pub fn write(w: impl Write + Seek, arrays: &[Array]) -> io::Result<()> {
    let mut zip = ZipWriter::new(w);
    let options = SimpleFileOptions::default()
        .compression_method(CompressionMethod::Stored)
        .last_modified_time(DateTime::default())
        .large_file(false);
    for a in arrays {
        zip.start_file(format!("{}.npy", a.name), options).map_err(io::Error::other)?;
        zip.write_all(&a.to_npy())?;
    }
    zip.finish().map_err(io::Error::other)?;
    Ok(())
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

    #[test]
    fn entries_are_stored_npy_files_and_reproducible() {
        let arrays = [Array::f32("a", &[2, 3], (0..6).map(|i| i as f32)), Array::scalar_f64("fps", 30.0)];
        let mut bytes = io::Cursor::new(Vec::new());
        write(&mut bytes, &arrays).unwrap();
        let mut again = io::Cursor::new(Vec::new());
        write(&mut again, &arrays).unwrap();
        assert_eq!(bytes.get_ref(), again.get_ref(), "same arrays, same bytes");
        let mut zip = zip::ZipArchive::new(io::Cursor::new(bytes.into_inner())).unwrap();
        assert_eq!(zip.len(), 2);
        for a in &arrays {
            let mut f = zip.by_name(&format!("{}.npy", a.name)).unwrap();
            assert_eq!(f.compression(), CompressionMethod::Stored);
            let mut data = Vec::new();
            io::Read::read_to_end(&mut f, &mut data).unwrap();
            assert_eq!(data, a.to_npy());
        }
    }
}
