//! What a scene calls for, decided in one place: a bounded object (cameras
//! around a region, a known background), an unbounded scene (the
//! background runs past the cameras) or a forward-facing capture (cameras
//! on a plane, all looking one way), with the reasons, each a sentence with
//! the numbers a user can check.
//!
//! The analysis reads only what a loaded scene holds: the cameras' poses
//! and fields of view, whether the photographs are transparent anywhere,
//! the unit cube's `aabb_scale` and, for a COLMAP model, how far its sparse
//! points lie ([`SparsePoints`]). The choice it makes is a default:
//! [`Scene::with_space`] overrides it (`--space` on the commands).

use glam::{DMat3, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Camera, Scene};

/// The kind of space a scene's content fills.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum SceneSpace {
    /// A bounded object: the content lies in a box the cameras surround.
    Object,
    /// The content runs past the cameras (walls, the horizon, the sky).
    Unbounded,
    /// Cameras on a plane, all looking one way: the content is seen from
    /// one side only.
    ForwardFacing,
}

impl SceneSpace {
    /// The name `--space` and `run.json` give it.
    pub fn name(self) -> &'static str {
        match self {
            SceneSpace::Object => "object",
            SceneSpace::Unbounded => "unbounded",
            SceneSpace::ForwardFacing => "forward-facing",
        }
    }
}

impl std::fmt::Display for SceneSpace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The space a scene is treated as, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SpaceAnalysis {
    pub space: SceneSpace,
    /// Sentences with the numbers behind the choice, the deciding one
    /// first. When overridden, the first says so and the rest are the
    /// analysis's own.
    pub reasons: Vec<String>,
    /// Whether the space was chosen by hand ([`Scene::with_space`]) rather
    /// than by the analysis.
    pub overridden: bool,
}

impl Default for SpaceAnalysis {
    /// A bounded object, unexplained: what a scene holds until it is
    /// analysed (every loader and demo builder analyses it before
    /// returning).
    fn default() -> Self {
        Self {
            space: SceneSpace::Object,
            reasons: Vec::new(),
            overridden: false,
        }
    }
}

/// How far a COLMAP model's sparse points lie from the cameras' centre
/// (the mean camera position), in the scene's world units: the loader keeps
/// this summary rather than the points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SparsePoints {
    pub count: usize,
    pub median_distance: f32,
    /// The distance within which 90 % of the points lie.
    pub far_distance: f32,
}

impl SparsePoints {
    /// The summary of `points` (world units) around the cameras at
    /// `camera_positions`, or `None` when there are no points or cameras.
    pub fn measure(points: &[DVec3], camera_positions: &[DVec3]) -> Option<Self> {
        if points.is_empty() || camera_positions.is_empty() {
            return None;
        }
        let centre =
            camera_positions.iter().copied().sum::<DVec3>() / camera_positions.len() as f64;
        let mut distances: Vec<f64> = points.iter().map(|p| p.distance(centre)).collect();
        distances.sort_by(f64::total_cmp);
        let quantile = |share: f64| {
            let index =
                ((distances.len() as f64 * share).ceil() as usize).clamp(1, distances.len());
            distances[index - 1] as f32
        };
        Some(Self {
            count: points.len(),
            median_distance: quantile(0.5),
            far_distance: quantile(FAR_POINT_SHARE),
        })
    }
}

/// The share of sparse points [`SparsePoints::far_distance`] holds.
const FAR_POINT_SHARE: f64 = 0.9;

/// Sparse points count as far beyond the cameras when
/// [`SparsePoints::far_distance`] is this many times the cameras' mean
/// distance from their centre: an object's points lie within the ring of
/// cameras (well under 1×), a room's walls and a garden's trees beyond it.
const FAR_POINT_FACTOR: f32 = 2.0;

/// A forward-facing capture's cameras all look within this many degrees of
/// their mean direction. LLFF's captures (NeRF paper, section 5.1) turn
/// their phone by well under 30°; cameras around an object spread over
/// 90° and more.
const FORWARD_MAX_ANGLE_DEG: f64 = 40.0;

/// A forward-facing capture's cameras lie on a plane across their mean
/// direction: their reach along it at most this share of their reach
/// across it. Cameras on an arc around an object of ±40° reach 0.17 as
/// deep as across, so a rig that looks one way stays under this.
const FORWARD_MAX_DEPTH_SHARE: f64 = 0.25;

/// Cameras look inward when this share of them have the point nearest to
/// all their optical axes inside their picture: a hand-held capture
/// around an object loses it from a few frames.
const INWARD_SHARE: f64 = 0.8;

/// Below this many cameras their arrangement says nothing.
const FEWEST_CAMERAS: usize = 3;

/// Decides what `scene` calls for from its cameras, its photographs' alpha,
/// its `aabb_scale` and its sparse points (see the module notes).
pub fn analyse(scene: &Scene) -> SpaceAnalysis {
    let cameras: Vec<Camera> = scene
        .photographed_training_views()
        .iter()
        .chain(&scene.val)
        .chain(&scene.test)
        .map(|frame| frame.camera)
        .collect();
    let transparent = if scene.has_alpha {
        Some(transparent_share(scene))
    } else {
        None
    };
    decide(&Evidence {
        layout: CameraLayout::measure(&cameras),
        transparent,
        aabb_scale: scene.unit_cube.aabb_scale,
        sparse_points: scene.sparse_points,
    })
}

impl Scene {
    /// The scene treated as `space` whatever the analysis found: the
    /// analysis's reasons are kept, after one saying it was overridden.
    pub fn with_space(mut self, space: SceneSpace) -> Scene {
        let analysis = &mut self.space;
        let found = analysis.space;
        if analysis.overridden && !analysis.reasons.is_empty() {
            // Overridden before: that note goes, the analysis's reasons stay.
            analysis.reasons.remove(0);
        }
        let note = if analysis.overridden {
            format!("chosen by hand as {space}")
        } else if space == found {
            format!("chosen by hand as {space}, as the analysis found")
        } else {
            format!("chosen by hand as {space}; the analysis found {found}")
        };
        analysis.reasons.insert(0, note);
        analysis.space = space;
        analysis.overridden = true;
        self
    }
}

/// The share of all pixels, over every view, that are not fully opaque.
fn transparent_share(scene: &Scene) -> f64 {
    let (transparent, total) = scene
        .frames()
        .collect::<Vec<_>>()
        .par_iter()
        .map(|frame| {
            let data = &frame.image.data;
            let transparent = data.chunks_exact(4).filter(|p| p[3] < 255).count();
            (transparent, data.len() / 4)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if total == 0 {
        0.0
    } else {
        transparent as f64 / total as f64
    }
}

/// What the decision reads.
struct Evidence {
    layout: Option<CameraLayout>,
    /// `None`: no image has an alpha channel; else the share of pixels not
    /// fully opaque.
    transparent: Option<f64>,
    aabb_scale: f32,
    sparse_points: Option<SparsePoints>,
}

impl Evidence {
    /// What the photographs' alpha says, for sentences that go on "…, but".
    fn no_alpha(&self) -> &'static str {
        match self.transparent {
            None => "no image has alpha",
            Some(_) => "every image is opaque everywhere",
        }
    }

    /// Why the sparse points say the content runs past the cameras, if
    /// they do.
    fn far_points(&self, camera_distance: f64) -> Option<String> {
        let points = self.sparse_points?;
        let ratio = points.far_distance as f64 / camera_distance.max(1e-12);
        (ratio > FAR_POINT_FACTOR as f64).then(|| {
            format!(
                "a tenth of the {} sparse points lie farther than {:.2} units from the \
                 cameras' centre, {ratio:.1} times the cameras' own distance from it ({:.2}): \
                 content runs far beyond the cameras",
                points.count, points.far_distance, camera_distance
            )
        })
    }
}

/// The decision (see the module notes), with its reasons.
fn decide(evidence: &Evidence) -> SpaceAnalysis {
    let decided = |space, reasons| SpaceAnalysis {
        space,
        reasons,
        overridden: false,
    };
    let aabb_scale = evidence.aabb_scale;
    let layout_sentence = evidence.layout.as_ref().map(CameraLayout::describe);

    if let Some(share) = evidence.transparent.filter(|&share| share > 0.0) {
        let mut reasons = vec![format!(
            "{} of the images' pixels are transparent: the background is known, so the \
             content ends where the alpha does",
            percent(share)
        )];
        reasons.extend(layout_sentence);
        return decided(SceneSpace::Object, reasons);
    }

    let Some(layout) = &evidence.layout else {
        // Too few cameras to read an arrangement: the box says it.
        let mut reasons = vec![format!(
            "too few cameras (fewer than {FEWEST_CAMERAS}) to tell how they are arranged"
        )];
        let space = if aabb_scale > 1.0 {
            reasons.insert(
                0,
                format!(
                    "{} and aabb_scale is {aabb_scale}: the background runs beyond the box \
                     of the cameras",
                    evidence.no_alpha()
                ),
            );
            SceneSpace::Unbounded
        } else {
            reasons.insert(
                0,
                format!("aabb_scale is {aabb_scale}: the content lies in the scene's box"),
            );
            SceneSpace::Object
        };
        return decided(space, reasons);
    };

    if let Some(sentence) = layout.forward_facing() {
        return decided(SceneSpace::ForwardFacing, vec![sentence]);
    }
    let not_forward = layout.why_not_forward_facing();

    match layout.inward_focus() {
        Some(focus) => {
            let mut reasons = Vec::new();
            if aabb_scale > 1.0 {
                reasons.push(format!(
                    "the {} cameras look inward at a point {:.2} units from their centre, but \
                     {} and aabb_scale is {aabb_scale}: the background runs beyond the cameras",
                    layout.count,
                    focus.from_centre,
                    evidence.no_alpha()
                ));
            }
            reasons.extend(evidence.far_points(layout.mean_distance));
            if reasons.is_empty() {
                reasons.push(format!(
                    "{}, and aabb_scale is {aabb_scale}: the content lies in the box they \
                     surround ({}, so the background is learned as part of it)",
                    layout.describe(),
                    evidence.no_alpha()
                ));
                reasons.push(not_forward);
                decided(SceneSpace::Object, reasons)
            } else {
                reasons.push(not_forward);
                decided(SceneSpace::Unbounded, reasons)
            }
        }
        None => {
            let mut reasons = vec![format!(
                "{}: they look around rather than at one region, as cameras inside the \
                 content do, and {}",
                layout.describe(),
                evidence.no_alpha()
            )];
            reasons.extend(evidence.far_points(layout.mean_distance));
            reasons.push(not_forward);
            decided(SceneSpace::Unbounded, reasons)
        }
    }
}

/// A share as a percentage, with a decimal where it is under 10 %.
fn percent(share: f64) -> String {
    let value = 100.0 * share;
    if value < 10.0 {
        format!("{value:.1} %")
    } else {
        format!("{value:.0} %")
    }
}

/// Where the cameras are and where they look.
struct CameraLayout {
    count: usize,
    /// The cameras' mean distance from their centre (the mean position).
    mean_distance: f64,
    /// The largest angle between a camera's viewing direction and their
    /// mean direction, in degrees (180 when the directions cancel out).
    widest_angle_deg: f64,
    /// The cameras' largest distance from their centre along their mean
    /// direction, and across it.
    along: f64,
    across: f64,
    focus: Option<Focus>,
}

/// The point nearest to every camera's optical axis (least squares), and
/// how the cameras see it.
struct Focus {
    /// Its distance from the cameras' centre.
    from_centre: f64,
    /// How many cameras have it inside their picture.
    seen_by: usize,
    /// The nearest and farthest camera from it.
    nearest: f64,
    farthest: f64,
}

impl CameraLayout {
    /// `None` for fewer than [`FEWEST_CAMERAS`] cameras.
    fn measure(cameras: &[Camera]) -> Option<Self> {
        if cameras.len() < FEWEST_CAMERAS {
            return None;
        }
        let count = cameras.len();
        let positions: Vec<DVec3> = cameras.iter().map(|c| c.position().as_dvec3()).collect();
        let forwards: Vec<DVec3> = cameras
            .iter()
            .map(|c| c.forward().as_dvec3().normalize_or_zero())
            .collect();
        let centre = positions.iter().copied().sum::<DVec3>() / count as f64;
        let mean_distance =
            positions.iter().map(|p| p.distance(centre)).sum::<f64>() / count as f64;
        let summed = forwards.iter().copied().sum::<DVec3>();
        let (widest_angle_deg, along, across) = if summed.length() > 1e-6 * count as f64 {
            let mean_forward = summed.normalize();
            let widest = forwards
                .iter()
                .map(|f| f.dot(mean_forward).clamp(-1.0, 1.0).acos().to_degrees())
                .fold(0.0, f64::max);
            let (mut along, mut across) = (0.0f64, 0.0f64);
            for p in &positions {
                let offset = *p - centre;
                let depth = offset.dot(mean_forward);
                along = along.max(depth.abs());
                across = across.max((offset - depth * mean_forward).length());
            }
            (widest, along, across)
        } else {
            (180.0, 0.0, 0.0)
        };
        let focus = nearest_to_axes(&positions, &forwards).map(|point| {
            let seen_by = cameras
                .iter()
                .filter(|camera| {
                    let k = camera.intrinsics;
                    camera.project(point.as_vec3()).is_some_and(|(u, v)| {
                        (0.0..=k.width as f32).contains(&u) && (0.0..=k.height as f32).contains(&v)
                    })
                })
                .count();
            let distances = positions.iter().map(|p| p.distance(point));
            Focus {
                from_centre: point.distance(centre),
                seen_by,
                nearest: distances.clone().fold(f64::INFINITY, f64::min),
                farthest: distances.fold(0.0, f64::max),
            }
        });
        Some(Self {
            count,
            mean_distance,
            widest_angle_deg,
            along,
            across,
            focus,
        })
    }

    /// The sentence saying the cameras make a forward-facing capture, when
    /// they do.
    fn forward_facing(&self) -> Option<String> {
        (self.widest_angle_deg <= FORWARD_MAX_ANGLE_DEG
            && self.across > 0.0
            && self.along <= FORWARD_MAX_DEPTH_SHARE * self.across)
            .then(|| {
                format!(
                    "the {} cameras all look within {:.0}° of one direction and lie on a plane \
                     across it ({:.2} units deep along it, {:.2} across): a forward-facing \
                     capture, its content seen from one side",
                    self.count, self.widest_angle_deg, self.along, self.across
                )
            })
    }

    /// Why the cameras are no forward-facing capture (for a layout that is
    /// not).
    fn why_not_forward_facing(&self) -> String {
        if self.widest_angle_deg > FORWARD_MAX_ANGLE_DEG {
            format!(
                "not forward-facing: the cameras' viewing directions spread up to {:.0}° from \
                 their mean (at most {FORWARD_MAX_ANGLE_DEG:.0}° in a forward-facing capture)",
                self.widest_angle_deg
            )
        } else {
            format!(
                "not forward-facing: the cameras look one way (within {:.0}°) but lie {:.2} \
                 units deep along it against {:.2} across it (at most {:.0} % as deep as across \
                 in a forward-facing capture)",
                self.widest_angle_deg,
                self.along,
                self.across,
                100.0 * FORWARD_MAX_DEPTH_SHARE
            )
        }
    }

    /// The focus when enough cameras look at it.
    fn inward_focus(&self) -> Option<&Focus> {
        self.focus
            .as_ref()
            .filter(|focus| focus.seen_by as f64 >= INWARD_SHARE * self.count as f64)
    }

    /// Where the cameras look, in one sentence.
    fn describe(&self) -> String {
        match (&self.focus, self.inward_focus()) {
            (_, Some(focus)) => format!(
                "the {} cameras look inward at a point {:.2} units from their centre, from \
                 {:.2} to {:.2} units away",
                self.count, focus.from_centre, focus.nearest, focus.farthest
            ),
            (Some(focus), None) => format!(
                "only {} of the {} cameras have in view the point nearest to all their optical \
                 axes ({:.2} units from their centre)",
                focus.seen_by, self.count, focus.from_centre
            ),
            (None, None) => format!(
                "the {} cameras' optical axes meet nowhere (they are nearly parallel), and the \
                 cameras lie {:.2} units deep along them",
                self.count, self.along
            ),
        }
    }
}

/// The point nearest to every optical axis (through `positions` along the
/// unit `forwards`) in the least-squares sense, or `None` when the axes
/// are too close to parallel to meet anywhere.
fn nearest_to_axes(positions: &[DVec3], forwards: &[DVec3]) -> Option<DVec3> {
    // Σ (I − d dᵀ) p = Σ (I − d dᵀ) c over cameras c with unit axes d.
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for (&c, &d) in positions.iter().zip(forwards) {
        let projector = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += projector;
        b += projector * c;
    }
    // The same conditioning test as COLMAP's scene centre: axes in at
    // least two directions.
    let n = positions.len() as f64;
    if a.determinant().abs() <= 1e-6 * n.powi(3) {
        return None;
    }
    Some(a.inverse() * b).filter(|p| p.is_finite())
}

#[cfg(test)]
mod tests;
