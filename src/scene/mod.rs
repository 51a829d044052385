//! What was photographed: cameras, rays, images, the dataset formats and the
//! built-in demo scene.

pub mod blender;
mod bounds;
mod camera;
pub mod camera_export;
pub mod colmap;
pub mod crop;
pub mod demo;
mod error;
pub mod exif;
pub mod identity;
mod image;
pub mod instant_ngp;
mod lens;
pub mod llff;
pub mod mask;
pub mod names;
pub mod photographs;
pub mod pose;
pub mod space;

use std::path::{Path, PathBuf};

use glam::Vec3;

pub use bounds::Aabb;
pub use camera::{Camera, Intrinsics, NdcSpace, Ray};
pub use error::{SceneError, SceneResult, escape_controls};
pub use image::{ImageRgba8, load_image, to_u8};
pub use lens::Lens;
pub use mask::PixelMask;
pub use space::{SceneSpace, SpaceAnalysis, SparsePoints};

/// Options for loading a scene from disk.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoadOptions {
    /// Integer downscale of every image (1 keeps full resolution).
    pub downscale: u32,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { downscale: 1 }
    }
}

/// Where a scene came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneFormat {
    /// NeRF-synthetic: `transforms_{train,val,test}.json`.
    Blender,
    /// instant-ngp / nerfstudio: one `transforms.json`.
    InstantNgp,
    /// zrak's built-in procedural scene, built in memory.
    Demo,
    /// A COLMAP sparse model and its `images/` folder.
    Colmap,
    /// The NeRF paper's forward-facing captures: `poses_bounds.npy` and
    /// `images/` (LLFF, Mildenhall et al. 2019).
    Llff,
}

/// The splits of a scene (`--split train|val|test` on the command line).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];

    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

/// One photograph and the camera that took it.
#[derive(Debug, Clone)]
pub struct Frame {
    pub camera: Camera,
    pub image: ImageRgba8,
    /// The image file it was read from (empty for in-memory scenes).
    pub image_path: PathBuf,
    /// Which of the image's pixels count (its size), when the scene gives
    /// a mask: the others are never training targets and are left out of
    /// the held-out scores. `None`: every pixel counts.
    pub mask: Option<PixelMask>,
}

impl Frame {
    /// The view at 1/`factor` of its resolution: the same pose, the
    /// intrinsics scaled, and the photograph area-averaged (what a camera
    /// with pixels `factor` times wider records; Mip-NeRF's multiscale
    /// Blender protocol).
    pub fn downscaled(&self, factor: u32) -> Frame {
        Frame {
            camera: Camera::new(
                self.camera.intrinsics.downscaled(factor),
                self.camera.camera_to_world,
            )
            .with_ndc(self.camera.ndc),
            image: self.image.downscaled(factor),
            image_path: self.image_path.clone(),
            mask: self.mask.as_ref().map(|mask| mask.downscaled(factor)),
        }
    }

    /// The pixels `x0..x0 + width`, `y0..y0 + height` of the view at full
    /// resolution: the camera's rays through them and the photograph's
    /// values, for scoring part of a view.
    pub fn cropped(&self, x0: u32, y0: u32, width: u32, height: u32) -> Frame {
        Frame {
            camera: Camera::new(
                self.camera.intrinsics.cropped(x0, y0, width, height),
                self.camera.camera_to_world,
            )
            .with_ndc(self.camera.ndc),
            image: self.image.cropped(x0, y0, width, height),
            image_path: self.image_path.clone(),
            mask: self
                .mask
                .as_ref()
                .map(|mask| mask.cropped(x0, y0, width, height)),
        }
    }
}

/// How world coordinates map into the unit cube that grid-based models work
/// in: `unit = world · scale + offset`. The scene's content lies in the cube
/// of side `aabb_scale` centred at (0.5, 0.5, 0.5) in unit coordinates
/// (instant-ngp's convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnitCubeMapping {
    pub scale: f32,
    pub offset: Vec3,
    pub aabb_scale: f32,
}

impl UnitCubeMapping {
    /// instant-ngp's defaults for NeRF-synthetic scenes: scale 0.33, offset
    /// 0.5, aabb_scale 1 (instant-ngp `src/nerf_loader.cu`, `NERF_SCALE`).
    pub const BLENDER: Self = Self {
        scale: 0.33,
        offset: Vec3::splat(0.5),
        aabb_scale: 1.0,
    };

    /// Multiplies a world length into a fraction of the scene box's
    /// diagonal (√3 · aabb_scale in unit-cube lengths).
    pub fn diagonal_scale(&self) -> f32 {
        self.scale / (3f32.sqrt() * self.aabb_scale)
    }

    pub fn to_unit(&self, world: Vec3) -> Vec3 {
        world * self.scale + self.offset
    }

    pub fn to_world(&self, unit: Vec3) -> Vec3 {
        (unit - self.offset) / self.scale
    }

    /// The mapping that fits the cube around `bounds` (its longest side,
    /// centred on it, a millionth larger so that rounding keeps the box's
    /// corners inside) to the unit cube, `aabb_scale` 1.
    pub fn around(bounds: &Aabb) -> Self {
        let half = 0.5 * bounds.size().max_element() * (1.0 + 1e-6);
        let scale = 0.5 / half;
        Self {
            scale,
            offset: Vec3::splat(0.5) - bounds.centre() * scale,
            aabb_scale: 1.0,
        }
    }

    /// The box holding the scene's content, in world coordinates.
    pub fn world_bounds(&self) -> Aabb {
        let half = 0.5 * self.aabb_scale;
        Aabb::new(
            self.to_world(Vec3::splat(0.5 - half)),
            self.to_world(Vec3::splat(0.5 + half)),
        )
    }
}

/// The share of the NDC box's side added beyond the cameras' rays in x and
/// y ([`Scene::with_ndc`]).
const NDC_MARGIN: f32 = 0.01;

/// A scene: frames per split, with what every model needs to know about
/// where the content is.
#[derive(Debug, Clone)]
pub struct Scene {
    /// A short name (the folder name, or "demo").
    pub name: String,
    /// The folder it was loaded from (empty for in-memory scenes).
    pub root: PathBuf,
    pub format: SceneFormat,
    pub train: Vec<Frame>,
    pub val: Vec<Frame>,
    pub test: Vec<Frame>,
    /// Whether the image files carry an alpha channel.
    pub has_alpha: bool,
    pub unit_cube: UnitCubeMapping,
    /// The box that contains the object, in world coordinates.
    pub bounds: Aabb,
    /// How many of the last training views are smaller copies of the
    /// others ([`Scene::with_training_scales`]): 0 as loaded.
    pub smaller_training_views: usize,
    /// How far a COLMAP model's sparse points lie (`None` for other
    /// formats, or a model without points): what [`space::analyse`] reads
    /// of them.
    pub sparse_points: Option<SparsePoints>,
    /// What the scene calls for (object, unbounded, forward-facing) and
    /// why: [`space::analyse`]'s, or chosen by [`Scene::with_space`].
    pub space: SpaceAnalysis,
    /// Where the cameras' poses came from, as the loader saw it: what
    /// decides whether they are refined ([`photographs::analyse`]).
    pub poses: PoseOrigin,
}

/// Where a scene's camera poses came from.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct PoseOrigin {
    /// Estimated from the photographs (structure from motion), so off by a
    /// fraction of a pixel to a few pixels; otherwise known exactly (the
    /// cameras a render was made from).
    pub estimated: bool,
    /// The sentence that says so, naming what in the files shows it.
    pub evidence: String,
}

impl PoseOrigin {
    /// The cameras a render was made from.
    pub fn exact(evidence: impl Into<String>) -> Self {
        Self {
            estimated: false,
            evidence: evidence.into(),
        }
    }

    /// Cameras estimated by structure from motion.
    pub fn estimated(evidence: impl Into<String>) -> Self {
        Self {
            estimated: true,
            evidence: evidence.into(),
        }
    }
}

impl Scene {
    /// The scene with every training view also at ½, ¼, … of its
    /// resolution, `scales` sizes in all (Mip-NeRF's multiscale Blender
    /// protocol uses 4: full, ½, ¼, ⅛). Training draws views uniformly,
    /// so each size gets an equal share of the rays: in expectation the
    /// paper's loss over every pixel of every size, each weighted by its
    /// footprint's area in the full-size image (Barron et al. 2021,
    /// section 5). `scales` 1 leaves the scene as it is; sizes that would
    /// fall below one pixel are left out.
    pub fn with_training_scales(mut self, scales: u32) -> Self {
        let sizes: Vec<u32> = (1..scales).map(|level| 1 << level).collect();
        let mut extra = Vec::new();
        for frame in self.photographed_training_views() {
            let k = frame.camera.intrinsics;
            for &factor in &sizes {
                if k.width / factor >= 1 && k.height / factor >= 1 {
                    extra.push(frame.downscaled(factor));
                }
            }
        }
        self.smaller_training_views += extra.len();
        self.train.extend(extra);
        self
    }

    /// The training views as loaded, without the smaller copies
    /// [`Self::with_training_scales`] adds: what identifies the scene.
    pub fn photographed_training_views(&self) -> &[Frame] {
        &self.train[..self.train.len() - self.smaller_training_views]
    }

    pub fn split(&self, split: Split) -> &[Frame] {
        match split {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// The nearest and farthest depth at which the scene's own cameras see
    /// its box (rays through each camera's corners and centre), or `None`
    /// when no camera does: the range depth images are shaded over.
    pub fn seen_depth_range(&self) -> Option<(f32, f32)> {
        let mut range: Option<(f32, f32)> = None;
        for frame in self.frames() {
            let k = frame.camera.intrinsics;
            let (w, h) = (k.width as f32, k.height as f32);
            let points = [
                (0.5, 0.5),
                (w - 0.5, 0.5),
                (0.5, h - 0.5),
                (w - 0.5, h - 0.5),
                (0.5 * w, 0.5 * h),
            ];
            for (u, v) in points {
                if let Some((near, far)) = self.ray_near_far(&frame.camera.ray_through(u, v)) {
                    range = Some(match range {
                        Some((n, f)) => (n.min(near), f.max(far)),
                        None => (near, far),
                    });
                }
            }
        }
        range
    }

    /// [`Self::seen_depth_range`], or (0, 1) when no camera sees the box.
    pub fn depth_range(&self) -> (f32, f32) {
        self.seen_depth_range().unwrap_or((0.0, 1.0))
    }

    /// All frames of all splits.
    pub fn frames(&self) -> impl Iterator<Item = &Frame> {
        self.train.iter().chain(&self.val).chain(&self.test)
    }

    /// Width and height shared by every frame.
    pub fn resolution(&self) -> Option<(u32, u32)> {
        self.frames()
            .next()
            .map(|f| (f.camera.intrinsics.width, f.camera.intrinsics.height))
    }

    /// Frames of all splits that carry a mask, and the pixels their masks
    /// leave out.
    pub fn masked_frames(&self) -> (usize, usize) {
        self.frames()
            .filter_map(|frame| frame.mask.as_ref())
            .fold((0, 0), |(frames, pixels), mask| {
                (frames + 1, pixels + mask.hidden())
            })
    }

    /// What `zrak info` and `zrak train` say of the masks: how many frames
    /// of each split have one and how many pixels they leave out, or `None`
    /// when no frame has a mask.
    pub fn describe_masks(&self) -> Option<String> {
        let (frames, pixels) = self.masked_frames();
        if frames == 0 {
            return None;
        }
        let per_split: Vec<String> = Split::ALL
            .iter()
            .map(|&split| {
                let masked = self
                    .split(split)
                    .iter()
                    .filter(|frame| frame.mask.is_some())
                    .count();
                format!("{} {masked} of {}", split.name(), self.split(split).len())
            })
            .collect();
        Some(format!(
            "{frames} frames have masks ({}); {pixels} pixels masked out, never trained on \
             nor scored",
            per_split.join(", ")
        ))
    }

    /// The training views whose mask leaves out every pixel: training
    /// skips them.
    pub fn fully_masked_training_views(&self) -> Vec<&Frame> {
        self.train
            .iter()
            .filter(|frame| frame.mask.as_ref().is_some_and(|mask| mask.counted() == 0))
            .collect()
    }

    /// Why training on this scene would do nothing, or `None`: no
    /// training views, a box that is not finite, or training cameras
    /// none of whose rays (checked on a grid of 16 × 16 pixels per view)
    /// crosses the box, so no sample would ever be taken.
    pub fn training_problem(&self) -> Option<String> {
        if self.train.is_empty() {
            return Some(format!(
                "the scene has no training views (val {}, test {})",
                self.val.len(),
                self.test.len()
            ));
        }
        let b = self.bounds;
        if !(b.min.is_finite() && b.max.is_finite() && b.min.cmplt(b.max).all()) {
            return Some(format!(
                "the scene's box [{}, {}] is not a finite box (check `scale`, `offset` and \
                 `aabb_scale`)",
                b.min, b.max
            ));
        }
        if self.fully_masked_training_views().len() == self.train.len() {
            return Some(format!(
                "every pixel of the {} training views is masked out: no pixel is left to \
                 train on",
                self.train.len()
            ));
        }
        const GRID: u32 = 16;
        let crosses = self.photographed_training_views().iter().any(|frame| {
            let k = frame.camera.intrinsics;
            (0..GRID).any(|j| {
                (0..GRID).any(|i| {
                    let u = (i as f32 + 0.5) / GRID as f32 * k.width as f32;
                    let v = (j as f32 + 0.5) / GRID as f32 * k.height as f32;
                    let ray = frame.camera.ray_through(u, v);
                    ray.origin.is_finite()
                        && ray.direction.is_finite()
                        && self
                            .ray_near_far(&ray)
                            .is_some_and(|(near, far)| far > near && far > 0.0)
                })
            })
        });
        if !crosses {
            return Some(format!(
                "no training camera's rays cross the scene's box [{:.4}, {:.4}] (check the \
                 cameras' poses and field of view, and `scale`, `offset` and `aabb_scale`)",
                b.min, b.max
            ));
        }
        None
    }
    /// The scene as its space treats it: a forward-facing capture in the
    /// LLFF layout in normalised device coordinates (NeRF, appendix C),
    /// every other scene as it is. Forward-facing captures in other layouts
    /// keep their world coordinates: NDC needs the LLFF loader's frame (the
    /// cameras around the origin looking down −z, nothing nearer than its
    /// near plane), which only that loader's rescale guarantees.
    pub fn in_its_space(self) -> Scene {
        if self.space.space == SceneSpace::ForwardFacing
            && self.format == SceneFormat::Llff
            && self.ndc().is_none()
        {
            self.with_ndc()
        } else {
            self
        }
    }

    /// The scene with every camera of every split giving its rays in
    /// normalised device coordinates (NeRF paper, appendix C), for a
    /// forward-facing capture: the NDC of the first training view's
    /// intrinsics with the near plane at z = −[`llff::NDC_NEAR`], and the
    /// box around what the cameras see there (a little beyond [−1, 1] in x
    /// and y, where cameras beside the reference look; z from −1, the near
    /// plane, to 1, infinity). It assumes the frame the LLFF loader leaves
    /// ([`llff`]): the cameras around the origin looking down −z, nothing
    /// they see nearer than `NDC_NEAR` (the loader puts the nearest bound at
    /// 1/0.75).
    pub fn with_ndc(mut self) -> Scene {
        let Some(reference) = self
            .photographed_training_views()
            .first()
            .or_else(|| self.frames().next())
            .map(|frame| frame.camera.intrinsics)
        else {
            return self;
        };
        let ndc = NdcSpace::of(&reference, llff::NDC_NEAR);
        for frame in self
            .train
            .iter_mut()
            .chain(&mut self.val)
            .chain(&mut self.test)
        {
            frame.camera.ndc = Some(ndc);
        }
        self.bounds = self.ndc_bounds();
        self.unit_cube = UnitCubeMapping::around(&self.bounds);
        self
    }

    /// The NDC space the cameras' rays are in, when they are
    /// ([`Self::with_ndc`]).
    pub fn ndc(&self) -> Option<NdcSpace> {
        self.frames().next().and_then(|frame| frame.camera.ndc)
    }

    /// The world point that views of the scene orbit and face, with the
    /// size of the region around it: the box's centre and diagonal, or, for
    /// a scene in NDC (whose box is in NDC), a point past the nearest
    /// content, where the LLFF loader puts the cameras about the origin
    /// looking down −z and the nearest content at 1/0.75.
    pub fn view_centre_and_size(&self) -> (Vec3, f32) {
        match self.ndc() {
            Some(_) => (Vec3::new(0.0, 0.0, -2.0), 4.0),
            None => (self.bounds.centre(), self.bounds.size().length()),
        }
    }

    /// The box in NDC that holds every camera's rays from the near plane
    /// to infinity (each view's corner rays at t = 0 and t = 1 along d′),
    /// at least [−1, 1]³, with z from −1 to 1 and a margin of
    /// [`NDC_MARGIN`] of the box's side in x and y for rays between pixel
    /// centres and corners.
    fn ndc_bounds(&self) -> Aabb {
        let mut min = Vec3::splat(-1.0);
        let mut max = Vec3::splat(1.0);
        for frame in self.frames() {
            let k = frame.camera.intrinsics;
            let (w, h) = (k.width as f32, k.height as f32);
            for (u, v) in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
                let ray = frame.camera.ray_through(u, v);
                for point in [ray.origin, ray.origin + ray.direction_unnormalised] {
                    if point.is_finite() {
                        min = min.min(point);
                        max = max.max(point);
                    }
                }
            }
        }
        let margin = NDC_MARGIN * (max - min);
        Aabb::new(
            Vec3::new(min.x - margin.x, min.y - margin.y, -1.0),
            Vec3::new(max.x + margin.x, max.y + margin.y, 1.0),
        )
    }

    /// Near and far distances (along the unit direction) for a ray: where it
    /// enters and leaves the scene box, or `None` when it misses the box.
    pub fn ray_near_far(&self, ray: &Ray) -> Option<(f32, f32)> {
        self.bounds.intersect_ray(ray, 0.0)
    }
}

impl Scene {
    /// Loads a scene from disk: a folder in the NeRF-synthetic layout
    /// (`transforms_{train,val,test}.json`, see [`blender`]), the
    /// instant-ngp / nerfstudio layout (`transforms.json`, see
    /// [`instant_ngp`]), the NeRF paper's LLFF layout (`poses_bounds.npy`,
    /// see [`llff`]) or with a COLMAP model (see [`colmap`]), or the path
    /// of one of those JSON files. A folder
    /// with both prefers the split files, because they carry the dataset's
    /// own train/val/test division; then `poses_bounds.npy`, because the
    /// NeRF paper's captures carry their COLMAP model beside it and a
    /// transforms.json there is most likely converted from it.
    pub fn load(path: &Path, options: LoadOptions) -> SceneResult<Scene> {
        let scene = Self::load_unchecked(path, options)?;
        scene.check_lenses(path)?;
        Ok(scene)
    }

    /// Refuses lenses whose distortion folds over inside the image: there
    /// some pixels have no direction (the inverse [`Lens::undistort`]
    /// finds no root), so their rays would be guesses. Checked on a 9 × 9
    /// grid of each distinct camera's image, corners included.
    fn check_lenses(&self, path: &Path) -> SceneResult<()> {
        let mut checked: Vec<Intrinsics> = Vec::new();
        for frame in self.frames() {
            let k = frame.camera.intrinsics;
            if k.lens.is_pinhole() || checked.contains(&k) {
                continue;
            }
            checked.push(k);
            const STEPS: u32 = 8;
            for j in 0..=STEPS {
                for i in 0..=STEPS {
                    let u = i as f64 / STEPS as f64 * k.width as f64;
                    let v = j as f64 / STEPS as f64 * k.height as f64;
                    let xd = (u - k.cx as f64) / k.fx as f64;
                    let yd = (v - k.cy as f64) / k.fy as f64;
                    if !k.lens.undistort(xd, yd).converged {
                        return Err(SceneError::new(
                            Self::lens_file(path),
                            format!(
                                "the lens of {} ({}) folds over inside its {}×{} image: \
                                 pixel ({u:.0}, {v:.0}) has no direction these \
                                 coefficients map to it, so its rays would be guesses; \
                                 check the distortion coefficients",
                                frame.image_path.display(),
                                k.lens.describe(),
                                k.width,
                                k.height
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// The file the lens coefficients of the scene at `path` are read
    /// from, for messages: the transforms.json or COLMAP cameras file.
    fn lens_file(path: &Path) -> PathBuf {
        if path.is_file() {
            return path.to_path_buf();
        }
        let transforms = path.join(instant_ngp::FILE_NAME);
        if transforms.is_file() {
            return transforms;
        }
        colmap::find_model_folder(path)
            .and_then(|folder| {
                ["cameras.bin", "cameras.txt"]
                    .iter()
                    .map(|name| folder.join(name))
                    .find(|p| p.is_file())
            })
            .unwrap_or_else(|| path.to_path_buf())
    }

    fn load_unchecked(path: &Path, options: LoadOptions) -> SceneResult<Scene> {
        pose::check_downscale(path, options.downscale)?;
        if path.is_file() {
            let is_split_file = Split::ALL
                .iter()
                .any(|&split| path.file_name() == Some(blender::split_file_name(split).as_ref()));
            return if is_split_file {
                let folder = path.parent().filter(|p| !p.as_os_str().is_empty());
                blender::load(folder.unwrap_or(Path::new(".")), options)
            } else {
                instant_ngp::load(path, options)
            };
        }
        if !path.is_dir() {
            let problem = crate::files::describe_not_a_folder(path);
            return Err(if crate::files::exists_at_all(path) {
                SceneError::unreadable(path, problem)
            } else {
                SceneError::not_found(path, problem)
            });
        }
        if blender::is_blender_folder(path) {
            blender::load(path, options)
        } else if llff::is_llff_folder(path) {
            llff::load(path, options)
        } else if crate::files::exists_at_all(&path.join(instant_ngp::FILE_NAME)) {
            instant_ngp::load(path, options)
        } else if colmap::is_colmap_folder(path) {
            colmap::load(path, options)
        } else {
            Err(SceneError::not_a_scene(
                path,
                "not a scene folder: it holds none of transforms_train.json, \
                 transforms_val.json, transforms_test.json, transforms.json, LLFF's \
                 poses_bounds.npy or a COLMAP model (sparse/0/cameras.bin and images.bin, \
                 or the .txt forms)",
            ))
        }
    }
}

/// The folder name of `path`, for display.
pub fn folder_name(path: &Path) -> String {
    path.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}
