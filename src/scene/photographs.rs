//! What a scene's photographs call for beyond their space: per-image
//! appearance (exposure and white balance that change from view to view),
//! camera refinement (poses estimated by structure from motion) and masks
//! (pixels a capture marks as not belonging to the scene). Renders need
//! none of them; a phone capture often needs all three. Each choice is
//! made here, from what the scene holds, with sentences that give its
//! numbers, and each but the masks can be overridden (`--appearance`,
//! `--refine-cameras`); masks are used whenever they exist.
//!
//! Appearance is decided from the photographs' EXIF where every training
//! image has it (exposure time × ISO / f-number², and whether white balance
//! was automatic); otherwise from the images themselves: views that
//! overlap show nearly the same content, so the difference of their mean
//! brightness and colour is mostly the camera's exposure and white balance.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::exif::{Exposure, read_exposure};
use super::{Frame, Scene};

/// A choice the analysis makes unless told (`--appearance`,
/// `--refine-cameras`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Switch {
    /// As the scene calls for.
    #[default]
    Auto,
    On,
    Off,
}

impl Switch {
    pub fn name(self) -> &'static str {
        match self {
            Switch::Auto => "auto",
            Switch::On => "on",
            Switch::Off => "off",
        }
    }
}

/// One part switched on or off, and why.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Choice {
    pub on: bool,
    /// Sentences with the numbers behind it, the deciding one first; when
    /// chosen by hand the first says so and the rest are the analysis's.
    pub reasons: Vec<String>,
    /// Chosen with a flag rather than by the analysis.
    pub chosen_by_hand: bool,
}

impl Choice {
    fn decided(on: bool, reasons: Vec<String>) -> Self {
        Self {
            on,
            reasons,
            chosen_by_hand: false,
        }
    }

    /// The analysis's choice unless `switch` names one, with `flag` the
    /// option that does.
    fn unless(self, switch: Switch, flag: &str) -> Self {
        let on = match switch {
            Switch::Auto => return self,
            Switch::On => true,
            Switch::Off => false,
        };
        let mut reasons = vec![format!(
            "chosen with {flag} {} (the scene alone would have it {})",
            switch.name(),
            if self.on { "on" } else { "off" }
        )];
        reasons.extend(self.reasons);
        Self {
            on,
            reasons,
            chosen_by_hand: true,
        }
    }

    /// "on" or "off", and how it was chosen.
    pub fn summary(&self) -> String {
        format!(
            "{} ({})",
            if self.on { "on" } else { "off" },
            if self.chosen_by_hand {
                "chosen by hand"
            } else {
                "from the scene"
            }
        )
    }
}

/// The switches a command was given.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Switches {
    pub appearance: Switch,
    pub refine_cameras: Switch,
}

/// What the photographs call for.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct PhotographAnalysis {
    /// A learned appearance vector per training image.
    pub appearance: Choice,
    /// A learned pose correction per training image.
    pub refine_cameras: Choice,
    /// Masks leave pixels out of training and scores (never by hand).
    pub masks: Choice,
}

/// EXIF exposures that span more than this many stops differ: a third of
/// a stop is the smallest step a camera's exposure compensation takes.
pub const EXIF_SPREAD_STOPS: f64 = 1.0 / 3.0;

/// Overlapping views whose mean brightness differs by more than this many
/// stops (median over the pairs) were exposed differently. Renders of one
/// exposure differ by what their content does between neighbouring views:
/// 0.045 stops on lego_400, 0.08 on the demo (objects of strong colours,
/// views 20° apart); ±1 stop of jitter gives about 0.6.
pub const BRIGHTNESS_SPREAD_STOPS: f64 = 0.2;

/// Overlapping views whose colour balance (red and blue against green)
/// differs by more than this share (median over the pairs) were white
/// balanced differently: the same renders differ by 1.0 % (lego_400) and
/// 2.2 % (the demo); ±15 % of jitter per channel gives about 10 %.
pub const COLOUR_SPREAD: f64 = 0.05;

/// Two views overlap when their optical axes are within this many
/// degrees …
const OVERLAP_MAX_ANGLE_DEG: f64 = 20.0;

/// … and their centres within this share of the cameras' extent.
const OVERLAP_MAX_DISTANCE: f64 = 0.2;

/// Views compared are at least this share of the capture apart in the
/// images' order (1/10: a tenth of the images between them).
const ORDER_GAP_DIVISOR: usize = 10;

/// Fewer overlapping pairs than this say nothing about exposure.
const FEWEST_PAIRS: usize = 3;

/// A view's pixels that count towards its mean: opaque (alpha at least
/// half) and not masked. A view with fewer than this share is left out.
const FEWEST_COUNTED_SHARE: f64 = 0.01;

/// Decides what `scene`'s photographs call for (see the module notes),
/// unless `switches` say.
pub fn analyse(scene: &Scene, switches: Switches) -> PhotographAnalysis {
    PhotographAnalysis {
        appearance: appearance(scene).unless(switches.appearance, "--appearance"),
        refine_cameras: refine_cameras(scene).unless(switches.refine_cameras, "--refine-cameras"),
        masks: masks(scene),
    }
}

fn refine_cameras(scene: &Scene) -> Choice {
    let evidence = if scene.poses.evidence.is_empty() {
        "nothing says where the cameras came from: they are taken as exact".to_string()
    } else {
        scene.poses.evidence.clone()
    };
    let verdict = if scene.poses.estimated {
        "estimated poses are off by a fraction of a pixel to a few pixels: a correction per \
         image is learned with the field"
    } else {
        "exact poses need no correction"
    };
    Choice::decided(scene.poses.estimated, vec![evidence, verdict.into()])
}

fn masks(scene: &Scene) -> Choice {
    let masked = |frames: &[Frame]| frames.iter().filter(|f| f.mask.is_some()).count();
    let train = scene.photographed_training_views();
    let in_train = masked(train);
    let held_out = masked(&scene.val) + masked(&scene.test);
    if in_train + held_out == 0 {
        return Choice::decided(false, vec!["no image has a mask".into()]);
    }
    Choice::decided(
        true,
        vec![format!(
            "{in_train} of {} training images and {held_out} held-out images have masks: their \
             masked pixels are never training targets and are left out of the scores",
            train.len()
        )],
    )
}

fn appearance(scene: &Scene) -> Choice {
    let views = scene.photographed_training_views();
    if views.len() < 2 {
        return Choice::decided(
            false,
            vec!["fewer than two training images: there is no other exposure to match".into()],
        );
    }
    let mut reasons = Vec::new();
    if let Some(exif) = exif_exposures(views) {
        let (low, high) = exif
            .iter()
            .filter_map(Exposure::stops)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| {
                (lo.min(s), hi.max(s))
            });
        let spread = high - low;
        if spread > EXIF_SPREAD_STOPS {
            return Choice::decided(
                true,
                vec![format!(
                    "EXIF: exposure (time × ISO / f-number²) spans {spread:.2} stops across the \
                     {} training images (over {EXIF_SPREAD_STOPS:.2}): each image gets an \
                     appearance vector",
                    views.len()
                )],
            );
        }
        if exif.iter().all(|e| e.auto_white_balance == Some(false)) {
            return Choice::decided(
                false,
                vec![format!(
                    "EXIF: exposure within {spread:.2} stops and white balance manual in all {} \
                     training images: one appearance serves them all",
                    views.len()
                )],
            );
        }
        reasons.push(format!(
            "EXIF: exposure within {spread:.2} stops, but white balance automatic or not \
             recorded: the images' colours decide"
        ));
    }
    let Some(spread) = measured_spread(views) else {
        reasons.insert(
            0,
            "no two training views overlap closely enough to compare their brightness: \
             appearance stays off"
                .into(),
        );
        return Choice::decided(false, reasons);
    };
    let differs =
        spread.brightness_stops > BRIGHTNESS_SPREAD_STOPS || spread.colour_share > COLOUR_SPREAD;
    reasons.insert(
        0,
        format!(
            "overlapping views differ in mean brightness by {:.3} stops and in colour balance \
             by {:.1} % (medians of {} pairs; {} over {BRIGHTNESS_SPREAD_STOPS} stops or {:.0} \
             %): {}",
            spread.brightness_stops,
            100.0 * spread.colour_share,
            spread.pairs,
            if differs { "at least one" } else { "neither" },
            100.0 * COLOUR_SPREAD,
            if differs {
                "exposure or white balance changes from view to view, so each image gets an \
                 appearance vector"
            } else {
                "one appearance serves every view"
            }
        ),
    );
    Choice::decided(differs, reasons)
}

/// Every training image's EXIF exposure, where every one records its time
/// and ISO.
fn exif_exposures(views: &[Frame]) -> Option<Vec<Exposure>> {
    if views.iter().any(|f| f.image_path.as_os_str().is_empty()) {
        return None;
    }
    let exposures: Vec<Option<Exposure>> = views
        .par_iter()
        .map(|f| read_exposure(&f.image_path).filter(|e| e.stops().is_some()))
        .collect();
    exposures.into_iter().collect()
}

/// How much overlapping views differ in brightness and colour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredSpread {
    /// Median |log2| of the ratio of the pairs' mean luminance.
    pub brightness_stops: f64,
    /// Median of the larger of the red/green and blue/green ratios' change,
    /// as a share (0.05: 5 %).
    pub colour_share: f64,
    pub pairs: usize,
}

/// [`MeasuredSpread`] of `views`, each paired with its nearest overlapping
/// view; `None` with fewer than [`FEWEST_PAIRS`] pairs.
pub fn measured_spread(views: &[Frame]) -> Option<MeasuredSpread> {
    let means: Vec<Option<[f64; 3]>> = views.par_iter().map(mean_colour).collect();
    let centres: Vec<glam::DVec3> = views
        .iter()
        .map(|f| f.camera.camera_to_world.w_axis.truncate().as_dvec3())
        .collect();
    let axes: Vec<glam::DVec3> = views
        .iter()
        .map(|f| {
            (-f.camera.camera_to_world.z_axis.truncate().as_dvec3()).normalize_or(glam::DVec3::Z)
        })
        .collect();
    let extent = centres
        .iter()
        .flat_map(|a| centres.iter().map(move |b| a.distance(*b)))
        .fold(0.0, f64::max)
        .max(f64::MIN_POSITIVE);
    let max_angle = OVERLAP_MAX_ANGLE_DEG.to_radians();
    let order_gap = (views.len() / ORDER_GAP_DIVISOR).max(1);
    let mut brightness = Vec::new();
    let mut colour = Vec::new();
    for i in 0..views.len() {
        let Some(a) = means[i] else { continue };
        // The nearest view by position and direction together, among
        // those taken apart in the capture's order (a video's next frame
        // shares its exposure whatever the camera does over the minutes).
        let nearest = (0..views.len())
            .filter(|&j| i.abs_diff(j) >= order_gap && means[j].is_some())
            .map(|j| {
                let angle = axes[i].dot(axes[j]).clamp(-1.0, 1.0).acos();
                let distance = centres[i].distance(centres[j]) / extent;
                (j, angle, distance)
            })
            .filter(|&(_, angle, distance)| angle <= max_angle && distance <= OVERLAP_MAX_DISTANCE)
            .min_by(|x, y| (x.1 / max_angle + x.2).total_cmp(&(y.1 / max_angle + y.2)));
        let Some((j, _, _)) = nearest else { continue };
        let b = means[j].expect("filtered to views with a mean");
        let luminance = |c: [f64; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
        brightness.push((luminance(a) / luminance(b)).log2().abs());
        let balance = |c: [f64; 3], k: usize| (c[k] / c[1]).ln();
        let change = [0, 2]
            .map(|k| (balance(a, k) - balance(b, k)).abs().exp_m1())
            .into_iter()
            .fold(0.0, f64::max);
        colour.push(change);
    }
    if brightness.len() < FEWEST_PAIRS {
        return None;
    }
    Some(MeasuredSpread {
        brightness_stops: median(&mut brightness),
        colour_share: median(&mut colour),
        pairs: brightness.len(),
    })
}

/// A view's mean colour over its counted pixels (see
/// [`FEWEST_COUNTED_SHARE`]), each channel at least one level of 255 so
/// ratios stay finite.
fn mean_colour(frame: &Frame) -> Option<[f64; 3]> {
    let image = &frame.image;
    let mut sum = [0u64; 3];
    let mut counted = 0u64;
    for (index, pixel) in image.data.chunks_exact(4).enumerate() {
        if pixel[3] < 128 {
            continue;
        }
        if let Some(mask) = &frame.mask
            && !mask.counting()[index]
        {
            continue;
        }
        for c in 0..3 {
            sum[c] += pixel[c] as u64;
        }
        counted += 1;
    }
    let total = image.width as u64 * image.height as u64;
    if counted == 0 || (counted as f64) < FEWEST_COUNTED_SHARE * total as f64 {
        return None;
    }
    Some(sum.map(|s| (s as f64 / counted as f64 / 255.0).max(1.0 / 255.0)))
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

#[cfg(test)]
mod tests;
