//! Why a run folder cannot be used, by the kind a caller decides on: the
//! run folders' (`run.rs`) and their lock's (`lock.rs`) one error type,
//! below both.

use std::path::{Path, PathBuf};

/// What is at a path given as a new run's folder.
#[derive(Debug, Clone, PartialEq)]
pub enum OutFolder {
    /// Nothing, or an empty folder (a lone lock file left by a refused
    /// start counts as empty).
    Free,
    /// A zrak run: a checkpoint, or a `run.json` zrak wrote (a run stopped
    /// before its first checkpoint).
    Run { has_checkpoint: bool },
    /// A folder holding other files: a few of their names and how many
    /// there are.
    Other { names: Vec<String>, count: usize },
    /// Not a folder (a file, a link that loops or points nowhere, a
    /// pipe): what it is.
    NotAFolder(String),
}

/// A run folder cannot be used as asked, by the kind a caller decides on;
/// each names the folder and shows as the message the command line prints.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunFolderError {
    /// No folder at the path (nothing, or something else) to resume or
    /// read.
    #[error("{}: no such run folder ({problem})", path.display())]
    NotFound { path: PathBuf, problem: String },
    /// A folder without a checkpoint to resume from.
    #[error("{}: no checkpoint to resume from (no {file} in the folder)", path.display())]
    NoCheckpoint {
        path: PathBuf,
        /// The checkpoint's file name in a run folder.
        file: &'static str,
    },
    /// Another process holds the folder's lock: `holder` says which
    /// ("another zrak (process 12)").
    #[error(
        "{}: {holder} is using this run folder; wait for it to finish or stop it (two \
         processes writing one run would corrupt it)",
        path.display()
    )]
    Locked { path: PathBuf, holder: String },
    /// A new run's folder that already holds a run or other files (see
    /// [`OutFolder`]); `message` names the ways on.
    #[error("{message}")]
    Occupied {
        path: PathBuf,
        found: OutFolder,
        message: String,
    },
    /// Anything else: not a folder, cannot be created, written, locked or
    /// moved aside, a checkpoint or log that is no regular file. `message`
    /// is the whole message, naming the file at fault.
    #[error("{message}")]
    Unusable { path: PathBuf, message: String },
}

impl RunFolderError {
    pub(super) fn unusable(path: &Path, message: String) -> Self {
        Self::Unusable {
            path: path.to_path_buf(),
            message,
        }
    }
}
