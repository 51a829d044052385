use std::path::PathBuf;

use glam::Vec3;

use super::*;
use crate::scene::demo::CAMERA_ANGLE_X;
use crate::scene::{Frame, ImageRgba8, Intrinsics, SceneFormat, UnitCubeMapping};

/// A scene of 2 × 2 photographs taken by `cameras`, `alpha` in every
/// pixel's fourth byte (255: opaque; the file has an alpha channel when
/// `has_alpha`).
fn scene_of(cameras: Vec<Camera>, has_alpha: bool, alpha: u8, aabb_scale: f32) -> Scene {
    let frames = cameras
        .into_iter()
        .map(|camera| Frame {
            camera,
            image: ImageRgba8::new(2, 2, [90, 90, 90, alpha].repeat(4)),
            image_path: PathBuf::new(),
            mask: None,
        })
        .collect();
    let unit_cube = UnitCubeMapping {
        aabb_scale,
        ..UnitCubeMapping::BLENDER
    };
    let mut scene = Scene {
        name: "cameras".into(),
        root: PathBuf::new(),
        format: SceneFormat::InstantNgp,
        train: frames,
        val: Vec::new(),
        test: Vec::new(),
        has_alpha,
        unit_cube,
        bounds: unit_cube.world_bounds(),
        smaller_training_views: 0,
        sparse_points: None,
        space: SpaceAnalysis::default(),
        poses: crate::scene::PoseOrigin::default(),
    };
    scene.space = analyse(&scene);
    scene
}

fn intrinsics() -> Intrinsics {
    Intrinsics::from_fov_x(64, 48, CAMERA_ANGLE_X)
}

/// `count` cameras spread evenly over an arc of `spread_deg` degrees of the
/// circle of radius 4 at `height` around the z axis, centred on +x, each
/// looking at the origin.
fn ring(count: usize, height: f32, spread_deg: f32) -> Vec<Camera> {
    (0..count)
        .map(|k| {
            let azimuth = (k as f32 / (count - 1).max(1) as f32 - 0.5) * spread_deg.to_radians();
            let eye = Vec3::new(4.0 * azimuth.cos(), 4.0 * azimuth.sin(), height);
            Camera::look_at(intrinsics(), eye, Vec3::ZERO, Vec3::Z)
        })
        .collect()
}

/// The demo's training spiral: 20 cameras over the upper hemisphere at
/// distance 4, looking at the origin.
fn around_an_object() -> Vec<Camera> {
    crate::scene::demo::split_cameras(
        &crate::scene::demo::DemoConfig {
            size: 32,
            train_views: 20,
            val_views: 0,
            test_views: 0,
        },
        crate::scene::Split::Train,
    )
}

/// A 4 × 4 grid of cameras 0.5 apart on the plane z = 0, all looking along
/// -z, turned towards a point 10 units ahead (as LLFF's hand-held captures
/// converge on their subject).
fn forward_grid() -> Vec<Camera> {
    let target = Vec3::new(0.0, 0.0, -10.0);
    (0..16)
        .map(|k| {
            let eye = Vec3::new(
                (k % 4) as f32 * 0.5 - 0.75,
                (k / 4) as f32 * 0.5 - 0.75,
                0.0,
            );
            Camera::look_at(intrinsics(), eye, target, Vec3::Y)
        })
        .collect()
}

#[test]
fn transparent_photographs_make_an_object() {
    let scene = scene_of(around_an_object(), true, 0, 1.0);
    let analysis = &scene.space;
    assert_eq!(analysis.space, SceneSpace::Object);
    assert!(!analysis.overridden);
    assert_eq!(
        analysis.reasons[0],
        "100 % of the images' pixels are transparent: the background is known, so the content \
         ends where the alpha does"
    );
    // The cameras' centre (their mean position) lies 4 · 0.579 above the
    // origin: the mean of sin(elevation), spread evenly from sin 10° to
    // sin 80°.
    assert_eq!(
        analysis.reasons[1],
        "the 20 cameras look inward at a point 2.32 units from their centre, from 4.00 to 4.00 \
         units away"
    );
    // Alpha decides even where aabb_scale is large.
    assert_eq!(
        scene_of(around_an_object(), true, 128, 16.0).space.space,
        SceneSpace::Object
    );
}

#[test]
fn opaque_cameras_around_a_point_are_an_object_in_a_unit_box_and_unbounded_in_a_larger() {
    let object = scene_of(around_an_object(), false, 255, 1.0).space;
    assert_eq!(object.space, SceneSpace::Object);
    assert_eq!(
        object.reasons[0],
        "the 20 cameras look inward at a point 2.32 units from their centre, from 4.00 to 4.00 \
         units away, and aabb_scale is 1: the content lies in the box they surround (no image \
         has alpha, so the background is learned as part of it)"
    );
    assert!(
        object.reasons[1]
            .starts_with("not forward-facing: the cameras' viewing directions spread up to"),
        "{:?}",
        object.reasons
    );
    let unbounded = scene_of(around_an_object(), false, 255, 16.0).space;
    assert_eq!(unbounded.space, SceneSpace::Unbounded);
    assert_eq!(
        unbounded.reasons[0],
        "the 20 cameras look inward at a point 2.32 units from their centre, but no image has \
         alpha and aabb_scale is 16: the background runs beyond the cameras"
    );
    // An alpha channel that is opaque everywhere says no more than none.
    let opaque_alpha = scene_of(around_an_object(), true, 255, 8.0).space;
    assert_eq!(opaque_alpha.space, SceneSpace::Unbounded);
    assert!(
        opaque_alpha.reasons[0]
            .contains("but every image is opaque everywhere and aabb_scale is 8"),
        "{:?}",
        opaque_alpha.reasons
    );
}

#[test]
fn cameras_looking_out_from_inside_the_content_are_unbounded() {
    // A room scanned from its middle: 12 cameras on a small circle, each
    // looking outward, away from the others.
    let cameras: Vec<Camera> = (0..12)
        .map(|k| {
            let azimuth = k as f32 / 12.0 * std::f32::consts::TAU;
            let out = Vec3::new(azimuth.cos(), azimuth.sin(), 0.0);
            Camera::look_at(intrinsics(), 0.3 * out, 5.0 * out, Vec3::Z)
        })
        .collect();
    let analysis = scene_of(cameras, false, 255, 1.0).space;
    assert_eq!(analysis.space, SceneSpace::Unbounded, "{analysis:?}");
    assert!(
        analysis.reasons[0].starts_with("only 0 of the 12 cameras have in view the point nearest"),
        "{:?}",
        analysis.reasons
    );
    assert!(
        analysis.reasons[0].ends_with(
            "they look around rather than at one region, as cameras inside the content do, \
             and no image has alpha"
        ),
        "{:?}",
        analysis.reasons
    );
}

#[test]
fn cameras_on_a_plane_looking_one_way_are_forward_facing() {
    let analysis = scene_of(forward_grid(), false, 255, 1.0).space;
    assert_eq!(analysis.space, SceneSpace::ForwardFacing, "{analysis:?}");
    // The corner cameras turn atan(0.75·√2 / 10) = 6° towards the target.
    assert_eq!(
        analysis.reasons,
        vec![
            "the 16 cameras all look within 6° of one direction and lie on a plane across it \
             (0.00 units deep along it, 1.06 across): a forward-facing capture, its content \
             seen from one side"
                .to_string()
        ]
    );
    // Transparent photographs are an object's, whatever the cameras.
    assert_eq!(
        scene_of(forward_grid(), true, 0, 1.0).space.space,
        SceneSpace::Object
    );
}

#[test]
fn cameras_one_way_but_spread_along_it_or_turned_widely_are_not_forward_facing() {
    // Walking down a corridor: all look along -z, but they lie 3 units
    // deep along it against 0.5 across.
    let corridor: Vec<Camera> = (0..8)
        .map(|k| {
            let eye = Vec3::new(0.5 * (k % 2) as f32, 0.0, -(k as f32) * 0.8);
            Camera::look_at(intrinsics(), eye, eye - Vec3::Z, Vec3::Y)
        })
        .collect();
    let analysis = scene_of(corridor, false, 255, 1.0).space;
    assert_eq!(analysis.space, SceneSpace::Unbounded, "{analysis:?}");
    assert_eq!(
        analysis.reasons.last().unwrap(),
        "not forward-facing: the cameras look one way (within 0°) but lie 2.80 units deep \
         along it against 0.25 across it (at most 25 % as deep as across in a forward-facing \
         capture)"
    );
    // An arc of ±60° around an object: turned by up to 60°.
    let arc = scene_of(ring(9, 0.0, 120.0), false, 255, 1.0).space;
    assert_eq!(arc.space, SceneSpace::Object, "{arc:?}");
    assert_eq!(
        arc.reasons[1],
        "not forward-facing: the cameras' viewing directions spread up to 60° from their mean \
         (at most 40° in a forward-facing capture)"
    );
    // An arc of ±20° is forward-facing: 0.06 deep against 1.37 across.
    let narrow = scene_of(ring(9, 0.0, 40.0), false, 255, 1.0).space;
    assert_eq!(narrow.space, SceneSpace::ForwardFacing, "{narrow:?}");
}

#[test]
fn sparse_points_far_beyond_the_cameras_make_the_scene_unbounded() {
    let cameras = around_an_object();
    let positions: Vec<DVec3> = cameras.iter().map(|c| c.position().as_dvec3()).collect();
    // 100 points: 80 on the objects (within 1 of the centre), 20 on walls
    // 12 to 15 away. The 90th percentile falls on the walls.
    let points: Vec<DVec3> = (0..100)
        .map(|k| {
            let radius = if k < 80 {
                k as f64 / 80.0
            } else {
                12.0 + (k - 80) as f64 * 0.15
            };
            DVec3::new(radius, 0.0, 0.0)
        })
        .collect();
    let summary = SparsePoints::measure(&points, &positions).unwrap();
    assert_eq!(summary.count, 100);
    let mut scene = scene_of(cameras.clone(), false, 255, 1.0);
    // The spiral's centre lies above the origin: distances from it.
    let centre = positions.iter().copied().sum::<DVec3>() / positions.len() as f64;
    let expected_far = DVec3::new(12.0 + 9.0 * 0.15, 0.0, 0.0).distance(centre) as f32;
    assert!((summary.far_distance - expected_far).abs() < 1e-5);
    scene.sparse_points = Some(summary);
    let analysis = analyse(&scene);
    assert_eq!(analysis.space, SceneSpace::Unbounded, "{analysis:?}");
    let camera_distance =
        positions.iter().map(|p| p.distance(centre)).sum::<f64>() / positions.len() as f64;
    assert_eq!(
        analysis.reasons[0],
        format!(
            "a tenth of the 100 sparse points lie farther than {expected_far:.2} units from the \
             cameras' centre, {:.1} times the cameras' own distance from it ({camera_distance:.2}): \
             content runs far beyond the cameras",
            expected_far as f64 / camera_distance
        )
    );
    // Points only on the objects: the object stays one.
    let near: Vec<DVec3> = points[..80].to_vec();
    scene.sparse_points = SparsePoints::measure(&near, &positions);
    assert_eq!(analyse(&scene).space, SceneSpace::Object);
    assert_eq!(SparsePoints::measure(&[], &positions), None);
}

#[test]
fn too_few_cameras_leave_it_to_alpha_and_the_box() {
    let two = ring(2, 1.0, 90.0);
    let analysis = scene_of(two.clone(), false, 255, 4.0).space;
    assert_eq!(analysis.space, SceneSpace::Unbounded);
    assert_eq!(
        analysis.reasons,
        vec![
            "no image has alpha and aabb_scale is 4: the background runs beyond the box of \
             the cameras"
                .to_string(),
            "too few cameras (fewer than 3) to tell how they are arranged".to_string()
        ]
    );
    assert_eq!(
        scene_of(two.clone(), false, 255, 1.0).space.space,
        SceneSpace::Object
    );
    assert_eq!(scene_of(two, true, 0, 4.0).space.space, SceneSpace::Object);
}

#[test]
fn an_override_keeps_the_analysis_and_says_so() {
    let scene = scene_of(around_an_object(), false, 255, 16.0);
    let found = scene.space.clone();
    let chosen = scene.with_space(SceneSpace::Object);
    assert_eq!(chosen.space.space, SceneSpace::Object);
    assert!(chosen.space.overridden);
    assert_eq!(
        chosen.space.reasons[0],
        "chosen by hand as object; the analysis found unbounded"
    );
    assert_eq!(chosen.space.reasons[1..], found.reasons[..]);
    // Overridden again: one note, the analysis's reasons as they were.
    let again = chosen.with_space(SceneSpace::ForwardFacing);
    assert_eq!(again.space.space, SceneSpace::ForwardFacing);
    assert_eq!(again.space.reasons[0], "chosen by hand as forward-facing");
    assert_eq!(again.space.reasons[1..], found.reasons[..]);
    // Chosen as found.
    let same = scene_of(around_an_object(), false, 255, 16.0).with_space(SceneSpace::Unbounded);
    assert_eq!(
        same.space.reasons[0],
        "chosen by hand as unbounded, as the analysis found"
    );
}

#[test]
fn spaces_are_named_in_kebab_case_everywhere() {
    use clap::ValueEnum;
    for (space, name) in [
        (SceneSpace::Object, "object"),
        (SceneSpace::Unbounded, "unbounded"),
        (SceneSpace::ForwardFacing, "forward-facing"),
    ] {
        assert_eq!(space.name(), name);
        assert_eq!(space.to_string(), name);
        assert_eq!(serde_json::to_value(space).unwrap(), name);
        assert_eq!(
            serde_json::from_value::<SceneSpace>(name.into()).unwrap(),
            space
        );
        assert_eq!(SceneSpace::from_str(name, false).unwrap(), space);
    }
}
