//! Where a bundle's files come from: a directory on disk, or a fixed set of files held in
//! memory (the default bundle compiled into the library, feature `embedded-default`, or a
//! host's own `include_bytes!` set).
//!
//! Every loader (manifest, sizes and SHA-256, tokenizer, graphs, parity index) reads
//! through a [`BundleSource`], so both kinds get exactly the same verification and the
//! same messages. Errors name `<dir>/<file>` for a directory, `<embedded>/<file>` for the
//! compiled-in default and `<memory>/<file>` for another in-memory set.
//!
//! What only means something on disk stays directory-only: the bundle must be a directory,
//! a listed file must be a regular file (symlinks to files are followed, as before), and
//! looking for unlisted files walks the tree without following symlinked directories. An
//! in-memory set has none of these hazards; its names are still checked for unlisted
//! entries, so a set that mixes two exports is rejected like a directory would be.
use std::borrow::Cow;
use std::fmt;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// An in-memory bundle: `(relative '/'-separated name, bytes)` pairs, `manifest.json`
/// among them. `'static` because the bytes are normally `include_bytes!` data.
pub type StaticFiles = &'static [(&'static str, &'static [u8])];

/// Label of the compiled-in default bundle in error messages (`<embedded>/step.onnx`).
pub const EMBEDDED_LABEL: &str = "<embedded>";
/// Label of any other in-memory bundle in error messages.
pub const MEMORY_LABEL: &str = "<memory>";

/// Where a bundle's files are read from. Cheap to clone (a path, or a `'static` slice).
#[derive(Clone)]
pub struct BundleSource {
    kind: Kind,
}

#[derive(Clone)]
enum Kind {
    Dir(PathBuf),
    /// `embedded` marks the compiled-in default, whose bytes cannot change while the
    /// process runs (so its hashes are checked once per process, see `bundle::embedded`).
    /// Private so that no other set can claim it.
    Memory {
        files: StaticFiles,
        embedded: bool,
    },
}

/// What [`BundleSource::stat`] found under a name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum FileStat {
    Missing,
    /// Present, but a directory or another non-regular entry (directories only).
    NotAFile,
    File {
        len: u64,
    },
}

impl BundleSource {
    /// A bundle directory.
    pub fn dir(path: impl Into<PathBuf>) -> BundleSource {
        BundleSource { kind: Kind::Dir(path.into()) }
    }

    /// A bundle held in memory; errors name its files `<memory>/<file>`. The graphs must be
    /// self-contained (no ONNX external data, which tract can only resolve on disk); the
    /// exporter writes them so.
    pub fn memory(files: StaticFiles) -> BundleSource {
        BundleSource { kind: Kind::Memory { files, embedded: false } }
    }

    /// The default bundle compiled into the library, or `None` in a build without the
    /// `embedded-default` feature.
    pub fn embedded() -> Option<BundleSource> {
        super::embedded::files().map(|files| BundleSource { kind: Kind::Memory { files, embedded: true } })
    }

    /// The bundle directory, for a bundle on disk.
    pub fn directory(&self) -> Option<&Path> {
        match &self.kind {
            Kind::Dir(d) => Some(d),
            Kind::Memory { .. } => None,
        }
    }

    /// Whether `rel` is a file this source leaves out on purpose: a reference graph of a
    /// natively-run model in the embedded default ([`super::embedded::omitted`]). The
    /// verification skips it, and loading it (the tract backend) is a clear error.
    pub fn omits(&self, rel: &str) -> bool {
        self.is_embedded() && super::embedded::omitted().contains(&rel)
    }

    /// Whether this is the default bundle compiled into the library.
    pub fn is_embedded(&self) -> bool {
        matches!(self.kind, Kind::Memory { embedded: true, .. })
    }

    /// What errors call the bundle as a whole: its directory, `<embedded>` or `<memory>`.
    pub fn root(&self) -> PathBuf {
        match &self.kind {
            Kind::Dir(d) => d.clone(),
            Kind::Memory { embedded, .. } => PathBuf::from(label(*embedded)),
        }
    }

    /// What errors call the file `rel` (relative, '/'-separated): `dir/rel`,
    /// `<embedded>/rel` or `<memory>/rel`.
    pub fn path_of(&self, rel: &str) -> PathBuf {
        match &self.kind {
            Kind::Dir(d) => d.join(rel),
            // Built as text so the separator stays '/' on every platform.
            Kind::Memory { embedded, .. } => PathBuf::from(format!("{}/{rel}", label(*embedded))),
        }
    }

    /// Directory bundles: the directory exists (the OS error is kept in the message, e.g.
    /// a symlink loop's "Too many levels of symbolic links"). In-memory bundles always pass.
    pub(crate) fn check_root(&self) -> Result<()> {
        match &self.kind {
            Kind::Dir(d) => match fs::metadata(d) {
                Ok(meta) if meta.is_dir() => Ok(()),
                Ok(_) => Err(Error::bundle(d, "not a directory")),
                Err(e) if e.kind() == io::ErrorKind::NotFound => {
                    Err(Error::bundle(d, "not a directory (it does not exist)"))
                }
                Err(e) => Err(Error::bundle(d, format!("not a directory that can be opened: {e}"))),
            },
            Kind::Memory { .. } => Ok(()),
        }
    }

    /// The bytes of `rel`; borrowed (no copy) for an in-memory bundle. A name that is not
    /// there is `io::ErrorKind::NotFound`, for either kind. On disk only a regular file is
    /// read (see [`open_regular`]: a FIFO or device never blocks the loader).
    pub(crate) fn read(&self, rel: &str) -> io::Result<Cow<'static, [u8]>> {
        self.read_at_most(rel, u64::MAX)
    }

    /// [`read`](Self::read), refusing a file longer than `limit` bytes
    /// (`io::ErrorKind::InvalidData`) without reading more than `limit + 1` bytes of it.
    pub(crate) fn read_at_most(&self, rel: &str, limit: u64) -> io::Result<Cow<'static, [u8]>> {
        let too_long = |len: u64| {
            io::Error::new(
                io::ErrorKind::InvalidData,
                format!("the file is {len} bytes, more than the {limit}-byte limit"),
            )
        };
        match &self.kind {
            Kind::Dir(d) => {
                let (file, len) = open_regular(&d.join(rel))?;
                if len > limit {
                    return Err(too_long(len));
                }
                let mut buf = Vec::with_capacity(len as usize);
                io::Read::read_to_end(&mut io::Read::take(file, limit.saturating_add(1)), &mut buf)?;
                if buf.len() as u64 > limit {
                    return Err(too_long(buf.len() as u64)); // grew while we read it
                }
                Ok(Cow::Owned(buf))
            }
            Kind::Memory { files, embedded } => match find(files, rel) {
                Some(b) if b.len() as u64 > limit => Err(too_long(b.len() as u64)),
                Some(b) => Ok(Cow::Borrowed(b)),
                None => {
                    Err(io::Error::new(io::ErrorKind::NotFound, format!("not among the {} files", label(*embedded))))
                }
            },
        }
    }

    /// [`read`](Self::read) with the error turned into an `Error::Bundle` naming the file.
    pub(crate) fn read_file(&self, rel: &str) -> Result<Cow<'static, [u8]>> {
        self.read(rel).map_err(|e| Error::bundle(self.path_of(rel), format!("cannot read: {e}")))
    }

    /// Whether `rel` is there, and its size.
    pub(crate) fn stat(&self, rel: &str) -> io::Result<FileStat> {
        match &self.kind {
            Kind::Dir(d) => match fs::metadata(d.join(rel)) {
                Ok(meta) if meta.is_file() => Ok(FileStat::File { len: meta.len() }),
                Ok(_) => Ok(FileStat::NotAFile),
                Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(FileStat::Missing),
                Err(e) => Err(e),
            },
            Kind::Memory { files, .. } => Ok(match find(files, rel) {
                Some(b) => FileStat::File { len: b.len() as u64 },
                None => FileStat::Missing,
            }),
        }
    }

    /// Lower-case hex SHA-256 of `rel` (streamed from disk for a directory, so a large
    /// graph is not held in memory twice).
    pub(crate) fn sha256(&self, rel: &str) -> Result<String> {
        match &self.kind {
            Kind::Dir(d) => super::verify::sha256_file(&d.join(rel)),
            Kind::Memory { .. } => Ok(super::verify::sha256_hex(&self.read_file(rel)?)),
        }
    }

    /// Whether the bundle has a subdirectory `name` (for a memory set: a file under `name/`).
    pub(crate) fn has_dir(&self, name: &str) -> bool {
        match &self.kind {
            Kind::Dir(d) => d.join(name).is_dir(),
            Kind::Memory { files, .. } => {
                files.iter().any(|(n, _)| n.strip_prefix(name).is_some_and(|rest| rest.starts_with('/')))
            }
        }
    }

    /// Relative '/'-separated names of every file present, skipping names with a component
    /// that starts with '.' (`.DS_Store`, editor swap files). A directory is walked without
    /// following symlinked directories (they are reported as entries).
    pub(crate) fn list(&self) -> Result<Vec<String>> {
        match &self.kind {
            Kind::Dir(d) => {
                let mut out = Vec::new();
                walk(d, "", 0, &mut out)?;
                Ok(out)
            }
            Kind::Memory { files, .. } => Ok(files
                .iter()
                .map(|(n, _)| *n)
                .filter(|n| !n.split('/').any(|c| c.starts_with('.')))
                .map(str::to_string)
                .collect()),
        }
    }
}

impl fmt::Display for BundleSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.root().display())
    }
}

/// Names only: the bytes of an in-memory bundle are far too long to print.
impl fmt::Debug for BundleSource {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.kind {
            Kind::Dir(d) => f.debug_tuple("BundleSource::Dir").field(d).finish(),
            Kind::Memory { files, embedded } => {
                write!(f, "BundleSource::Memory({}, {} files)", label(*embedded), files.len())
            }
        }
    }
}

fn label(embedded: bool) -> &'static str {
    if embedded {
        EMBEDDED_LABEL
    } else {
        MEMORY_LABEL
    }
}

/// Opens `path` for reading only if it is a regular file (symlinks to one are followed),
/// and returns it with its length. The open itself never blocks: it uses `O_NONBLOCK`, so a
/// FIFO without a writer (which a plain `open` would wait on forever) or a device is opened,
/// seen by `fstat` to be no regular file and refused (`io::ErrorKind::InvalidInput`). The
/// check is on the opened descriptor, so the file cannot be swapped between check and read.
/// `O_NONBLOCK` has no effect on reads of a regular file.
pub(crate) fn open_regular(path: &Path) -> io::Result<(fs::File, u64)> {
    let mut opts = fs::OpenOptions::new();
    opts.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        opts.custom_flags(libc::O_NONBLOCK);
    }
    let file = opts.open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        let what = if meta.is_dir() { "a directory" } else { "not a regular file (a FIFO, socket or device)" };
        return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("it is {what}")));
    }
    Ok((file, meta.len()))
}

fn find(files: StaticFiles, rel: &str) -> Option<&'static [u8]> {
    files.iter().find(|(n, _)| *n == rel).map(|(_, b)| *b)
}

/// Relative paths of the files under `dir`, skipping dot-names; symlinks to directories
/// are not followed.
fn walk(dir: &Path, prefix: &str, depth: usize, out: &mut Vec<String>) -> Result<()> {
    if depth >= 16 {
        return Err(Error::bundle(dir, "directory tree too deep"));
    }
    let rd = fs::read_dir(dir).map_err(|e| Error::bundle(dir, format!("cannot list: {e}")))?;
    for entry in rd {
        let entry = entry.map_err(|e| Error::bundle(dir, format!("cannot list: {e}")))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else {
            return Err(Error::bundle(entry.path(), "file name is not UTF-8"));
        };
        if name.starts_with('.') {
            continue;
        }
        let rel = if prefix.is_empty() { name.to_string() } else { format!("{prefix}/{name}") };
        let ft = entry.file_type().map_err(|e| Error::bundle(entry.path(), format!("cannot stat: {e}")))?;
        if ft.is_dir() {
            walk(&entry.path(), &rel, depth + 1, out)?;
        } else {
            out.push(rel);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    static FILES: &[(&str, &[u8])] = &[("manifest.json", b"{}"), ("parity/index.json", b"[]"), (".hidden/x", b"")];

    #[test]
    fn memory_names_and_reads() {
        let s = BundleSource::memory(FILES);
        assert!(!s.is_embedded() && s.directory().is_none());
        assert_eq!(s.path_of("a/b.onnx"), PathBuf::from("<memory>/a/b.onnx"));
        assert_eq!(&*s.read("manifest.json").unwrap(), b"{}");
        assert_eq!(s.read("nope").unwrap_err().kind(), io::ErrorKind::NotFound);
        assert_eq!(s.stat("parity/index.json").unwrap(), FileStat::File { len: 2 });
        assert_eq!(s.stat("parity").unwrap(), FileStat::Missing);
        assert!(s.has_dir("parity") && !s.has_dir("par"));
        assert_eq!(s.list().unwrap(), ["manifest.json", "parity/index.json"]);
        assert_eq!(format!("{s:?}"), "BundleSource::Memory(<memory>, 3 files)");
    }
}
