//! Loading the native path's tensors: `<dir>/<name>.npy` per tensor, as listed in a
//! manifest's `native` section (names are the PyTorch `state_dict` keys). A tensor stored as
//! int8 has a float32 scale per row (first axis) in `<dir>/<name>.scale.npy`, and stands for
//! `q * scale` exactly as the ONNX graph's `Cast * Mul` rebuilds it.
//!
//! Every file is checked against the manifest (dtype, shape) and for finite values, so a
//! corrupt or mismatched file is a load-time `Error::Bundle`.
use crate::bundle::manifest::{NativeDtype, NativeSpec};
use crate::bundle::npy::{self, NpyDtype};
use crate::bundle::BundleSource;
use crate::error::{Error, Result};

/// A weight matrix `rows x cols`, row-major (a Linear's `(out, in)`, a Conv1d's
/// `(out, in * kernel)`): the layout a GEMV reads row by row.
#[derive(Clone, Debug)]
pub(crate) enum Matrix {
    F32 {
        rows: usize,
        cols: usize,
        w: Vec<f32>,
    },
    /// `w[r][c] = q[r * cols + c] as f32 * scale[r]`.
    I8 {
        rows: usize,
        cols: usize,
        q: Vec<i8>,
        scale: Vec<f32>,
    },
}

impl Matrix {
    pub(crate) fn rows(&self) -> usize {
        match self {
            Matrix::F32 { rows, .. } | Matrix::I8 { rows, .. } => *rows,
        }
    }

    pub(crate) fn cols(&self) -> usize {
        match self {
            Matrix::F32 { cols, .. } | Matrix::I8 { cols, .. } => *cols,
        }
    }

    /// Bytes the weights occupy (what one pass over the matrix reads).
    pub(crate) fn bytes(&self) -> usize {
        match self {
            Matrix::F32 { w, .. } => 4 * w.len(),
            Matrix::I8 { q, scale, .. } => q.len() + 4 * scale.len(),
        }
    }

    /// Row `r` as f32 (for the rare gather of one row, e.g. an embedding lookup).
    pub(crate) fn row_into(&self, r: usize, out: &mut [f32]) {
        match self {
            Matrix::F32 { cols, w, .. } => out.copy_from_slice(&w[r * cols..(r + 1) * cols]),
            Matrix::I8 { cols, q, scale, .. } => {
                for (o, &v) in out.iter_mut().zip(&q[r * cols..(r + 1) * cols]) {
                    *o = f32::from(v) * scale[r];
                }
            }
        }
    }
}

/// An embedding table read one row at a time: a [`Matrix`], or int4 rows kept packed (the
/// text encoder's word table: 30522 rows of which a prompt reads a few dozen).
#[derive(Clone, Debug)]
pub(crate) enum Table {
    Rows(Matrix),
    /// `w[r][c] = (nibble(r, c) - 8) * scale[r]`, nibbles packed as [`NativeDtype::Int4`] says.
    I4 {
        rows: usize,
        cols: usize,
        packed: Vec<u8>,
        scale: Vec<f32>,
    },
}

impl Table {
    pub(crate) fn rows(&self) -> usize {
        match self {
            Table::Rows(m) => m.rows(),
            Table::I4 { rows, .. } => *rows,
        }
    }

    /// Row `r` as f32 into `out` (`cols` long).
    pub(crate) fn row_into(&self, r: usize, out: &mut [f32]) {
        match self {
            Table::Rows(m) => m.row_into(r, out),
            Table::I4 { cols, packed, scale, .. } => {
                let stride = cols.div_ceil(2);
                let row = &packed[r * stride..(r + 1) * stride];
                for (c, o) in out.iter_mut().enumerate() {
                    let nibble = if c % 2 == 0 { row[c / 2] & 15 } else { row[c / 2] >> 4 };
                    *o = f32::from(i8::try_from(nibble).unwrap_or(8) - 8) * scale[r];
                }
            }
        }
    }
}

/// The tensors of one `native` section, read on demand.
pub(crate) struct Tensors<'a> {
    src: &'a BundleSource,
    spec: &'a NativeSpec,
}

impl<'a> Tensors<'a> {
    pub(crate) fn new(src: &'a BundleSource, spec: &'a NativeSpec) -> Self {
        Tensors { src, spec }
    }

    /// The declared shape of `name`, or a bundle error naming the missing tensor.
    pub(crate) fn shape(&self, name: &str) -> Result<&'a [usize]> {
        Ok(&self.entry(name)?.shape)
    }

    /// Every tensor name the section lists.
    pub(crate) fn names(&self) -> impl Iterator<Item = &'a str> {
        self.spec.tensors.keys().map(String::as_str)
    }

    fn entry(&self, name: &str) -> Result<&'a crate::bundle::manifest::NativeTensor> {
        self.spec.tensors.get(name).ok_or_else(|| {
            Error::bundle(self.src.path_of(&self.spec.dir), format!("native weights lack tensor {name}"))
        })
    }

    fn file(&self, name: &str, suffix: &str) -> String {
        format!("{}/{name}{suffix}.npy", self.spec.dir)
    }

    fn read(&self, rel: &str, dtype: NpyDtype, shape: &[usize]) -> Result<npy::Npy> {
        let path = self.src.path_of(rel);
        let a = npy::parse(&path, self.src.read_file(rel)?.into_owned())?;
        if a.dtype != dtype || a.shape != shape {
            return Err(Error::bundle(
                &path,
                format!(
                    "is {} {:?}, the manifest declares {} {:?}",
                    a.dtype.numpy_name(),
                    a.shape,
                    dtype.numpy_name(),
                    shape
                ),
            ));
        }
        Ok(a)
    }

    fn floats(&self, rel: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let path = self.src.path_of(rel);
        let v = self.read(rel, NpyDtype::F32, shape)?.to_f32(&path)?;
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::bundle(&path, format!("value {i} is not finite")));
        }
        Ok(v)
    }

    /// A float32 tensor of exactly `len` elements (any shape), e.g. a bias or a LayerNorm weight.
    pub(crate) fn vector(&self, name: &str, len: usize) -> Result<Vec<f32>> {
        let e = self.entry(name)?;
        let n: usize = e.shape.iter().product();
        if e.dtype != NativeDtype::Float32 || n != len {
            return Err(Error::bundle(
                self.src.path_of(&self.file(name, "")),
                format!("native tensor {name} is {:?} {:?}, expected float32 with {len} values", e.dtype, e.shape),
            ));
        }
        self.floats(&self.file(name, ""), &e.shape)
    }

    /// A tensor of shape `(rows, ...)` with `cols` = the product of the other axes, as a
    /// [`Matrix`] (float32 or int8 + scale, whichever the bundle stores).
    pub(crate) fn matrix(&self, name: &str, rows: usize, cols: usize) -> Result<Matrix> {
        match self.table(name, rows, cols)? {
            Table::Rows(m) => Ok(m),
            Table::I4 { .. } => Err(Error::bundle(
                self.src.path_of(&self.file(name, "")),
                format!("native tensor {name} is int4, which only embedding tables may be"),
            )),
        }
    }

    /// Like [`matrix`](Self::matrix), for a table read row by row: int4 is accepted too.
    pub(crate) fn table(&self, name: &str, rows: usize, cols: usize) -> Result<Table> {
        let e = self.entry(name)?;
        let rel = self.file(name, "");
        let path = self.src.path_of(&rel);
        let (r, c) = match e.shape.split_first() {
            Some((&r, rest)) => (r, rest.iter().product::<usize>()),
            None => (0, 0),
        };
        if (r, c) != (rows, cols) {
            return Err(Error::bundle(
                &path,
                format!("native tensor {name} has shape {:?}, expected {rows} rows of {cols}", e.shape),
            ));
        }
        let scale = || -> Result<Vec<f32>> {
            let scale = self.floats(&self.file(name, ".scale"), &[rows])?;
            if let Some(i) = scale.iter().position(|s| *s < 0.0) {
                return Err(Error::bundle(
                    self.src.path_of(&self.file(name, ".scale")),
                    format!("scale {i} is negative"),
                ));
            }
            Ok(scale)
        };
        Ok(match e.dtype {
            NativeDtype::Float32 => Table::Rows(Matrix::F32 { rows, cols, w: self.floats(&rel, &e.shape)? }),
            NativeDtype::Int8 => {
                let q = self.read(&rel, NpyDtype::I8, &e.shape)?.to_i8(&path)?;
                Table::Rows(Matrix::I8 { rows, cols, q, scale: scale()? })
            }
            NativeDtype::Int4 => {
                if e.shape.len() != 2 {
                    return Err(Error::bundle(&path, format!("int4 tensor {name} must be 2-D, is {:?}", e.shape)));
                }
                let packed = self.read(&rel, NpyDtype::U8, &[rows, cols.div_ceil(2)])?.into_u8(&path)?;
                Table::I4 { rows, cols, packed, scale: scale()? }
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The exporter's packing (`native_weights.pack_int4`): column 2j in byte j's low nibble,
    /// 2j + 1 in its high one, each q + 8; an odd row's last high nibble is 8 (zero).
    fn pack(q: &[i8], cols: usize) -> Vec<u8> {
        q.chunks(cols)
            .flat_map(|row| {
                row.chunks(2).map(|p| (p[0] + 8) as u8 | (((p.get(1).copied().unwrap_or(0) + 8) as u8) << 4))
            })
            .collect()
    }

    #[test]
    fn int4_rows_unpack_to_q_times_scale() {
        for cols in [1, 2, 7, 8] {
            let rows = 3;
            let q: Vec<i8> = (0..rows * cols).map(|i| (i as i8 * 5) % 15 - 7).collect();
            let scale = vec![0.5, 0.25, 2.0];
            let t = Table::I4 { rows, cols, packed: pack(&q, cols), scale: scale.clone() };
            assert_eq!(t.rows(), rows);
            let mut row = vec![0.0; cols];
            for r in 0..rows {
                t.row_into(r, &mut row);
                let want: Vec<f32> = q[r * cols..(r + 1) * cols].iter().map(|&v| f32::from(v) * scale[r]).collect();
                assert_eq!(row, want, "{cols} columns, row {r}");
            }
        }
    }
}
