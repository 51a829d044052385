//! Errors for loading scenes: every one names the file (and frame, when one
//! frame is at fault) and says what is wrong with it.

use std::fmt;
use std::path::{Path, PathBuf};

/// A scene could not be loaded. The message names the file and the problem.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneError {
    /// The file (or folder) at fault.
    pub path: PathBuf,
    /// The index of the frame within its JSON file, when one frame is at fault.
    pub frame: Option<usize>,
    /// What is wrong, in plain words.
    pub problem: String,
}

impl SceneError {
    pub fn new(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    pub fn in_frame(path: impl AsRef<Path>, frame: usize, problem: impl Into<String>) -> Self {
        Self {
            path: path.as_ref().to_path_buf(),
            frame: Some(frame),
            problem: problem.into(),
        }
    }
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.frame {
            Some(frame) => write!(
                f,
                "{}: frame {}: {}",
                self.path.display(),
                frame,
                self.problem
            ),
            None => write!(f, "{}: {}", self.path.display(), self.problem),
        }
    }
}

impl std::error::Error for SceneError {}

pub type SceneResult<T> = Result<T, SceneError>;
