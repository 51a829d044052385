//! The demo with something that moves: a ball that floats above the stand
//! at another place in each training photograph, with instant-ngp's
//! `dynamic_mask_*.png` marking it, and held-out views without it. A field
//! trained on the photographs alone must explain a ball that is there in
//! one view and not in the next, and leaves fog where it passed; with the
//! masks it never sees the ball.

use std::path::Path;

use glam::Vec3;
use rayon::prelude::*;

use super::{
    AMBIENT, DemoConfig, FILL_INTENSITY, KEY_INTENSITY, SAMPLES_PER_SIDE, Shape, World,
    intersect_shape, split_cameras,
};
use crate::scene::mask::{PixelMask, dynamic_mask_path};
use crate::scene::{Camera, Frame, ImageRgba8, Scene, SceneResult, Split, to_u8};

/// The moving ball's radius, in world units: about a fifth of the view's
/// width at the demo's camera distance, so that it covers a few hundred
/// pixels of a 64-pixel view.
pub const MOVING_RADIUS: f32 = 0.3;

/// How many places the ball visits, the training views taking them in
/// turn (view k at place k mod `MOVING_PLACES`): the ball moves between
/// any two consecutive views, and each place is seen with the ball from
/// half the views, all around, and empty from the other half, so a field
/// without masks has a consistent reason to put fog there (a ball at a
/// new place in every view would leave its fog anywhere along that view's
/// rays, where no test could find it).
pub const MOVING_PLACES: usize = 2;

/// Its colour: a magenta no other object has.
const MOVING_COLOUR: Vec3 = Vec3::new(0.85, 0.2, 0.75);

/// Where the ball is in training view `index`: one of [`MOVING_PLACES`]
/// points spread over a circle of radius 0.75 at height 0.55, above the stand's
/// objects (the tallest, the blue cylinder, ends at 0.38) and inside the
/// demo's box.
pub fn moving_object_centre(index: usize) -> Vec3 {
    let place = (index % MOVING_PLACES) as f32;
    let angle = std::f32::consts::TAU * (place + 0.5) / MOVING_PLACES as f32;
    Vec3::new(0.75 * angle.cos(), 0.75 * angle.sin(), 0.55)
}

/// The demo with the moving ball in every training view (at
/// [`moving_object_centre`]) and each training view's mask hiding every
/// pixel the ball touches; the held-out views are the demo's own, without
/// the ball. Training views are written, loaded and scored like a capture
/// with masks.
pub fn build_moving_object(config: &DemoConfig) -> Scene {
    let mut scene = super::build(config);
    let cameras = split_cameras(config, Split::Train);
    scene.train = cameras
        .par_iter()
        .enumerate()
        .map(|(index, camera)| {
            let (image, mask) = render_with_ball(camera, moving_object_centre(index));
            Frame {
                camera: *camera,
                image,
                image_path: Default::default(),
                mask: Some(mask),
            }
        })
        .collect();
    scene.name = "demo-moving".into();
    scene
}

/// Writes [`build_moving_object`] under `dir` in the instant-ngp layout:
/// `transforms.json` (with nerfstudio's split lists),
/// `{train,val,test}/r_N.png`, and beside each training image its
/// `dynamic_mask_r_N.png` (white where the ball is).
pub fn write_moving_object(config: &DemoConfig, dir: &Path) -> SceneResult<()> {
    let scene = build_moving_object(config);
    super::write_instant_ngp(&scene, dir)?;
    let folder = dir.join(Split::Train.name());
    scene
        .train
        .par_iter()
        .enumerate()
        .try_for_each(|(index, frame)| {
            let image = folder.join(format!("r_{index}.png"));
            let path = dynamic_mask_path(&image).expect("an image file name");
            frame
                .mask
                .as_ref()
                .expect("every training view has a mask")
                .save_dynamic_mask_png(&path)
        })
}

/// The demo as `camera` sees it with the ball at `centre` (lit by the key
/// and fill lights, casting no shadow, so that nothing outside its own
/// pixels changes from view to view), and the mask hiding every pixel any
/// of whose samples meets the ball, in front of the other objects or
/// behind them.
fn render_with_ball(camera: &Camera, centre: Vec3) -> (ImageRgba8, PixelMask) {
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let world = World::new();
    let ball = Shape::Sphere {
        centre,
        radius: MOVING_RADIUS,
    };
    let n = SAMPLES_PER_SIDE;
    let rows: Vec<(Vec<u8>, Vec<bool>)> = (0..height)
        .into_par_iter()
        .map(|row| {
            let mut pixels = Vec::with_capacity(width as usize * 4);
            let mut counts = Vec::with_capacity(width as usize);
            for column in 0..width {
                let mut colour = Vec3::ZERO;
                let mut hits = 0u32;
                let mut touches_ball = false;
                for s in 0..n * n {
                    let (dx, dy) = (
                        ((s % n) as f32 + 0.5) / n as f32,
                        ((s / n) as f32 + 0.5) / n as f32,
                    );
                    let ray = camera.ray_through(column as f32 + dx, row as f32 + dy);
                    let (o, d) = (ray.origin, ray.direction);
                    let on_ball = intersect_shape(&ball, o, d, f32::INFINITY);
                    touches_ball |= on_ball.is_some();
                    let behind_others = |t: f32| world.intersect(o, d).is_some_and(|h| h.t < t);
                    let seen = match on_ball {
                        Some((t, normal)) if !behind_others(t) => Some(
                            MOVING_COLOUR
                                * (AMBIENT
                                    + KEY_INTENSITY * normal.dot(world.key).max(0.0)
                                    + FILL_INTENSITY * normal.dot(world.fill).max(0.0)),
                        ),
                        _ => world.trace(o, d),
                    };
                    if let Some(c) = seen {
                        colour += c.min(Vec3::ONE);
                        hits += 1;
                    }
                }
                // As the demo's own render: the mean of the covered samples
                // is the straight colour, the coverage the alpha.
                if hits > 0 {
                    let straight = colour / hits as f32;
                    pixels.extend([straight.x, straight.y, straight.z].map(to_u8));
                    pixels.push(to_u8(hits as f32 / (n * n) as f32));
                } else {
                    pixels.extend([0; 4]);
                }
                counts.push(!touches_ball);
            }
            (pixels, counts)
        })
        .collect();
    let (data, counts): (Vec<Vec<u8>>, Vec<Vec<bool>>) = rows.into_iter().unzip();
    (
        ImageRgba8::new(width, height, data.concat()),
        PixelMask::new(width, height, counts.concat()),
    )
}
