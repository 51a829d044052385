//! One writer per run folder: an advisory lock on the folder's
//! `.zrak.lock` (the standard library's `File::try_lock`: `flock` on
//! Linux, `LockFileEx` on Windows), held for as long as the [`RunLock`]
//! lives and released by the system when the process ends however it
//! ends, so a crashed run never leaves a stale lock behind. The file holds
//! the holder's process id, so a refused writer can say who holds it.
//! Readers (`eval`, `render`) take no lock: checkpoints are replaced whole
//! by a rename, so a reader sees the old one or the new one.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::{Path, PathBuf};

use super::folder_error::RunFolderError;

/// The lock file inside a run folder.
pub const LOCK_FILE: &str = ".zrak.lock";

/// A held lock on a run folder; dropping it releases the lock.
#[derive(Debug)]
pub struct RunLock {
    path: PathBuf,
    // Kept open: the lock lives as long as this descriptor.
    _file: File,
}

impl RunLock {
    /// Takes the lock on `dir` (which must exist), or says which process
    /// holds it.
    pub fn acquire(dir: &Path) -> Result<Self, RunFolderError> {
        let path = dir.join(LOCK_FILE);
        // Never through a link: a run folder downloaded or left in a shared
        // `/tmp` could point its lock at any of the user's files, which the
        // process id below would replace. Nor truncated on opening: the
        // file is emptied only once the lock is ours.
        let mut file = crate::files::open_for_writing_no_follow(
            &path,
            OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false),
        )
        .map_err(|message| RunFolderError::Unusable {
            path: path.clone(),
            message,
        })?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                // A process id is a few digits: read no more than a line.
                let mut text = String::new();
                let _ = (&mut file).take(64).read_to_string(&mut text);
                let holder = match text.trim().parse::<u32>() {
                    Ok(pid) => format!("another zrak (process {pid})"),
                    Err(_) => "another zrak".into(),
                };
                return Err(RunFolderError::Locked {
                    path: dir.to_path_buf(),
                    holder,
                });
            }
            Err(TryLockError::Error(error)) => {
                return Err(RunFolderError::Unusable {
                    path: dir.to_path_buf(),
                    message: format!("{}: cannot lock the run folder: {error}", dir.display()),
                });
            }
        }
        // Ours now: record who holds it.
        let record = (|| -> std::io::Result<()> {
            file.set_len(0)?;
            file.rewind()?;
            writeln!(file, "{}", std::process::id())?;
            file.flush()
        })();
        record.map_err(|e| RunFolderError::Unusable {
            path: path.clone(),
            message: format!("{}: cannot write the run's lock file: {e}", path.display()),
        })?;
        Ok(Self { path, _file: file })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_folder_is_refused_naming_the_holder() {
        let dir = tempfile::tempdir().unwrap();
        let first = RunLock::acquire(dir.path()).unwrap();
        // The lock belongs to the open file, so a second open in the same
        // process conflicts as another process would.
        let error = RunLock::acquire(dir.path()).unwrap_err();
        assert_eq!(
            error,
            RunFolderError::Locked {
                path: dir.path().to_path_buf(),
                holder: format!("another zrak (process {})", std::process::id()),
            }
        );
        assert!(
            error
                .to_string()
                .contains(&format!("process {}", std::process::id())),
            "{error}"
        );
        drop(first);
        RunLock::acquire(dir.path()).expect("released with the first lock");
    }

    #[cfg(unix)]
    #[test]
    fn a_lock_file_that_is_a_link_is_refused_and_its_target_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("bashrc");
        std::fs::write(&target, "the user's own").unwrap();
        let run = dir.path().join("run");
        std::fs::create_dir(&run).unwrap();
        std::os::unix::fs::symlink(&target, run.join(LOCK_FILE)).unwrap();
        let error = RunLock::acquire(&run).unwrap_err();
        assert!(
            matches!(error, RunFolderError::Unusable { .. }),
            "{error:?}"
        );
        let error = error.to_string();
        assert!(
            error.contains(LOCK_FILE)
                && error.contains("symbolic link")
                && error.contains("remove it"),
            "{error}"
        );
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "the user's own");
    }
}
