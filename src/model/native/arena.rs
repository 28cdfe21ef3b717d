//! One buffer for a loaded model's weight matrices, backed by transparent huge pages.
use super::kernels::MatRef;
use super::weights::Matrix;

/// A matrix in an [`Arena`]: offsets of its values (f32, or int8 and then the f32 row
/// scales).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Wm {
    pub(crate) rows: usize,
    pub(crate) cols: usize,
    int8: bool,
    at: usize,
    scale_at: usize,
}

impl Wm {
    /// Bytes one product reads.
    pub(crate) fn bytes(&self) -> usize {
        if self.int8 {
            self.rows * self.cols + 4 * self.rows
        } else {
            4 * self.rows * self.cols
        }
    }
}

/// A model's weight matrices in one buffer, copied there at load (the native step's and
/// the native decoder's). On Linux the buffer is 2 MiB-aligned and advised for
/// transparent huge pages before it is touched: a GEMV
/// streaming 1.8 GB through 4 KiB pages (where the loader's allocations usually end up)
/// reads ~15 GB/s on one Zen 4 core, through 2 MiB pages ~24 GB/s (measured on the 2-core
/// machine; the prefetchers stop at 4 KiB boundaries and every page costs a TLB walk).
/// Pages past what is written are never touched, so the int8 matrices' share of the
/// f32-sized bound costs address space only.
pub(crate) struct Arena {
    base: *mut u8,
    layout: std::alloc::Layout,
    used: usize,
    /// `used` at the last `trim`.
    trimmed: usize,
}

// SAFETY: the buffer is owned (freed on drop), written only while loading (`&mut self`),
// then only read.
unsafe impl Send for Arena {}
unsafe impl Sync for Arena {}

impl Arena {
    const ALIGN: usize = 2 << 20;

    /// `n` bytes rounded up to the 64-byte slots an arena hands out.
    pub(crate) fn size(n: usize) -> usize {
        n.div_ceil(64) * 64
    }

    /// An arena of `bytes`; `None` if the system cannot provide that much address space
    /// (a size computed from a corrupt manifest must be an error, not an abort).
    pub(crate) fn new(bytes: usize) -> Option<Arena> {
        let layout = std::alloc::Layout::from_size_align(bytes.max(64), Self::ALIGN).ok()?;
        // SAFETY: the layout has a non-zero size.
        let base = unsafe { std::alloc::alloc(layout) };
        if base.is_null() {
            return None;
        }
        #[cfg(target_os = "linux")]
        // SAFETY: advice on memory this arena owns; base is page-aligned. A failure only
        // means 4 KiB pages.
        unsafe {
            libc::madvise(base as *mut libc::c_void, layout.size(), libc::MADV_HUGEPAGE);
        }
        Some(Arena { base, layout, used: 0, trimmed: 0 })
    }

    /// An upper bound on the arena `tensors` need: every one as f32, plus a scale per row.
    pub(crate) fn bound<'a>(shapes: impl Iterator<Item = &'a [usize]>) -> usize {
        shapes
            .map(|s| {
                let n = s.iter().fold(1usize, |a, &d| a.saturating_mul(d));
                let rows = s.first().copied().unwrap_or(1);
                Self::size(n.saturating_mul(4)).saturating_add(Self::size(rows.saturating_mul(4)))
            })
            .fold(0usize, usize::saturating_add)
    }

    /// Copies `n` bytes from `src` into the next slot; returns its offset.
    fn push(&mut self, src: *const u8, n: usize) -> usize {
        let at = self.used;
        assert!(
            at + Self::size(n) <= self.layout.size(),
            "native weight arena: {} + {n} bytes of {}",
            at,
            self.layout.size()
        );
        // SAFETY: [at, at + n) is inside the buffer (checked) and not yet handed out.
        unsafe { std::ptr::copy_nonoverlapping(src, self.base.add(at), n) };
        self.used += Self::size(n);
        at
    }

    /// Moves `m` into the arena.
    pub(crate) fn put(&mut self, m: Matrix) -> Wm {
        let (rows, cols) = (m.rows(), m.cols());
        let w = match &m {
            Matrix::F32 { w, .. } => {
                let at = self.push(w.as_ptr() as *const u8, 4 * w.len());
                Wm { rows, cols, int8: false, at, scale_at: 0 }
            }
            Matrix::I8 { q, scale, .. } => {
                let at = self.push(q.as_ptr() as *const u8, q.len());
                let scale_at = self.push(scale.as_ptr() as *const u8, 4 * scale.len());
                Wm { rows, cols, int8: true, at, scale_at }
            }
        };
        debug_assert_eq!(w.bytes(), m.bytes());
        drop(m);
        if self.used - self.trimmed >= 256 << 20 {
            self.trim();
        }
        w
    }

    /// Gives the loader's freed buffers back to the system: each tensor is read, converted
    /// and copied here, and glibc keeps the freed heap memory mapped (without this the
    /// paper model's step keeps ~1.4 GB more resident after load).
    pub(crate) fn trim(&mut self) {
        self.trimmed = self.used;
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        // SAFETY: malloc_trim only releases free heap memory.
        unsafe {
            libc::malloc_trim(0);
        }
    }

    /// The matrix `w` (made by this arena's `put`).
    pub(crate) fn mat(&self, w: &Wm) -> MatRef<'_> {
        let n = w.rows * w.cols;
        let end = if w.int8 { w.scale_at + 4 * w.rows } else { w.at + 4 * n };
        assert!(end <= self.used, "a matrix of another arena");
        // SAFETY: `put` wrote these ranges (64-byte aligned offsets into a 2 MiB-aligned
        // buffer, so f32 reads are aligned) and nothing writes them again.
        unsafe {
            if w.int8 {
                MatRef::I8 {
                    rows: w.rows,
                    cols: w.cols,
                    q: std::slice::from_raw_parts(self.base.add(w.at) as *const i8, n),
                    scale: std::slice::from_raw_parts(self.base.add(w.scale_at) as *const f32, w.rows),
                }
            } else {
                MatRef::F32 {
                    rows: w.rows,
                    cols: w.cols,
                    w: std::slice::from_raw_parts(self.base.add(w.at) as *const f32, n),
                }
            }
        }
    }
}

impl std::fmt::Debug for Arena {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Arena").field("used", &self.used).field("capacity", &self.layout.size()).finish()
    }
}

impl Drop for Arena {
    fn drop(&mut self) {
        // SAFETY: allocated in `new` with this layout.
        unsafe { std::alloc::dealloc(self.base, self.layout) }
    }
}
