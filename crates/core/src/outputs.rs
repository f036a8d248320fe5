//! The files a command writes, checked before it reads or writes anything: no output
//! may be one of its inputs or another output, and each one's directory must exist. A
//! mistyped path (`--out m.csv` for `--data m.csv`) would otherwise replace a
//! measurement or a recording with the report about it, and a bad path met halfway
//! would leave a failed run's first outputs written over the last good ones.
//!
//! A command that writes several files stages them ([`Staged`]): each is written
//! whole to a temporary file beside it, and only when every one is written are they
//! renamed into place, so a failed run leaves the last good set as it was. The commit
//! syncs each file before its rename and each directory after, so what a command
//! reported written is on the disk: a power cut a second later kept a new file absent
//! or empty, and a replaced one old.

use std::path::{Path, PathBuf};

/// Why an output path was refused.
#[derive(Debug, Clone, thiserror::Error, PartialEq, Eq)]
pub enum OutputError {
    /// The output names a file the command reads.
    #[error("{output}: is the input {input}; refusing to overwrite it")]
    IsInput {
        /// The output, as given.
        output: String,
        /// The input it names, as given.
        input: String,
    },
    /// Two outputs name the same file.
    #[error("{output}: named for two outputs")]
    Twice {
        /// The output, as given.
        output: String,
    },
    /// The output's directory does not exist (or is no directory).
    #[error("{output}: the directory {dir} does not exist")]
    NoDirectory {
        /// The output, as given.
        output: String,
        /// Its directory.
        dir: String,
    },
    /// The output names an existing directory.
    #[error("{output}: is a directory; give a file name")]
    IsDirectory {
        /// The output, as given.
        output: String,
    },
    /// An output directory's path names something else (a file).
    #[error("{flag} {dir}: is a file; {flag} takes a directory, made if it does not exist")]
    NotADirectory {
        /// The flag that names it.
        flag: &'static str,
        /// The path, as given.
        dir: String,
    },
    /// An output directory could not be made.
    #[error("{flag} {dir}: cannot make the directory: {message}")]
    MakeDirectory {
        /// The flag that names it.
        flag: &'static str,
        /// The path, as given.
        dir: String,
        /// The system's reason.
        message: String,
    },
}

/// Makes the output directory `dir` that `flag` names, with its parents; a file
/// there is named as such (the system says only "File exists").
pub fn make_dir(flag: &'static str, dir: &Path) -> Result<(), OutputError> {
    if dir.exists() && !dir.is_dir() {
        return Err(OutputError::NotADirectory {
            flag,
            dir: dir.display().to_string(),
        });
    }
    std::fs::create_dir_all(dir).map_err(|e| OutputError::MakeDirectory {
        flag,
        dir: dir.display().to_string(),
        message: e.to_string(),
    })
}

/// Same file: same device and inode, so links and `./` spellings are caught. A path
/// that does not exist yet is no input.
fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
        _ => a == b,
    }
}

/// Checks `outputs` against `inputs` and each other; see the module.
pub fn check(inputs: &[&Path], outputs: &[&Path]) -> Result<(), OutputError> {
    for (k, out) in outputs.iter().enumerate() {
        if let Some(input) = inputs.iter().find(|i| same_file(out, i)) {
            return Err(OutputError::IsInput {
                output: out.display().to_string(),
                input: input.display().to_string(),
            });
        }
        if out.is_dir() {
            return Err(OutputError::IsDirectory {
                output: out.display().to_string(),
            });
        }
        if outputs[..k].iter().any(|o| same_file(out, o)) {
            return Err(OutputError::Twice {
                output: out.display().to_string(),
            });
        }
        let dir = match out.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        if !dir.is_dir() {
            return Err(OutputError::NoDirectory {
                output: out.display().to_string(),
                dir: dir.display().to_string(),
            });
        }
    }
    Ok(())
}

/// Writes `contents` to `path` through a temporary file beside it, renamed over
/// `path` once complete: a full disk or a kill leaves the old file, never half a new
/// one.
pub fn write(path: &Path, contents: impl AsRef<[u8]>) -> std::io::Result<()> {
    let mut staged = Staged::new();
    staged.write(path, contents)?;
    staged.commit().map_err(|(_, e)| e)
}

/// Files written together or not at all: each goes to a temporary file beside it
/// (so the rename stays on one file system), and [`Staged::commit`] renames them all
/// into place once every one is complete. Dropped without a commit (an error on the
/// way), it removes its temporary files and leaves the outputs as they were.
#[derive(Debug, Default)]
pub struct Staged {
    /// (temporary, final) path of every staged file.
    files: Vec<(PathBuf, PathBuf)>,
}

impl Staged {
    /// Nothing staged yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// The temporary path that stands in for `path` until the commit, for a file
    /// that something else writes (a database, an export); staging `path` again
    /// gives the same temporary.
    pub fn path_for(&mut self, path: &Path) -> PathBuf {
        if let Some((tmp, _)) = self.files.iter().find(|(_, p)| p == path) {
            return tmp.clone();
        }
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(format!(".tmp{}", std::process::id()));
        let tmp = PathBuf::from(tmp);
        self.files.push((tmp.clone(), path.to_path_buf()));
        tmp
    }

    /// Writes `contents` whole to `path`'s temporary file.
    pub fn write(&mut self, path: &Path, contents: impl AsRef<[u8]>) -> std::io::Result<()> {
        let tmp = self.path_for(path);
        std::fs::write(tmp, contents)
    }

    /// Syncs every staged file (those written through [`Staged::path_for`] too), then
    /// renames them into place in the order staged and syncs their directories; on an
    /// error, the file it names (the final path) and the error. Before the renames,
    /// an error leaves every output as it was.
    pub fn commit(mut self) -> Result<(), (PathBuf, std::io::Error)> {
        for (tmp, path) in &self.files {
            std::fs::File::open(tmp)
                .and_then(|f| f.sync_all())
                .map_err(|e| (path.clone(), e))?;
        }
        let files = std::mem::take(&mut self.files);
        for (k, (tmp, path)) in files.iter().enumerate() {
            if let Err(e) = put_in_place(tmp, path) {
                // The rest stay staged, so that drop removes them.
                self.files = files[k..].to_vec();
                return Err((path.clone(), e));
            }
        }
        let mut dirs: Vec<&Path> = Vec::new();
        for (_, path) in &files {
            let dir = match path.parent() {
                Some(d) if !d.as_os_str().is_empty() => d,
                _ => Path::new("."),
            };
            if !dirs.contains(&dir) {
                dirs.push(dir);
                std::fs::File::open(dir)
                    .and_then(|d| d.sync_all())
                    .map_err(|e| (path.clone(), e))?;
            }
        }
        Ok(())
    }
}

/// Renames `tmp` over `path`; into a device, a fifo or a socket (`--plot /dev/null`)
/// it copies instead: renamed over, `/dev/null` became a regular file for every
/// program on the machine.
fn put_in_place(tmp: &Path, path: &Path) -> std::io::Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if !m.is_file() && !m.is_dir() => {
            let mut from = std::fs::File::open(tmp)?;
            let mut to = std::fs::OpenOptions::new().write(true).open(path)?;
            std::io::copy(&mut from, &mut to)?;
            std::fs::remove_file(tmp)
        }
        _ => std::fs::rename(tmp, path),
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        for (tmp, _) in &self.files {
            let _ = std::fs::remove_file(tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // `--plot /dev/null` (or `--out`) as root renamed a regular file over the
    // machine's /dev/null, which every program then read garbage from. A null device
    // of the test's own (mknod needs root) must stay a device.
    #[test]
    fn an_output_into_a_device_writes_into_it_and_leaves_it_a_device() {
        use std::os::unix::fs::FileTypeExt;
        let dir = tempfile::tempdir().unwrap();
        let null = dir.path().join("null");
        let made = std::process::Command::new("mknod")
            .arg(&null)
            .args(["c", "1", "3"])
            .status();
        if !made.is_ok_and(|s| s.success()) {
            println!("SKIPPED: mknod needs root");
            return;
        }
        write(&null, "svg").unwrap();
        let kind = std::fs::metadata(&null).unwrap().file_type();
        assert!(kind.is_char_device(), "{kind:?}");
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1, "a temporary file is left: {left:?}");
    }

    #[test]
    fn an_output_that_is_an_input_is_refused_by_any_spelling() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("m.csv");
        std::fs::write(&data, "t_s\n").unwrap();
        let dotted = dir.path().join(".").join("m.csv");
        let linked = dir.path().join("link.csv");
        std::fs::hard_link(&data, &linked).unwrap();
        for out in [&data, &dotted, &linked] {
            let e = check(&[&data], &[out.as_path()]).unwrap_err();
            assert!(matches!(e, OutputError::IsInput { .. }), "{e}");
            assert!(e.to_string().contains("refusing to overwrite"), "{e}");
        }
        let other = dir.path().join("model.toml");
        assert_eq!(check(&[&data], &[&other]), Ok(()));
    }

    #[test]
    fn two_outputs_on_one_file_and_a_missing_directory_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.svg");
        let e = check(&[], &[&a, &a]).unwrap_err();
        assert_eq!(
            e,
            OutputError::Twice {
                output: a.display().to_string()
            }
        );
        let lost = dir.path().join("no").join("p.svg");
        let e = check(&[], &[&a, &lost]).unwrap_err();
        assert!(matches!(e, OutputError::NoDirectory { .. }), "{e}");
        assert!(e.to_string().contains("does not exist"), "{e}");
        // A bare file name lives in the working directory, which exists.
        assert_eq!(check(&[], &[Path::new("report.csv")]), Ok(()));
    }

    /// `--out report.toml`, a file, got the system's "File exists (os error 17)".
    #[test]
    fn an_output_directory_that_is_a_file_is_named_as_such() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("model.toml");
        std::fs::write(&file, "x").unwrap();
        let e = make_dir("--out", &file).unwrap_err().to_string();
        assert_eq!(
            e,
            format!(
                "--out {}: is a file; --out takes a directory, made if it does not exist",
                file.display()
            )
        );
        assert_eq!(std::fs::read_to_string(&file).unwrap(), "x");
        let e = make_dir("--out", &file.join("sub"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("cannot make the directory"), "{e}");
        let sub = dir.path().join("a/b");
        make_dir("--out", &sub).unwrap();
        make_dir("--out", &sub).unwrap();
        assert!(sub.is_dir());
    }

    #[test]
    fn write_replaces_whole_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("model.toml");
        std::fs::write(&p, "old").unwrap();
        write(&p, "new").unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new");
        // Into a directory that is gone: an error, and no temporary file left.
        let lost = dir.path().join("gone").join("x.toml");
        assert!(write(&lost, "x").is_err());
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1, "{left:?}");
    }

    /// calibrate replaced its model, then failed on a plot path that was a directory.
    #[test]
    fn an_output_that_is_a_directory_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = check(&[], &[dir.path()]).unwrap_err();
        assert!(matches!(e, OutputError::IsDirectory { .. }), "{e}");
        assert!(
            e.to_string().ends_with("is a directory; give a file name"),
            "{e}"
        );
    }

    #[test]
    fn staged_files_replace_the_old_ones_together_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.csv"), dir.path().join("b.md"));
        std::fs::write(&a, "old a").unwrap();
        std::fs::write(&b, "old b").unwrap();
        // The second write fails (its directory is gone): nothing is replaced, and
        // no temporary file is left.
        let mut s = Staged::new();
        s.write(&a, "new a").unwrap();
        assert!(s.write(&dir.path().join("gone").join("c"), "x").is_err());
        drop(s);
        assert_eq!(std::fs::read_to_string(&a).unwrap(), "old a");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
        // Written by someone else through its temporary path, then committed.
        let mut s = Staged::new();
        s.write(&a, "new a").unwrap();
        let tmp = s.path_for(&b);
        assert_eq!(s.path_for(&b), tmp);
        std::fs::write(&tmp, "new b").unwrap();
        assert_eq!(std::fs::read_to_string(&b).unwrap(), "old b");
        s.commit().unwrap();
        assert_eq!(std::fs::read_to_string(&a).unwrap(), "new a");
        assert_eq!(std::fs::read_to_string(&b).unwrap(), "new b");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    /// Every staged file is synced before the first rename: one that was never
    /// written (its writer failed silently) fails the commit with every output as it
    /// was, not after the first ones were replaced.
    #[test]
    fn a_staged_file_never_written_fails_the_commit_before_any_rename() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a.csv"), dir.path().join("b.db"));
        std::fs::write(&a, "old a").unwrap();
        let mut s = Staged::new();
        s.write(&a, "new a").unwrap();
        let _ = s.path_for(&b);
        let (path, e) = s.commit().unwrap_err();
        assert_eq!((path, e.kind()), (b, std::io::ErrorKind::NotFound));
        assert_eq!(std::fs::read_to_string(&a).unwrap(), "old a");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
