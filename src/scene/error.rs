//! Errors for loading scenes: every one names the file (and frame, when one
//! frame is at fault) and says what is wrong with it.

use std::fmt;
use std::path::{Path, PathBuf};

/// A scene could not be loaded: the kind of problem, for a caller that
/// decides on it, with the file (or folder) at fault, the index of the frame
/// within its JSON file when one frame is at fault, and what is wrong in
/// plain words. Every kind shows as `PATH: PROBLEM` or
/// `PATH: frame N: PROBLEM`.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneError {
    /// Nothing is at the path: the scene's folder, a JSON file or an image
    /// a JSON file lists.
    NotFound {
        path: PathBuf,
        frame: Option<usize>,
        problem: String,
    },
    /// A folder holding none of the scene formats zrak reads.
    NotAScene {
        path: PathBuf,
        frame: Option<usize>,
        problem: String,
    },
    /// Something is at the path but cannot be read: a folder where a file
    /// belongs, a named pipe, a link that leads nowhere, no permission, an
    /// error while reading.
    Unreadable {
        path: PathBuf,
        frame: Option<usize>,
        problem: String,
    },
    /// An image that needs more memory to decode than this process has.
    TooLarge {
        path: PathBuf,
        frame: Option<usize>,
        problem: String,
    },
    /// The file was read and what it holds is wrong: malformed JSON, a
    /// field missing or out of range, a pose that is no pose, an image that
    /// does not decode.
    Invalid {
        path: PathBuf,
        frame: Option<usize>,
        problem: String,
    },
}

impl SceneError {
    /// A problem with what `path` holds ([`SceneError::Invalid`]).
    pub fn new(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    /// A problem with frame `frame` of the JSON file `path`
    /// ([`SceneError::Invalid`]).
    pub fn in_frame(path: impl AsRef<Path>, frame: usize, problem: impl Into<String>) -> Self {
        Self::Invalid {
            path: path.as_ref().to_path_buf(),
            frame: Some(frame),
            problem: problem.into(),
        }
    }

    /// Nothing at `path` ([`SceneError::NotFound`]).
    pub fn not_found(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self::NotFound {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    /// A folder of no scene format ([`SceneError::NotAScene`]).
    pub fn not_a_scene(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self::NotAScene {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    /// `path` cannot be read ([`SceneError::Unreadable`]).
    pub fn unreadable(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self::Unreadable {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    /// `path` needs more memory than there is ([`SceneError::TooLarge`]).
    pub fn too_large(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Self::TooLarge {
            path: path.as_ref().to_path_buf(),
            frame: None,
            problem: problem.into(),
        }
    }

    /// The file (or folder) at fault.
    pub fn path(&self) -> &Path {
        self.parts().0
    }

    /// The index of the frame within its JSON file, when one frame is at
    /// fault.
    pub fn frame(&self) -> Option<usize> {
        self.parts().1
    }

    /// What is wrong, in plain words.
    pub fn problem(&self) -> &str {
        self.parts().2
    }

    /// The same kind of error, told of frame `frame` of the JSON file
    /// `path` with `problem`: an image's error as the frame listing it.
    pub fn in_frame_of(self, path: impl AsRef<Path>, frame: usize, problem: String) -> Self {
        let (path, frame) = (path.as_ref().to_path_buf(), Some(frame));
        match self {
            Self::NotFound { .. } => Self::NotFound {
                path,
                frame,
                problem,
            },
            Self::NotAScene { .. } => Self::NotAScene {
                path,
                frame,
                problem,
            },
            Self::Unreadable { .. } => Self::Unreadable {
                path,
                frame,
                problem,
            },
            Self::TooLarge { .. } => Self::TooLarge {
                path,
                frame,
                problem,
            },
            Self::Invalid { .. } => Self::Invalid {
                path,
                frame,
                problem,
            },
        }
    }

    fn parts(&self) -> (&Path, Option<usize>, &str) {
        match self {
            Self::NotFound {
                path,
                frame,
                problem,
            }
            | Self::NotAScene {
                path,
                frame,
                problem,
            }
            | Self::Unreadable {
                path,
                frame,
                problem,
            }
            | Self::TooLarge {
                path,
                frame,
                problem,
            }
            | Self::Invalid {
                path,
                frame,
                problem,
            } => (path, *frame, problem),
        }
    }
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (path, frame, problem) = self.parts();
        match frame {
            Some(frame) => write!(f, "{}: frame {}: {}", shown(path), frame, problem),
            None => write!(f, "{}: {}", shown(path), problem),
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
