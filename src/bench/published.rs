//! What the three papers report on the NeRF-synthetic (Blender) scenes, for
//! the report to set beside zrak's own figures. These are facts carried
//! over from the papers, each with its source; they were measured on the
//! 200 test views at 800×800 after far longer training on GPUs, so they
//! are a ceiling to read zrak's numbers against, not a like-for-like score.

use serde::Serialize;

use crate::field::ModelKind;

/// The eight NeRF-synthetic scenes, in the papers' column order.
pub const SCENES: [&str; 8] = [
    "chair",
    "drums",
    "ficus",
    "hotdog",
    "lego",
    "materials",
    "mic",
    "ship",
];

/// One paper's figures.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Published {
    pub model: ModelKind,
    /// Test-set PSNR per scene, in [`SCENES`] order.
    pub psnr: [f64; 8],
    /// Test-set SSIM per scene, when the paper reports it.
    pub ssim: Option<[f64; 8]>,
    /// The means over the eight scenes as the paper prints them (rounded
    /// from unrounded figures, so not always the mean of the rounded ones).
    pub mean_psnr: f64,
    pub mean_ssim: Option<f64>,
    /// How long the paper trained.
    pub training: &'static str,
    pub source: &'static str,
}

/// The papers' figures, NeRF, Mip-NeRF and Instant-NGP.
pub const PUBLISHED: [Published; 3] = [
    Published {
        model: ModelKind::Nerf,
        psnr: [33.00, 25.01, 30.13, 36.18, 32.54, 29.62, 32.91, 28.65],
        ssim: Some([0.967, 0.925, 0.964, 0.974, 0.961, 0.949, 0.980, 0.856]),
        mean_psnr: 31.01,
        mean_ssim: Some(0.947),
        training: "100–300k iterations, 1–2 days on one V100 GPU",
        source: "Mildenhall et al., NeRF: Representing Scenes as Neural Radiance Fields for \
                 View Synthesis, ECCV 2020, per-scene results on the Realistic Synthetic 360° \
                 scenes (supplementary material)",
    },
    Published {
        model: ModelKind::MipNerf,
        psnr: [35.14, 25.48, 33.29, 37.48, 35.70, 30.71, 36.51, 30.41],
        ssim: Some([0.981, 0.932, 0.980, 0.982, 0.978, 0.959, 0.991, 0.882]),
        mean_psnr: 33.09,
        mean_ssim: Some(0.961),
        training: "1 M iterations of 4096 rays",
        source: "Barron et al., Mip-NeRF: A Multiscale Representation for Anti-Aliasing \
                 Neural Radiance Fields, ICCV 2021, single-scale Blender results per scene \
                 (supplementary material)",
    },
    Published {
        model: ModelKind::Ngp,
        psnr: [35.00, 26.02, 33.51, 37.40, 36.39, 29.78, 36.22, 31.10],
        ssim: None,
        mean_psnr: 33.18,
        mean_ssim: None,
        training: "5 minutes on one RTX 3090 GPU",
        source: "Müller et al., Instant Neural Graphics Primitives with a Multiresolution \
                 Hash Encoding, SIGGRAPH 2022, Table 2 (\"Ours: Hash\", 5 min)",
    },
];

/// The NeRF-synthetic scene a folder name stands for (`lego_400` → `lego`),
/// if any: the name, or its part before the first `_` or `-`.
pub fn blender_scene(name: &str) -> Option<&'static str> {
    let lower = name.to_ascii_lowercase();
    let stem = lower.split(['_', '-']).next().unwrap_or(&lower);
    SCENES.iter().copied().find(|s| *s == stem)
}

/// The paper's figures for `model` on `scene` (a NeRF-synthetic scene
/// name): PSNR and, when reported, SSIM.
pub fn figures(model: ModelKind, scene: &str) -> Option<(f64, Option<f64>, &'static Published)> {
    let index = SCENES.iter().position(|s| *s == scene)?;
    let paper = PUBLISHED.iter().find(|p| p.model == model)?;
    Some((paper.psnr[index], paper.ssim.map(|s| s[index]), paper))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_papers_means_match_their_scenes() {
        // Each paper prints its mean beside the per-scene figures: the mean
        // of the figures here must round to it, a check that none was
        // mistyped.
        for paper in &PUBLISHED {
            let mean = paper.psnr.iter().sum::<f64>() / 8.0;
            assert!(
                (mean - paper.mean_psnr).abs() <= 0.006,
                "{:?}: {mean}",
                paper.model
            );
            if let (Some(ssim), Some(printed)) = (paper.ssim, paper.mean_ssim) {
                let mean = ssim.iter().sum::<f64>() / 8.0;
                assert!(
                    (mean - printed).abs() <= 0.0006,
                    "{:?}: {mean}",
                    paper.model
                );
            }
        }
    }

    #[test]
    fn folder_names_map_to_blender_scenes() {
        assert_eq!(blender_scene("lego_400"), Some("lego"));
        assert_eq!(blender_scene("Ship"), Some("ship"));
        assert_eq!(blender_scene("demo"), None);
        assert_eq!(blender_scene("legoland"), None);
        let (psnr, ssim, paper) = figures(ModelKind::Nerf, "lego").unwrap();
        assert_eq!((psnr, ssim), (32.54, Some(0.961)));
        assert!(paper.source.contains("Mildenhall"));
        assert_eq!(figures(ModelKind::Ngp, "lego").unwrap().1, None);
    }
}
