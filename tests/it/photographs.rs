//! What the photographs call for (appearance vectors, camera refinement,
//! masks) on the demo and, where they are beside the checkout, the shared
//! datasets: renders keep all three off, the phone capture turns on what
//! it needs; `zrak info` and `zrak train` say so with reasons, run.json
//! keeps it, and the flags override it.

use std::path::Path;
use std::process::Command;

use crate::common::zrak_bin;

fn zrak(args: &[&str]) -> String {
    let output = Command::new(zrak_bin()).args(args).output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "zrak {args:?}: {stderr}");
    String::from_utf8(output.stdout).unwrap() + &stderr
}

#[test]
fn renders_keep_appearance_refinement_and_masks_off_and_say_why() {
    let _cores = crate::common::shared();
    let mut scenes = vec![("demo", "the demo is rendered from the cameras it stores")];
    let lego = "../shared/data/nerf_synthetic/lego_400";
    if Path::new(lego).is_dir() {
        scenes.push((lego, "NeRF-synthetic renders"));
    } else {
        eprintln!("{lego} is not beside the checkout: skipped");
    }
    for (scene, pose_reason) in scenes {
        let printed = zrak(&["info", scene]);
        assert!(
            printed.contains("\nappearance  off (from the scene)\n  - overlapping views differ"),
            "{scene}: {printed}"
        );
        assert!(
            printed.contains("one appearance serves every view"),
            "{scene}: {printed}"
        );
        assert!(
            printed.contains(&format!(
                "\nrefine cams off (from the scene)\n  - {pose_reason}"
            )),
            "{scene}: {printed}"
        );
        assert!(
            printed.contains("\nmasks       off (from the scene)\n  - no image has a mask\n"),
            "{scene}: {printed}"
        );
    }
}

/// The demo with each training view's exposure and white balance
/// jittered (±1 stop, ±15 %): its overlapping views differ, so appearance
/// turns on; the same demo without jitter keeps it off.
#[test]
fn jittered_exposure_turns_appearance_on() {
    let _cores = crate::common::shared();
    let dir = tempfile::tempdir().unwrap();
    for (name, jitter, expected) in [
        ("plain", &[][..], "off"),
        (
            "jittered",
            &["--exposure-jitter", "1", "--white-balance-jitter", "0.15"][..],
            "on",
        ),
    ] {
        let out = dir.path().join(name);
        let out = out.to_str().unwrap();
        let mut args = vec!["demo", "--out", out, "--size", "32", "--views", "40"];
        args.extend_from_slice(jitter);
        zrak(&args);
        let printed = zrak(&["info", out]);
        assert!(
            printed.contains(&format!(
                "\nappearance  {expected} (from the scene)\n  - overlapping views differ"
            )),
            "{name}: {printed}"
        );
    }
}

#[test]
fn the_phone_capture_gets_appearance_and_camera_refinement_with_reasons() {
    let _cores = crate::common::shared();
    let gum = "../shared/data/real/gum-desk";
    if !Path::new(gum).is_dir() {
        eprintln!("{gum} is not beside the checkout: skipped");
        return;
    }
    let printed = zrak(&["info", gum]);
    assert!(
        printed.contains("\nappearance  on (from the scene)\n  - overlapping views differ"),
        "{printed}"
    );
    assert!(
        printed.contains("exposure or white balance changes from view to view"),
        "{printed}"
    );
    assert!(
        printed.contains(
            "\nrefine cams on (from the scene)\n  - transforms.json posed by structure from \
             motion: 246 frames carry colmap2nerf's `sharpness`; its cameras have lens \
             distortion; 246 of 246 images are JPEGs\n"
        ),
        "{printed}"
    );
}

#[test]
fn the_flags_override_the_choice_and_run_json_keeps_it() {
    let _cores = crate::common::shared();
    let printed = zrak(&[
        "info",
        "demo",
        "--downscale",
        "8",
        "--appearance",
        "on",
        "--refine-cameras",
        "off",
    ]);
    assert!(
        printed.contains(
            "\nappearance  on (chosen by hand)\n  - chosen with --appearance on (the scene alone \
             would have it off)\n  - overlapping views differ"
        ),
        "{printed}"
    );
    assert!(
        printed.contains(
            "\nrefine cams off (chosen by hand)\n  - chosen with --refine-cameras off (the scene \
             alone would have it off)\n"
        ),
        "{printed}"
    );

    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let printed = zrak(&[
        "train",
        "demo",
        "--downscale",
        "8",
        "--steps",
        "2",
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(
        printed.contains("appearance  off (from the scene)"),
        "{printed}"
    );
    let config: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    let photographs = &config["photographs"];
    assert_eq!(photographs["appearance"]["on"], false, "{config}");
    assert_eq!(
        photographs["appearance"]["chosen_by_hand"], false,
        "{config}"
    );
    assert_eq!(photographs["refine_cameras"]["on"], false, "{config}");
    assert_eq!(photographs["masks"]["on"], false, "{config}");
    assert!(
        photographs["refine_cameras"]["reasons"][0]
            .as_str()
            .unwrap()
            .starts_with("the demo is rendered"),
        "{config}"
    );

    // A resumed run keeps its own choice: the flags are refused.
    let output = Command::new(zrak_bin())
        .args([
            "train",
            "--resume",
            run.to_str().unwrap(),
            "--steps",
            "3",
            "--appearance",
            "on",
        ])
        .output()
        .unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--appearance and --refine-cameras are the run's own when resuming"),
        "{stderr}"
    );
}
