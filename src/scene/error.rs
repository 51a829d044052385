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
                shown(&self.path),
                frame,
                self.problem
            ),
            None => write!(f, "{}: {}", shown(&self.path), self.problem),
        }
    }
}

impl std::error::Error for SceneError {}

pub type SceneResult<T> = Result<T, SceneError>;

/// `path` for a message, with any control character escaped as Rust writes
/// it (`\0`, `\n`, `\u{1b}`): a name read from a scene file may hold
/// anything, and a raw NUL, newline or escape sequence would garble the
/// message or the terminal showing it.
pub fn shown(path: &Path) -> String {
    escape_controls(&path.display().to_string())
}

/// `text` with its control characters escaped, everything else as it is.
pub fn escape_controls(text: &str) -> String {
    if !text.chars().any(char::is_control) {
        return text.to_string();
    }
    text.chars()
        .map(|c| {
            if c.is_control() {
                c.escape_debug().to_string()
            } else {
                c.to_string()
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_characters_are_escaped_in_paths() {
        assert_eq!(shown(Path::new("train/r_0.png")), "train/r_0.png");
        assert_eq!(
            shown(Path::new("train/r\n0\u{1b}[2J.png")),
            "train/r\\n0\\u{1b}[2J.png"
        );
        assert_eq!(escape_controls("a\0b"), "a\\0b");
        // Accented letters are not control characters.
        assert_eq!(escape_controls("café"), "café");
    }
}
