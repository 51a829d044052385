//! The scene analysis on the demo scenes and, where they are beside the
//! checkout, the shared datasets: each classified as the issue says, with
//! reasons that carry their numbers; `zrak info` prints them and `--space`
//! overrides them.

use std::path::Path;
use std::process::Command;

use zrak::scene::demo::{
    DemoConfig, {self},
};
use zrak::scene::{LoadOptions, Scene, SceneSpace};

use crate::common::zrak_bin;

fn small() -> DemoConfig {
    DemoConfig {
        size: 32,
        train_views: 20,
        val_views: 2,
        test_views: 2,
    }
}

#[test]
fn the_demo_is_an_object_and_its_large_and_unbounded_variants_are_unbounded() {
    let _cores = crate::common::shared();
    let object = demo::build(&small()).space;
    assert_eq!(object.space, SceneSpace::Object, "{object:?}");
    assert!(!object.overridden);
    assert!(
        object.reasons[0].ends_with(
            "of the images' pixels are transparent: the background is known, so the content \
             ends where the alpha does"
        ),
        "{:?}",
        object.reasons
    );
    // 24 cameras on the spiral, each looking at the origin.
    assert!(
        object.reasons[1].starts_with("the 24 cameras look inward at a point"),
        "{:?}",
        object.reasons
    );

    let large = demo::build_large(&small()).space;
    assert_eq!(large.space, SceneSpace::Unbounded, "{large:?}");
    assert!(
        large.reasons[0].ends_with(
            "but no image has alpha and aabb_scale is 8: the background runs beyond the cameras"
        ),
        "{:?}",
        large.reasons
    );

    let unbounded = demo::build_unbounded(&small()).space;
    assert_eq!(unbounded.space, SceneSpace::Unbounded, "{unbounded:?}");
    assert!(
        unbounded.reasons[0].ends_with(
            "but no image has alpha and aabb_scale is 16: the background runs beyond the cameras"
        ),
        "{:?}",
        unbounded.reasons
    );
}

#[test]
fn the_large_demo_written_to_disk_stays_unbounded_though_its_pngs_have_alpha() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    demo::write_large(&small(), dir.path()).unwrap();
    let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert!(scene.has_alpha, "the PNGs are RGBA");
    assert_eq!(
        scene.space.space,
        SceneSpace::Unbounded,
        "{:?}",
        scene.space
    );
    assert!(
        scene.space.reasons[0].contains("but every image is opaque everywhere and aabb_scale is 8"),
        "{:?}",
        scene.space.reasons
    );
    // The Blender layout of the demo keeps its transparency: an object.
    let dir = tempfile::tempdir().unwrap();
    demo::write(&small(), dir.path()).unwrap();
    let scene = Scene::load(dir.path(), LoadOptions::default()).unwrap();
    assert_eq!(scene.space.space, SceneSpace::Object, "{:?}", scene.space);
}

/// The shared datasets, where they are beside the checkout (as
/// `zrak bench` looks for lego_400).
#[test]
fn lego_is_an_object_and_gum_desk_is_unbounded() {
    let _cores = crate::common::shared();
    for (folder, expected) in [
        ("../shared/data/nerf_synthetic/lego_400", SceneSpace::Object),
        ("../shared/data/real/gum-desk", SceneSpace::Unbounded),
    ] {
        let path = Path::new(folder);
        if !path.is_dir() {
            eprintln!("{folder} is not beside the checkout: skipped");
            continue;
        }
        let scene = Scene::load(path, LoadOptions { downscale: 4 }).unwrap();
        assert_eq!(scene.space.space, expected, "{folder}: {:?}", scene.space);
    }
}

fn zrak(args: &[&str]) -> String {
    let output = Command::new(zrak_bin()).args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "zrak {args:?}: {stderr}");
    String::from_utf8(output.stdout).unwrap()
}

#[test]
fn zrak_info_prints_the_space_and_its_reasons_and_space_overrides_it() {
    let _cores = crate::common::shared();
    let printed = zrak(&["info", "demo", "--downscale", "8"]);
    assert!(
        printed.contains("\nspace       object (from the scene analysis; --space overrides it)\n"),
        "{printed}"
    );
    assert!(
        printed.contains("\n  - the 120 cameras look inward at a point"),
        "{printed}"
    );
    let printed = zrak(&["info", "demo", "--downscale", "8", "--space", "unbounded"]);
    assert!(
        printed.contains(
            "\nspace       unbounded (chosen with --space)\n  - chosen by hand as unbounded; the \
             analysis found object\n"
        ),
        "{printed}"
    );

    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("unbounded");
    let out_text = out.to_str().unwrap();
    zrak(&[
        "demo",
        "--unbounded",
        "--out",
        out_text,
        "--size",
        "16",
        "--views",
        "20",
    ]);
    let printed = zrak(&["info", out_text]);
    assert!(
        printed
            .contains("\nspace       unbounded (from the scene analysis; --space overrides it)\n"),
        "{printed}"
    );
    assert!(
        printed.contains(
            "but every image is opaque everywhere and aabb_scale is 16: the background runs \
             beyond the cameras"
        ),
        "{printed}"
    );
}
