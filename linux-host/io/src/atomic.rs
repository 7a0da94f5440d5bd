//! Atomic file output: write into a temporary file beside the target, then rename it over the
//! target, so a reader (or a crash) never sees half a file; and [`OutputSet`], a folder's
//! whole set of outputs replaced together, so a killed or failed re-run never leaves old and
//! new files mixed.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
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
        fs::create_dir_all(dir)
            .with_context(|| format!("cannot write {}: creating its folder", path.display()))?;
        let temp = tempfile::Builder::new()
            .prefix(".cloi-")
            .suffix(".tmp")
            .tempfile_in(dir)
            .with_context(|| {
                format!(
                    "cannot write {}: creating a temporary file in {}",
                    path.display(),
                    dir.display()
                )
            })?;
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

/// Prefix of every temporary name this module creates in an output folder.
const TEMP_PREFIX: &str = ".cloi-";

/// The outputs of one run, staged in a hidden folder inside the output folder and moved into
/// it together by [`OutputSet::commit`].
///
/// Until the commit the folder keeps the previous run's files untouched, whatever happens to
/// this run (an error, a full disk, SIGKILL). The commit first removes the previous files the
/// new set replaces, its *marker* (the file every reader should check, such as `report.json`)
/// first, then moves the new files in (each a rename, so never half a file), the marker last.
/// A commit cut short therefore leaves old files only or new files only, never both, and no
/// marker; whenever the marker exists, the whole set beside it comes from its run. Staging
/// folders and temporary files that a killed run left behind are removed when the next set
/// begins, so two runs must not write into one folder at the same time.
#[derive(Debug)]
pub struct OutputSet {
    dir: PathBuf,
    staging: tempfile::TempDir,
}

impl OutputSet {
    /// Starts a set for `dir` (created when missing).
    ///
    /// # Errors
    /// The folder cannot be created, listed or written.
    pub fn begin(dir: &Path) -> Result<Self> {
        fs::create_dir_all(dir).with_context(|| format!("creating folder {}", dir.display()))?;
        for entry in fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
            let entry = entry.with_context(|| format!("listing {}", dir.display()))?;
            if !entry.file_name().to_string_lossy().starts_with(TEMP_PREFIX) {
                continue;
            }
            let path = entry.path();
            let removed = if entry.file_type().is_ok_and(|t| t.is_dir()) {
                fs::remove_dir_all(&path)
            } else {
                fs::remove_file(&path)
            };
            removed.with_context(|| format!("removing {} of a killed run", path.display()))?;
        }
        let staging = tempfile::Builder::new()
            .prefix(&format!("{TEMP_PREFIX}staging-"))
            .tempdir_in(dir)
            .with_context(|| format!("creating a staging folder in {}", dir.display()))?;
        Ok(Self {
            dir: dir.to_owned(),
            staging,
        })
    }

    /// Where this run writes the file `name` before the commit.
    pub fn path(&self, name: &str) -> PathBuf {
        self.staging.path().join(name)
    }

    /// The staging folder itself, for writers that take a folder.
    pub fn folder(&self) -> &Path {
        self.staging.path()
    }

    /// Replaces the folder's files by the staged ones, the `marker` last (see the type's
    /// docs), and returns their final paths.
    ///
    /// # Errors
    /// The marker was not staged (nothing changes), or a file could not be removed or moved
    /// (the folder then holds no marker).
    pub fn commit(self, marker: &str) -> Result<Vec<PathBuf>> {
        let staged_marker = self.staging.path().join(marker);
        if !staged_marker.is_file() {
            bail!("the output set has no {marker}");
        }
        let mut names: Vec<_> = fs::read_dir(self.staging.path())
            .with_context(|| format!("listing {}", self.staging.path().display()))?
            .map(|e| e.map(|e| e.file_name()))
            .collect::<std::io::Result<_>>()
            .with_context(|| format!("listing {}", self.staging.path().display()))?;
        // The marker first out and last in; the others in a fixed order.
        names.sort_by_key(|n| (n.as_os_str() != marker, n.clone()));
        for name in &names {
            let old = self.dir.join(name);
            match fs::remove_file(&old) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(e).with_context(|| format!("removing {}", old.display())),
            }
        }
        names.rotate_left(1);
        let mut moved = Vec::with_capacity(names.len());
        for name in names {
            let (from, to) = (self.staging.path().join(&name), self.dir.join(&name));
            fs::rename(&from, &to)
                .with_context(|| format!("moving {} to {}", from.display(), to.display()))?;
            moved.push(to);
        }
        // Make the renames durable before the staging folder goes.
        if let Ok(d) = fs::File::open(&self.dir) {
            let _ = d.sync_all();
        }
        Ok(moved)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_set_replaces_the_old_set_only_on_commit() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let old = OutputSet::begin(&out).unwrap();
        write_file(&old.path("a.txt"), b"old a").unwrap();
        write_file(&old.path("report.json"), b"old report").unwrap();
        old.commit("report.json").unwrap();
        // A second run that fails (or is killed) before its commit changes nothing; the next
        // one removes what it left.
        let failed = OutputSet::begin(&out).unwrap();
        write_file(&failed.path("a.txt"), b"never").unwrap();
        std::mem::forget(failed);
        let names = |d: &Path| {
            let mut v: Vec<String> = fs::read_dir(d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        assert_eq!(fs::read(out.join("a.txt")).unwrap(), b"old a");
        assert_eq!(names(&out).len(), 3, "{:?}", names(&out));
        let new = OutputSet::begin(&out).unwrap();
        assert_eq!(names(&out).len(), 3, "the killed run's staging is gone");
        write_file(&new.path("a.txt"), b"new a").unwrap();
        write_file(&new.path("b.txt"), b"new b").unwrap();
        assert!(new.commit("missing.json").is_err());
        let new = OutputSet::begin(&out).unwrap();
        write_file(&new.path("a.txt"), b"new a").unwrap();
        write_file(&new.path("report.json"), b"new report").unwrap();
        let moved = new.commit("report.json").unwrap();
        assert_eq!(moved.last().unwrap(), &out.join("report.json"));
        assert_eq!(names(&out), ["a.txt", "report.json"]);
        assert_eq!(fs::read(out.join("a.txt")).unwrap(), b"new a");
    }

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
