//! The files a command writes, checked before it reads or writes anything: no output
//! may be one of its inputs or another output, and each one's directory must exist. A
//! mistyped path (`--out m.csv` for `--data m.csv`) would otherwise replace a
//! measurement or a recording with the report about it, and a bad path met halfway
//! would leave a failed run's first outputs written over the last good ones.

use std::path::Path;

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
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(format!(".tmp{}", std::process::id()));
    let tmp = std::path::PathBuf::from(tmp);
    let result = std::fs::write(&tmp, contents).and_then(|()| std::fs::rename(&tmp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
