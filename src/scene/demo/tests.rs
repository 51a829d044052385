use super::*;

fn small() -> DemoConfig {
    DemoConfig {
        size: 64,
        train_views: 6,
        val_views: 2,
        test_views: 3,
    }
}

fn camera_at(size: u32, elevation_deg: f32, azimuth_deg: f32) -> Camera {
    let intrinsics = Intrinsics::from_fov_x(size, size, CAMERA_ANGLE_X);
    let eye = on_hemisphere(elevation_deg.to_radians(), azimuth_deg.to_radians());
    Camera::look_at(intrinsics, eye, Vec3::ZERO, Vec3::Z)
}

fn pixel_at(image: &ImageRgba8, camera: &Camera, point: Vec3) -> [f32; 4] {
    let (u, v) = camera.project(point).expect("point in front of the camera");
    image.rgba(u as u32, v as u32)
}

#[test]
fn two_builds_are_identical() {
    let a = build(&small());
    let b = build(&small());
    for (x, y) in a.frames().zip(b.frames()) {
        assert_eq!(x.camera, y.camera);
        assert_eq!(x.image.data, y.image.data);
    }
    assert_eq!(a.frames().count(), 11);
    assert_eq!((a.train.len(), a.val.len(), a.test.len()), (6, 2, 3));
    assert_eq!(a.resolution(), Some((64, 64)));
    assert_eq!(a.format, SceneFormat::Demo);
    assert_eq!(a.name, "demo");
    assert!(a.has_alpha);
    assert_eq!(a.bounds, UnitCubeMapping::BLENDER.world_bounds());
}

#[test]
fn training_scales_add_each_view_at_half_and_quarter_size() {
    let scene = build(&small());
    let views = scene.train.len();
    let scaled = build(&small()).with_training_scales(3);
    assert_eq!(scaled.train.len(), 3 * views);
    assert_eq!(scaled.val.len(), scene.val.len());
    assert_eq!(scaled.test.len(), scene.test.len());
    // Full-size views first, then each view at ½ and ¼.
    for (index, original) in scene.train.iter().enumerate() {
        assert_eq!(scaled.train[index].image.data, original.image.data);
        for (level, factor) in [2u32, 4].into_iter().enumerate() {
            let smaller = &scaled.train[views + 2 * index + level];
            let k = smaller.camera.intrinsics;
            assert_eq!((k.width, k.height), (64 / factor, 64 / factor));
            assert_eq!(
                smaller.image.data,
                original.image.downscaled(factor).data,
                "the photograph is the area average of the full-size one"
            );
            // A pixel's cone is the one through the centre of the
            // factor × factor block it covers, `factor` times as wide.
            for (i, j) in [(0, 0), (3, 7), (k.width - 1, k.height - 1)] {
                let ray = smaller.camera.pixel_ray(i, j);
                let centre = original.camera.ray_through(
                    factor as f32 * (i as f32 + 0.5),
                    factor as f32 * (j as f32 + 0.5),
                );
                assert!((ray.origin - centre.origin).length() < 1e-5);
                assert!((ray.direction - centre.direction).length() < 1e-5);
                let ratio = ray.radius() / centre.radius();
                assert!(
                    (ratio - factor as f32).abs() < 1e-4 * factor as f32,
                    "{ratio}"
                );
            }
        }
    }
    assert_eq!(build(&small()).with_training_scales(1).train.len(), views);
    // The same scene to a checkpoint, so a multiscale run's checkpoint
    // loads in the viewer, which trains at one size.
    assert_eq!(scaled.photographed_training_views().len(), views);
    assert_eq!(
        crate::scene::identity::SceneIdentity::of(&scaled),
        crate::scene::identity::SceneIdentity::of(&scene)
    );
}

#[test]
fn cameras_look_at_origin_from_upper_hemisphere() {
    let config = DemoConfig::default();
    let mut all = Vec::new();
    for split in Split::ALL {
        let cameras = split_cameras(&config, split);
        assert_eq!(cameras.len(), config.views(split));
        all.extend(cameras);
    }
    for camera in &all {
        let p = camera.position();
        assert!((p.length() - CAMERA_DISTANCE).abs() < 1e-4);
        let elevation = (p.z / p.length()).asin().to_degrees();
        assert!((9.9..=80.1).contains(&elevation), "elevation {elevation}");
        assert!((camera.forward() + p.normalize()).length() < 1e-5);
        // The camera's up axis leans towards world up: images are upright.
        assert!(camera.camera_to_world.y_axis.z > 0.0);
        let (u, v) = camera.project(Vec3::ZERO).unwrap();
        assert!((u - 64.0).abs() < 1e-3 && (v - 64.0).abs() < 1e-3);
    }
    // Validation and test views are novel: no closer to a training view
    // than a good fraction of the spacing between training views.
    let train = split_cameras(&config, Split::Train);
    let nearest_train = |position: Vec3, skip: Option<usize>| {
        train
            .iter()
            .enumerate()
            .filter(|(index, _)| Some(*index) != skip)
            .map(|(_, t)| (t.position() - position).length())
            .fold(f32::INFINITY, f32::min)
    };
    let mut spacing: Vec<f32> = (0..train.len())
        .map(|k| nearest_train(train[k].position(), Some(k)))
        .collect();
    spacing.sort_by(f32::total_cmp);
    let median_spacing = spacing[spacing.len() / 2];
    for split in [Split::Val, Split::Test] {
        let cameras = split_cameras(&config, split);
        for camera in &cameras {
            let nearest = nearest_train(camera.position(), None);
            assert!(
                nearest > 0.4 * median_spacing,
                "{split:?} view {nearest} from a training view (spacing {median_spacing})"
            );
        }
        // And they are spread over the hemisphere, not bunched.
        let elevations: Vec<f32> = cameras
            .iter()
            .map(|c| (c.position().z / CAMERA_DISTANCE).asin().to_degrees())
            .collect();
        let lowest = elevations.iter().copied().fold(f32::INFINITY, f32::min);
        let highest = elevations.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        assert!(lowest < 25.0 && highest > 60.0, "{split:?}: {elevations:?}");
    }
    // Val and test differ from each other too.
    let val = split_cameras(&config, Split::Val);
    for camera in split_cameras(&config, Split::Test) {
        assert!(
            val.iter()
                .all(|v| (v.position() - camera.position()).length() > 0.3)
        );
    }
}

#[test]
fn surface_distance_is_zero_on_each_object_and_grows_away() {
    // On the red ball's top, the green block's top face, the blue
    // cylinder's cap and the stand's rim; then above them.
    let on = [
        RED_CENTRE + Vec3::Z * RED_RADIUS,
        GREEN_CENTRE + Vec3::Z * GREEN_HALF,
        BLUE_BOTTOM + Vec3::Z * BLUE_HEIGHT,
        Vec3::new(GROUND_RADIUS, 0.0, GROUND_Z - 0.5 * GROUND_THICKNESS),
        YELLOW_CENTRE - Vec3::Y * YELLOW_RADIUS,
    ];
    for p in on {
        assert!(surface_distance(p) < 1e-5, "{p}: {}", surface_distance(p));
    }
    assert!((surface_distance(RED_CENTRE + Vec3::Z * (RED_RADIUS + 0.1)) - 0.1).abs() < 1e-5);
    // Inside the ball, the distance to its surface.
    assert!((surface_distance(RED_CENTRE + Vec3::Z * 0.2) - 0.22).abs() < 1e-5);
    // Far above everything: the distance to the blue cylinder's cap.
    let top = BLUE_BOTTOM + Vec3::Z * (BLUE_HEIGHT + 1.0);
    assert!((surface_distance(top) - 1.0).abs() < 1e-5);
}

#[test]
fn content_fits_in_scene_box() {
    let bounds = UnitCubeMapping::BLENDER.world_bounds();
    let inner = crate::scene::Aabb::new(bounds.min + 0.25, bounds.max - 0.25);
    let world = World::new();
    // Whatever a camera sees lies well inside the scene box, and inside
    // the sphere that `trace` uses to skip rays that miss everything
    // (checked without that shortcut).
    for (elevation, azimuth) in [(10.0, 30.0), (45.0, 160.0), (80.0, -110.0)] {
        let camera = camera_at(64, elevation, azimuth);
        for ray in camera.all_rays() {
            if let Some(hit) = world.intersect(ray.origin, ray.direction) {
                let p = ray.at(hit.t);
                assert!(inner.contains(p), "{p} outside the inner box");
                assert!(
                    p.length() <= CONTENT_RADIUS,
                    "{p} outside the content sphere"
                );
            }
        }
    }
}

#[test]
fn corner_is_transparent_and_centre_is_opaque() {
    for camera in split_cameras(&small(), Split::Train) {
        let image = render_view(&camera);
        let last = image.width - 1;
        for (x, y) in [(0, 0), (last, 0), (0, last), (last, last)] {
            assert_eq!(image.rgba(x, y)[3], 0.0, "corner ({x}, {y})");
        }
        let mid = image.width / 2;
        assert_eq!(image.rgba(mid, mid)[3], 1.0);
        // And the silhouette has soft edges from supersampling.
        assert!(image.data.chunks_exact(4).any(|p| p[3] > 0 && p[3] < 255));
    }
}

#[test]
fn primitives_show_their_colours() {
    // From high up every object is in plain sight.
    let camera = camera_at(128, 75.0, -100.0);
    let image = render_view(&camera);
    let top_of_blue = BLUE_BOTTOM + Vec3::new(0.0, 0.0, BLUE_HEIGHT);
    let top_of_green = GREEN_CENTRE + Vec3::new(0.0, 0.0, GREEN_HALF);
    let [r, g, b, a] = pixel_at(&image, &camera, RED_CENTRE);
    assert!(
        a == 1.0 && r > 0.5 && g < 0.35 && b < 0.35,
        "red: {r} {g} {b}"
    );
    let [r, g, b, a] = pixel_at(&image, &camera, top_of_green);
    assert!(
        a == 1.0 && g > 0.5 && r < 0.35 && b < 0.35,
        "green: {r} {g} {b}"
    );
    let [r, g, b, a] = pixel_at(&image, &camera, top_of_blue);
    assert!(
        a == 1.0 && b > 0.5 && r < 0.35 && g < 0.45,
        "blue: {r} {g} {b}"
    );
    let [r, g, b, a] = pixel_at(&image, &camera, YELLOW_CENTRE);
    assert!(
        a == 1.0 && r > 0.6 && g > 0.5 && b < 0.3,
        "yellow: {r} {g} {b}"
    );
    // The stand shows both checker colours.
    // Centres of two neighbouring squares at the front of the stand.
    let light = pixel_at(&image, &camera, Vec3::new(-0.11, -0.99, GROUND_Z));
    let dark = pixel_at(&image, &camera, Vec3::new(0.11, -0.99, GROUND_Z));
    assert!(light[0] - dark[0] > 0.3, "checker {light:?} vs {dark:?}");
}

#[test]
fn glossy_ball_is_view_dependent_and_matte_box_is_not() {
    let size = 128;
    let a = camera_at(size, 35.0, -40.0);
    let b = camera_at(size, 35.0, -140.0);
    let world = World::new();
    // The point of the red ball where camera `a` sees the key light's
    // highlight: its normal halves the angle between light and eye.
    let mut normal = (world.key + (a.position() - RED_CENTRE).normalize()).normalize();
    for _ in 0..5 {
        let point = RED_CENTRE + RED_RADIUS * normal;
        normal = (world.key + (a.position() - point).normalize()).normalize();
    }
    let glossy_point = RED_CENTRE + RED_RADIUS * normal;
    let matte_point = GREEN_CENTRE + Vec3::new(0.0, 0.0, GREEN_HALF);
    let (image_a, image_b) = (render_view(&a), render_view(&b));
    // Both cameras see both points directly.
    for camera in [&a, &b] {
        for (point, object) in [(glossy_point, 1), (matte_point, 2)] {
            let (u, v) = camera.project(point).unwrap();
            let ray = camera.ray_through(u, v);
            let hit = world.intersect(ray.origin, ray.direction).unwrap();
            assert_eq!(hit.object, object);
            assert!((ray.at(hit.t) - point).length() < 1e-3);
        }
    }
    let difference =
        |p: [f32; 4], q: [f32; 4]| (0..3).map(|i| (p[i] - q[i]).abs()).fold(0.0, f32::max);
    let glossy = difference(
        pixel_at(&image_a, &a, glossy_point),
        pixel_at(&image_b, &b, glossy_point),
    );
    let matte = difference(
        pixel_at(&image_a, &a, matte_point),
        pixel_at(&image_b, &b, matte_point),
    );
    assert!(glossy > 0.4, "glossy point changes by only {glossy}");
    // Camera `a` sees a white highlight there, not just a brighter red.
    let [r, g, b, _] = pixel_at(&image_a, &a, glossy_point);
    assert!(r.min(g).min(b) > 0.75, "highlight {r} {g} {b}");
    assert!(matte < 0.02, "matte point changes by {matte}");
}

#[test]
fn shadows_fall_away_from_the_key_light() {
    let world = World::new();
    // Just beyond the red ball, away from the light, the stand is in
    // shadow; on the lit side it is not.
    let down = |p: Vec3| world.trace(p + Vec3::Z, -Vec3::Z).unwrap();
    let away = Vec3::new(-world.key.x, -world.key.y, 0.0).normalize();
    let foot = Vec3::new(RED_CENTRE.x, RED_CENTRE.y, GROUND_Z);
    let shaded = down(foot + (RED_RADIUS + 0.1) * away);
    let lit = down(foot - (RED_RADIUS + 0.1) * away);
    assert!(
        lit.max_element() > shaded.max_element() + 0.3,
        "{lit} vs {shaded}"
    );
}

#[test]
fn write_produces_blender_layout() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("new").join("demo");
    let config = small();
    write(&config, &root).unwrap();
    let scene = build(&config);
    for split in Split::ALL {
        let text = std::fs::read_to_string(root.join(format!("transforms_{}.json", split.name())))
            .unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        let angle = json["camera_angle_x"].as_f64().unwrap();
        assert!((angle - CAMERA_ANGLE_X as f64).abs() < 1e-7);
        let entries = json["frames"].as_array().unwrap();
        let frames = scene.split(split);
        assert_eq!(entries.len(), frames.len());
        for (index, (entry, frame)) in entries.iter().zip(frames).enumerate() {
            let file_path = entry["file_path"].as_str().unwrap();
            assert_eq!(file_path, format!("./{}/r_{index}", split.name()));
            let matrix = entry["transform_matrix"].as_array().unwrap();
            assert_eq!(matrix.len(), 4);
            for (r, row) in matrix.iter().enumerate() {
                let row = row.as_array().unwrap();
                assert_eq!(row.len(), 4);
                let expected = frame.camera.camera_to_world.row(r);
                for c in 0..4 {
                    let value = row[c].as_f64().unwrap() as f32;
                    assert!(
                        (value - expected[c]).abs() < 1e-6,
                        "{split:?} {index} [{r}][{c}]"
                    );
                }
            }
            let png = root.join(format!("{}.png", &file_path[2..]));
            let loaded = crate::scene::load_image(&png).unwrap();
            assert!(loaded.file_has_alpha);
            assert_eq!(loaded.image, frame.image);
        }
    }
}

#[test]
fn write_into_unwritable_place_names_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("a_file");
    std::fs::write(&file, "not a folder").unwrap();
    let target = file.join("demo");
    let config = DemoConfig {
        size: 8,
        train_views: 1,
        val_views: 1,
        test_views: 1,
    };
    let error = write(&config, &target).unwrap_err();
    assert!(
        error.path().starts_with(&target),
        "{}",
        error.path().display()
    );
    let message = error.to_string();
    assert!(message.contains(&target.display().to_string()), "{message}");
    assert!(message.contains("cannot create folder"), "{message}");
}
