//! Checkpoints: named f32 tensors plus a JSON header, written to a temporary
//! file and renamed into place, so a crash mid-write leaves the previous
//! checkpoint intact.
//!
//! Layout: the magic `ZRAKCKPT`, a little-endian u32 format version, a u64
//! header length, the header as JSON, then each tensor's f32 values
//! (little-endian) in the header's order.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::scene::Scene;

const MAGIC: &[u8; 8] = b"ZRAKCKPT";
const FORMAT_VERSION: u32 = 1;

/// What identifies the scene a checkpoint was trained on: loading it with
/// another scene is refused with both named.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SceneIdentity {
    pub name: String,
    pub train_frames: usize,
    pub width: u32,
    pub height: u32,
    /// FNV-1a over every training pose and intrinsics, bit for bit.
    pub cameras_hash: u64,
}

impl SceneIdentity {
    pub fn of(scene: &Scene) -> Self {
        let mut hash = Fnv1a::new();
        // Training at several sizes changes how the scene is trained, not
        // which scene it is: its checkpoints load wherever the scene does.
        let views = scene.photographed_training_views();
        for frame in views {
            for value in frame.camera.camera_to_world.to_cols_array() {
                hash.write(&value.to_le_bytes());
            }
            let k = frame.camera.intrinsics;
            for value in [k.fx, k.fy, k.cx, k.cy] {
                hash.write(&value.to_le_bytes());
            }
            // Only a distorting lens adds to the hash, so that checkpoints
            // of pinhole scenes written before lenses existed still load.
            if k.lens != crate::scene::Lens::Pinhole {
                hash.write(format!("{:?}", k.lens).as_bytes());
            }
        }
        let (width, height) = scene.resolution().unwrap_or((0, 0));
        Self {
            name: scene.name.clone(),
            train_frames: views.len(),
            width,
            height,
            cameras_hash: hash.finish(),
        }
    }
}

impl std::fmt::Display for SceneIdentity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "`{}` ({} training views at {}×{}, cameras {:016x})",
            self.name, self.train_frames, self.width, self.height, self.cameras_hash
        )
    }
}

struct Fnv1a(u64);

impl Fnv1a {
    fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    fn finish(&self) -> u64 {
        self.0
    }
}

/// A checkpoint in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct Checkpoint {
    /// Model name, step, configuration, scene identity and anything else
    /// small; free-form JSON owned by the trainer.
    pub header: serde_json::Value,
    pub tensors: Vec<(String, Vec<f32>)>,
}

/// A checkpoint could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{path}: {problem}")]
    Io { path: PathBuf, problem: String },
    #[error("{path}: not a zrak checkpoint ({problem})")]
    Format { path: PathBuf, problem: String },
}

#[derive(Serialize, Deserialize)]
struct StoredHeader {
    header: serde_json::Value,
    tensors: Vec<(String, usize)>,
}

impl Checkpoint {
    pub fn tensor(&self, name: &str) -> Option<&[f32]> {
        self.tensors
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, values)| values.as_slice())
    }

    /// Writes to `path` through a temporary file in the same folder and a
    /// rename, so readers see either the old file or the complete new one.
    pub fn save(&self, path: &Path) -> Result<(), CheckpointError> {
        let io = |problem: String| CheckpointError::Io {
            path: path.to_path_buf(),
            problem,
        };
        let temporary = path.with_extension("tmp");
        let stored = StoredHeader {
            header: self.header.clone(),
            tensors: self
                .tensors
                .iter()
                .map(|(name, values)| (name.clone(), values.len()))
                .collect(),
        };
        let header = serde_json::to_vec(&stored).map_err(|e| io(e.to_string()))?;
        let write = || -> std::io::Result<()> {
            let mut out = BufWriter::new(File::create(&temporary)?);
            out.write_all(MAGIC)?;
            out.write_all(&FORMAT_VERSION.to_le_bytes())?;
            out.write_all(&(header.len() as u64).to_le_bytes())?;
            out.write_all(&header)?;
            for (_, values) in &self.tensors {
                out.write_all(bytemuck::cast_slice(values))?;
            }
            let file = out.into_inner().map_err(|e| e.into_error())?;
            file.sync_all()
        };
        if let Err(e) = write() {
            let _ = std::fs::remove_file(&temporary);
            return Err(io(format!("cannot write checkpoint: {e}")));
        }
        std::fs::rename(&temporary, path)
            .map_err(|e| io(format!("cannot move the new checkpoint into place: {e}")))
    }

    pub fn load(path: &Path) -> Result<Self, CheckpointError> {
        let format = |problem: &str| CheckpointError::Format {
            path: path.to_path_buf(),
            problem: problem.to_string(),
        };
        let file = File::open(path).map_err(|e| CheckpointError::Io {
            path: path.to_path_buf(),
            problem: format!("cannot open checkpoint: {e}"),
        })?;
        // Lengths read from the file are checked against what it holds
        // before anything is allocated for them: a damaged length must give
        // an error, not an allocation failure that aborts the process.
        let file_length = file
            .metadata()
            .map_err(|e| CheckpointError::Io {
                path: path.to_path_buf(),
                problem: format!("cannot read checkpoint: {e}"),
            })?
            .len();
        let mut remaining = file_length.saturating_sub(20);
        let mut input = BufReader::new(file);
        let mut magic = [0u8; 8];
        input
            .read_exact(&mut magic)
            .map_err(|_| format("file too short"))?;
        if &magic != MAGIC {
            return Err(format("wrong magic bytes"));
        }
        let mut word = [0u8; 4];
        input
            .read_exact(&mut word)
            .map_err(|_| format("file too short"))?;
        let version = u32::from_le_bytes(word);
        if version != FORMAT_VERSION {
            return Err(format(&format!(
                "format version {version}, this zrak reads {FORMAT_VERSION}"
            )));
        }
        let mut long = [0u8; 8];
        input
            .read_exact(&mut long)
            .map_err(|_| format("file too short"))?;
        let header_length = u64::from_le_bytes(long);
        if header_length > remaining.min(64 << 20) {
            return Err(format(&format!(
                "header length {header_length} is more than the file holds"
            )));
        }
        remaining -= header_length;
        let mut header = vec![0u8; header_length as usize];
        input
            .read_exact(&mut header)
            .map_err(|_| format("truncated header"))?;
        let stored: StoredHeader =
            serde_json::from_slice(&header).map_err(|e| format(&format!("bad header: {e}")))?;
        let mut tensors = Vec::with_capacity(stored.tensors.len());
        for (name, length) in stored.tensors {
            let bytes = (length as u64).checked_mul(4).filter(|&b| b <= remaining);
            let Some(bytes) = bytes else {
                return Err(format(&format!(
                    "truncated in tensor `{name}` ({length} values, {} bytes left)",
                    remaining
                )));
            };
            remaining -= bytes;
            let mut values = vec![0f32; length];
            input
                .read_exact(bytemuck::cast_slice_mut(&mut values))
                .map_err(|_| format(&format!("truncated in tensor `{name}`")))?;
            tensors.push((name, values));
        }
        Ok(Self {
            header: stored.header,
            tensors,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Checkpoint {
        Checkpoint {
            header: serde_json::json!({"model": "ngp", "step": 42}),
            tensors: vec![
                ("weights".into(), vec![1.0, -2.5, f32::MIN_POSITIVE, 3e30]),
                ("empty".into(), vec![]),
            ],
        }
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        assert_eq!(Checkpoint::load(&path).unwrap(), sample());
        assert!(!path.with_extension("tmp").exists());
    }

    #[test]
    fn failed_write_keeps_the_previous_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        // A directory where the temporary file should go makes the write fail.
        std::fs::create_dir(path.with_extension("tmp")).unwrap();
        let mut newer = sample();
        newer.header = serde_json::json!({"step": 43});
        let error = newer.save(&path).unwrap_err().to_string();
        assert!(
            error.contains("checkpoint.zrak") && error.contains("cannot write"),
            "{error}"
        );
        assert_eq!(Checkpoint::load(&path).unwrap(), sample());
    }

    #[test]
    fn truncated_or_foreign_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("checkpoint.zrak");
        sample().save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 3]).unwrap();
        let error = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(error.contains("truncated in tensor `weights`"), "{error}");
        std::fs::write(&path, b"PNG and other things").unwrap();
        let error = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(error.contains("not a zrak checkpoint"), "{error}");
    }
}
