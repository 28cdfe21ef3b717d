//! A minimal `.npy` reader for the bundle's parity vectors (`parity/**/*.npy`).
//!
//! Only what `numpy.save` writes for the parity files is supported: format versions 1-3,
//! C order, little-endian `f4`/`f8`/`i4`/`i8`/`u8` (plus `|u1`/`|i1`/`|b1` single bytes).
//! Anything else is an error, never a panic: the files come from disk.
use std::io::Read;
use std::path::Path;

use crate::error::{Error, Result};

/// Element type of an array.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NpyDtype {
    F32,
    F64,
    I32,
    I64,
    U64,
    U8,
    I8,
    Bool,
}

impl NpyDtype {
    /// numpy's name (`str(array.dtype)`), as parity/index.json records it.
    pub fn numpy_name(self) -> &'static str {
        match self {
            NpyDtype::F32 => "float32",
            NpyDtype::F64 => "float64",
            NpyDtype::I32 => "int32",
            NpyDtype::I64 => "int64",
            NpyDtype::U64 => "uint64",
            NpyDtype::U8 => "uint8",
            NpyDtype::I8 => "int8",
            NpyDtype::Bool => "bool",
        }
    }

    fn size(self) -> usize {
        match self {
            NpyDtype::F64 | NpyDtype::I64 | NpyDtype::U64 => 8,
            NpyDtype::F32 | NpyDtype::I32 => 4,
            NpyDtype::U8 | NpyDtype::I8 | NpyDtype::Bool => 1,
        }
    }

    fn from_descr(descr: &str) -> Option<Self> {
        Some(match descr {
            "<f4" => NpyDtype::F32,
            "<f8" => NpyDtype::F64,
            "<i4" => NpyDtype::I32,
            "<i8" => NpyDtype::I64,
            "<u8" => NpyDtype::U64,
            "|u1" => NpyDtype::U8,
            "|i1" => NpyDtype::I8,
            "|b1" => NpyDtype::Bool,
            _ => return None,
        })
    }
}

/// The header of a `.npy` file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NpyHeader {
    pub dtype: NpyDtype,
    pub shape: Vec<usize>,
    /// Byte offset of the data.
    pub data_offset: usize,
}

impl NpyHeader {
    /// Number of elements (1 for a 0-d array).
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A whole array: header plus the raw little-endian data.
#[derive(Clone, Debug)]
pub struct Npy {
    pub dtype: NpyDtype,
    pub shape: Vec<usize>,
    data: Vec<u8>,
}

fn err(path: &Path, msg: impl Into<String>) -> Error {
    Error::bundle(path, msg)
}

/// Parses the header at the start of `bytes` (`path` is only for messages).
pub fn parse_header(path: &Path, bytes: &[u8]) -> Result<NpyHeader> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(err(path, "not a .npy file (bad magic)"));
    }
    let major = bytes[6];
    let (len, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10usize),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(err(path, "truncated .npy header"));
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(err(path, format!("unsupported .npy format version {v}"))),
    };
    let end = start.checked_add(len).filter(|&e| e <= bytes.len()).ok_or_else(|| err(path, "truncated .npy header"))?;
    let text = std::str::from_utf8(&bytes[start..end]).map_err(|_| err(path, "non-UTF-8 .npy header"))?;
    let descr = dict_value(text, "descr").ok_or_else(|| err(path, format!("no 'descr' in .npy header {text:?}")))?;
    let descr = descr.trim().trim_matches(|c| c == '\'' || c == '"');
    let dtype = NpyDtype::from_descr(descr)
        .ok_or_else(|| err(path, format!("unsupported .npy dtype {descr:?} (need little-endian f4/f8/i4/i8/u8)")))?;
    let fortran = dict_value(text, "fortran_order").ok_or_else(|| err(path, "no 'fortran_order' in .npy header"))?;
    if fortran.trim() != "False" {
        return Err(err(path, "Fortran-order .npy arrays are not supported"));
    }
    let shape_text = dict_value(text, "shape").ok_or_else(|| err(path, "no 'shape' in .npy header"))?;
    let inner = shape_text
        .trim()
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .ok_or_else(|| err(path, format!("bad .npy shape {shape_text:?}")))?;
    let mut shape = Vec::new();
    for part in inner.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        shape.push(part.parse::<usize>().map_err(|_| err(path, format!("bad .npy shape {shape_text:?}")))?);
    }
    Ok(NpyHeader { dtype, shape, data_offset: end })
}

/// The raw text of `key`'s value in numpy's header dict (`{'descr': '<f4', 'fortran_order':
/// False, 'shape': (7, 4), }`): up to the next top-level comma.
fn dict_value<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    let pat_single = format!("'{key}'");
    let pat_double = format!("\"{key}\"");
    let at = text
        .find(&pat_single)
        .map(|i| i + pat_single.len())
        .or_else(|| text.find(&pat_double).map(|i| i + pat_double.len()))?;
    let rest = text[at..].trim_start().strip_prefix(':')?;
    let mut depth = 0i32;
    for (i, c) in rest.char_indices() {
        match c {
            '(' | '[' => depth += 1,
            ')' | ']' => depth -= 1,
            ',' | '}' if depth == 0 => return Some(&rest[..i]),
            _ => {}
        }
    }
    None
}

/// Reads only the header of the file at `path`.
pub fn read_header(path: &Path) -> Result<NpyHeader> {
    let mut f = std::fs::File::open(path).map_err(|e| err(path, format!("cannot open: {e}")))?;
    let mut buf = Vec::with_capacity(256);
    f.by_ref().take(65536 + 12).read_to_end(&mut buf).map_err(|e| err(path, format!("cannot read: {e}")))?;
    parse_header(path, &buf)
}

/// Reads the whole array at `path`.
pub fn read(path: &Path) -> Result<Npy> {
    let bytes = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    parse(path, bytes)
}

/// Parses a whole `.npy` file held in memory.
pub fn parse(path: &Path, mut bytes: Vec<u8>) -> Result<Npy> {
    let h = parse_header(path, &bytes)?;
    // Checked: the shape comes from the file (a product that overflows is no real array).
    let need = h
        .shape
        .iter()
        .try_fold(h.dtype.size(), |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| err(path, "absurd .npy shape"))?;
    let have = bytes.len() - h.data_offset;
    if have != need {
        return Err(err(path, format!("{:?} {:?} needs {need} data bytes, file has {have}", h.dtype, h.shape)));
    }
    bytes.drain(..h.data_offset);
    Ok(Npy { dtype: h.dtype, shape: h.shape, data: bytes })
}

macro_rules! chunks {
    ($data:expr, $t:ty, $n:expr) => {
        $data.chunks_exact($n).map(|c| <$t>::from_le_bytes(c.try_into().unwrap_or([0; $n])))
    };
}

impl Npy {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values as f64 (exact for every supported dtype but 64-bit integers above 2^53).
    pub fn to_f64(&self) -> Vec<f64> {
        match self.dtype {
            NpyDtype::F32 => chunks!(self.data, f32, 4).map(f64::from).collect(),
            NpyDtype::F64 => chunks!(self.data, f64, 8).collect(),
            NpyDtype::I32 => chunks!(self.data, i32, 4).map(f64::from).collect(),
            NpyDtype::I64 => chunks!(self.data, i64, 8).map(|v| v as f64).collect(),
            NpyDtype::U64 => chunks!(self.data, u64, 8).map(|v| v as f64).collect(),
            NpyDtype::U8 | NpyDtype::Bool => self.data.iter().map(|&v| f64::from(v)).collect(),
            NpyDtype::I8 => self.data.iter().map(|&v| f64::from(v as i8)).collect(),
        }
    }

    /// The values as f32 (float arrays only; f64 is rounded).
    pub fn to_f32(&self, path: &Path) -> Result<Vec<f32>> {
        match self.dtype {
            NpyDtype::F32 => Ok(chunks!(self.data, f32, 4).collect()),
            NpyDtype::F64 => Ok(chunks!(self.data, f64, 8).map(|v| v as f32).collect()),
            d => Err(err(path, format!("expected a float array, got {}", d.numpy_name()))),
        }
    }

    /// The values as i64 (integer arrays only; u64 above i64::MAX is an error).
    pub fn to_i64(&self, path: &Path) -> Result<Vec<i64>> {
        match self.dtype {
            NpyDtype::I64 => Ok(chunks!(self.data, i64, 8).collect()),
            NpyDtype::I32 => Ok(chunks!(self.data, i32, 4).map(i64::from).collect()),
            NpyDtype::U8 => Ok(self.data.iter().map(|&v| i64::from(v)).collect()),
            NpyDtype::I8 => Ok(self.data.iter().map(|&v| i64::from(v as i8)).collect()),
            NpyDtype::U64 => chunks!(self.data, u64, 8)
                .map(|v| i64::try_from(v).map_err(|_| err(path, format!("uint64 value {v} exceeds i64"))))
                .collect(),
            d => Err(err(path, format!("expected an integer array, got {}", d.numpy_name()))),
        }
    }

    /// The values as i8 (int8 arrays only).
    pub fn to_i8(&self, path: &Path) -> Result<Vec<i8>> {
        match self.dtype {
            NpyDtype::I8 => Ok(self.data.iter().map(|&v| v as i8).collect()),
            d => Err(err(path, format!("expected an int8 array, got {}", d.numpy_name()))),
        }
    }

    /// The values as u8 (uint8 arrays only), e.g. packed int4 weights.
    pub fn into_u8(self, path: &Path) -> Result<Vec<u8>> {
        match self.dtype {
            NpyDtype::U8 => Ok(self.data),
            d => Err(err(path, format!("expected a uint8 array, got {}", d.numpy_name()))),
        }
    }

    /// The values as u64 (uint64 arrays only).
    pub fn to_u64(&self, path: &Path) -> Result<Vec<u64>> {
        match self.dtype {
            NpyDtype::U64 => Ok(chunks!(self.data, u64, 8).collect()),
            d => Err(err(path, format!("expected a uint64 array, got {}", d.numpy_name()))),
        }
    }
}

/// `data` (raw little-endian, C order) as a `.npy` file of format 1.0 with the dtype
/// descriptor `descr` (`<f4`, `<f8`, `|i1`, `|u1`, ...) and `shape`; the header is padded so
/// the data starts at a multiple of 64 bytes. What `numpy.save` writes and [`parse`] reads.
pub fn encode(descr: &str, shape: &[usize], data: &[u8]) -> Vec<u8> {
    let shape = match shape {
        [] => "()".to_string(),
        [n] => format!("({n},)"),
        dims => format!("({})", dims.iter().map(usize::to_string).collect::<Vec<_>>().join(", ")),
    };
    with_header(descr, &shape, data)
}

fn with_header(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    // magic (6) + version (2) + header length (2) + header, ending in '\n'.
    let unpadded = 10 + header.len() + 1;
    header.extend(std::iter::repeat_n(' ', unpadded.next_multiple_of(64) - unpadded));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    // the shape as header text, so tests can also write malformed ones
    fn file(descr: &str, shape: &str, data: &[u8]) -> Vec<u8> {
        with_header(descr, shape, data)
    }

    #[test]
    fn reads_f32_and_i64() {
        let p = Path::new("x.npy");
        let data: Vec<u8> = [1.5f32, -2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = parse(p, file("<f4", "(1, 2)", &data)).unwrap();
        assert_eq!(a.shape, vec![1, 2]);
        assert_eq!(a.to_f32(p).unwrap(), vec![1.5, -2.0]);
        let data: Vec<u8> = [7i64].iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = parse(p, file("<i8", "(1,)", &data)).unwrap();
        assert_eq!(a.to_i64(p).unwrap(), vec![7]);
        let a = parse(p, file("<f8", "()", &2.0f64.to_le_bytes())).unwrap();
        assert_eq!(a.shape, Vec::<usize>::new());
        assert_eq!(a.to_f64(), vec![2.0]);
    }

    #[test]
    fn rejects_bad_files() {
        let p = Path::new("x.npy");
        assert!(parse(p, b"garbage".to_vec()).is_err());
        assert!(parse(p, file(">f4", "(1,)", &[0; 4])).is_err());
        assert!(parse(p, file("<f4", "(2,)", &[0; 4])).is_err());
        assert!(parse(p, file("<f4", "(a,)", &[0; 4])).is_err());
        let mut f = file("<f4", "(1,)", &[0; 4]);
        f.truncate(12);
        assert!(parse(p, f).is_err());
    }
}
