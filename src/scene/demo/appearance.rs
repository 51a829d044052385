//! The demo photographed as a phone would: each training view at its own
//! exposure and white balance, held-out views as rendered. The true
//! factors are written beside the scene (`appearance_truth.json`), so a
//! test can compare what appearance embeddings learned with them.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::DemoConfig;
use crate::rng::Pcg32;
use crate::scene::{ImageRgba8, Scene, SceneError, SceneResult, to_u8};

/// The file beside `transforms.json` that holds each training view's true
/// exposure and channel gains.
pub const APPEARANCE_TRUTH_FILE: &str = "appearance_truth.json";

/// How far each training view's appearance strays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AppearanceJitter {
    /// Exposure: each view's brightness scaled by 2^(s·u), u uniform in
    /// [−1, 1]: up to this many stops (s) either way.
    pub exposure_stops: f32,
    /// White balance: each channel scaled by (1 + w)^u, u uniform in
    /// [−1, 1] per channel: up to this share (w) either way.
    pub white_balance: f32,
    /// The draws' seed.
    pub seed: u64,
}

/// One training view's true appearance: its linear colours were scaled by
/// `exposure` · `gains[c]` (then clamped to [0, 1]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewAppearance {
    /// The image, relative to the scene's folder.
    pub file_path: String,
    pub exposure: f32,
    pub gains: [f32; 3],
}

/// What [`APPEARANCE_TRUTH_FILE`] holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AppearanceTruth {
    pub exposure_stops: f32,
    pub white_balance: f32,
    pub seed: u64,
    /// The training views, in `train_filenames` order.
    pub train: Vec<ViewAppearance>,
}

impl AppearanceTruth {
    /// Reads `dir`'s [`APPEARANCE_TRUTH_FILE`].
    pub fn read(dir: &Path) -> SceneResult<Self> {
        let path = dir.join(APPEARANCE_TRUTH_FILE);
        let text = std::fs::read_to_string(&path)
            .map_err(|e| SceneError::new(&path, format!("cannot read file: {e}")))?;
        serde_json::from_str(&text)
            .map_err(|e| SceneError::new(&path, format!("malformed appearance truth: {e}")))
    }
}

impl AppearanceJitter {
    /// The appearance of each of `views` training views, drawn from the
    /// seed in pairs: view 2k draws its four u, view 2k + 1 takes their
    /// negatives (an odd last view none). The factors' logarithms then
    /// average to zero over the training views, so the held-out views'
    /// unscaled appearance is the training views' mean, which is what a
    /// model renders them with.
    pub fn draw(&self, views: usize) -> Vec<ViewAppearance> {
        let mut rng = Pcg32::new(self.seed, 0x6a69_7474_6572);
        let mut draws: [f32; 4] = [0.0; 4];
        (0..views)
            .map(|index| {
                if index % 2 == 0 {
                    draws = if index + 1 < views {
                        std::array::from_fn(|_| 2.0 * rng.next_f32() - 1.0)
                    } else {
                        [0.0; 4]
                    };
                } else {
                    draws = draws.map(|u| -u);
                }
                ViewAppearance {
                    file_path: format!("train/r_{index}.png"),
                    exposure: (self.exposure_stops * draws[0]).exp2(),
                    gains: std::array::from_fn(|c| (1.0 + self.white_balance).powf(draws[c + 1])),
                }
            })
            .collect()
    }
}

/// `image` with its colours scaled as `appearance` says, clamped; alpha
/// as it was.
pub fn apply_appearance(image: &ImageRgba8, appearance: &ViewAppearance) -> ImageRgba8 {
    let mut data = image.data.clone();
    for pixel in data.chunks_exact_mut(4) {
        for (value, gain) in pixel[..3].iter_mut().zip(appearance.gains) {
            *value = to_u8(*value as f32 / 255.0 * appearance.exposure * gain);
        }
    }
    ImageRgba8::new(image.width, image.height, data)
}

/// The demo with each training view's appearance jittered, and the truth.
pub fn build_appearance_jitter(
    config: &DemoConfig,
    jitter: &AppearanceJitter,
) -> (Scene, AppearanceTruth) {
    let mut scene = super::build(config);
    let train = jitter.draw(scene.train.len());
    for (frame, appearance) in scene.train.iter_mut().zip(&train) {
        frame.image = apply_appearance(&frame.image, appearance);
    }
    scene.name = "demo-appearance".into();
    let truth = AppearanceTruth {
        exposure_stops: jitter.exposure_stops,
        white_balance: jitter.white_balance,
        seed: jitter.seed,
        train,
    };
    (scene, truth)
}

/// Writes [`build_appearance_jitter`] under `dir` in the instant-ngp
/// layout (`transforms.json` with nerfstudio's split lists,
/// `{train,val,test}/r_N.png`) and the truth beside it
/// ([`APPEARANCE_TRUTH_FILE`]).
pub fn write_appearance_jitter(
    config: &DemoConfig,
    jitter: &AppearanceJitter,
    dir: &Path,
) -> SceneResult<()> {
    let (scene, truth) = build_appearance_jitter(config, jitter);
    super::write_instant_ngp(&scene, dir)?;
    let path = dir.join(APPEARANCE_TRUTH_FILE);
    let text = serde_json::to_string_pretty(&truth)
        .map_err(|e| SceneError::new(&path, format!("cannot encode JSON: {e}")))?;
    crate::files::write_bytes_atomically(&path, text.as_bytes())
        .map_err(|e| SceneError::new(&path, format!("cannot write file: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_draws_stay_within_their_ranges_and_follow_the_seed() {
        let jitter = AppearanceJitter {
            exposure_stops: 1.0,
            white_balance: 0.15,
            seed: 7,
        };
        let views = jitter.draw(200);
        assert_eq!(views, jitter.draw(200));
        assert_ne!(views, AppearanceJitter { seed: 8, ..jitter }.draw(200));
        for view in &views {
            assert!((0.5..=2.0).contains(&view.exposure), "{view:?}");
            assert!(
                view.gains.iter().all(|g| (1.0 / 1.15..=1.15).contains(g)),
                "{view:?}"
            );
        }
        // Their logarithms average to zero: the held-out views' appearance
        // is the mean.
        let mean_stops = views.iter().map(|v| v.exposure.log2()).sum::<f32>() / 200.0;
        let mean_gain = views.iter().map(|v| v.gains[1].ln()).sum::<f32>() / 200.0;
        assert!(mean_stops.abs() < 1e-5 && mean_gain.abs() < 1e-5);
        assert!((views[0].exposure * views[1].exposure - 1.0).abs() < 1e-6);
        // An odd last view is left as rendered.
        let odd = jitter.draw(5);
        assert_eq!((odd[4].exposure, odd[4].gains), (1.0, [1.0; 3]));
        // Both ends of the exposure range are reached.
        let (low, high) = views.iter().fold((2f32, 0f32), |(l, h), v| {
            (l.min(v.exposure), h.max(v.exposure))
        });
        assert!(low < 0.6 && high > 1.8, "{low} {high}");
    }

    #[test]
    fn a_view_is_scaled_per_channel_and_clamped() {
        let image = ImageRgba8::new(1, 1, vec![100, 200, 50, 77]);
        let appearance = ViewAppearance {
            file_path: String::new(),
            exposure: 2.0,
            gains: [1.0, 1.0, 0.5],
        };
        let out = apply_appearance(&image, &appearance);
        assert_eq!(out.data, vec![200, 255, 50, 77]);
    }
}
