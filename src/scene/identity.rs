//! What identifies the scene a model was trained on, so that a checkpoint
//! loaded with another scene is refused with both named.

use serde::{Deserialize, Serialize};

use super::Scene;

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
            if k.lens != super::Lens::Pinhole {
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

/// FNV-1a, 64 bits.
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
