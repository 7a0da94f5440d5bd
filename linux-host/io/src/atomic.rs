//! Atomic file output: write into a temporary file beside the target, then rename it over the
//! target, so a reader (or a crash) never sees half a file.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use tempfile::NamedTempFile;

/// A file being written; it appears at its final path only on [`AtomicFile::commit`].
/// Dropping it without committing removes the temporary file.
#[derive(Debug)]
pub struct AtomicFile {
    target: PathBuf,
    temp: BufWriter<NamedTempFile>,
}

/// The folder of `path` ("." for a bare file name).
fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

impl AtomicFile {
    /// Starts writing `path` (creating its parent folders).
    ///
    /// # Errors
    /// The folder cannot be created or is not writable.
    pub fn create(path: &Path) -> Result<Self> {
        let dir = parent_dir(path);
        fs::create_dir_all(dir).with_context(|| format!("creating folder {}", dir.display()))?;
        let temp = tempfile::Builder::new()
            .prefix(".cloi-")
            .suffix(".tmp")
            .tempfile_in(dir)
            .with_context(|| format!("creating a temporary file in {}", dir.display()))?;
        Ok(Self {
            target: path.to_owned(),
            temp: BufWriter::with_capacity(1 << 16, temp),
        })
    }

    /// The final path.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// The buffered writer (it also seeks, for formats such as MCAP).
    pub fn writer(&mut self) -> &mut BufWriter<NamedTempFile> {
        &mut self.temp
    }

    /// Flushes, syncs and renames the file to its final path.
    ///
    /// # Errors
    /// Any IO error; the target is then left as it was.
    pub fn commit(self) -> Result<()> {
        let target = self.target;
        let temp = self
            .temp
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("writing {}", target.display()))?;
        Self::persist(temp, &target)
    }

    /// Renames an already written temporary file to `target`.
    pub(crate) fn persist(temp: NamedTempFile, target: &Path) -> Result<()> {
        // Temporary files are private (0600); give the result the target's old permissions,
        // or the usual 0644 for a new file.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let perms = fs::metadata(target)
                .map(|m| m.permissions())
                .unwrap_or_else(|_| fs::Permissions::from_mode(0o644));
            temp.as_file()
                .set_permissions(perms)
                .with_context(|| format!("setting permissions of {}", target.display()))?;
        }
        temp.as_file()
            .sync_all()
            .with_context(|| format!("syncing {}", target.display()))?;
        temp.persist(target)
            .map_err(|e| e.error)
            .with_context(|| format!("renaming the temporary file to {}", target.display()))?;
        Ok(())
    }

    /// Splits into the target path and the buffered temporary file, for writers that take
    /// ownership of their output (the MCAP writer).
    pub(crate) fn into_parts(self) -> (PathBuf, BufWriter<NamedTempFile>) {
        (self.target, self.temp)
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.temp.write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.temp.flush()
    }
}

/// Writes a whole file atomically.
///
/// # Errors
/// Any IO error; the target is then left as it was.
pub fn write_file(path: &Path, contents: &[u8]) -> Result<()> {
    let mut file = AtomicFile::create(path)?;
    file.write_all(contents)
        .with_context(|| format!("writing {}", path.display()))?;
    file.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_appears_only_on_commit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub").join("a.txt");
        let mut f = AtomicFile::create(&path).unwrap();
        f.write_all(b"hello").unwrap();
        f.flush().unwrap();
        assert!(!path.exists());
        f.commit().unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"hello");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = fs::metadata(&path).unwrap().permissions().mode();
            assert_eq!(mode & 0o777, 0o644);
        }
        // No temporary file is left behind.
        assert_eq!(fs::read_dir(path.parent().unwrap()).unwrap().count(), 1);
    }

    #[test]
    fn dropped_file_leaves_old_contents() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.txt");
        write_file(&path, b"old").unwrap();
        {
            let mut f = AtomicFile::create(&path).unwrap();
            f.write_all(b"new but abandoned").unwrap();
        }
        assert_eq!(fs::read(&path).unwrap(), b"old");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
