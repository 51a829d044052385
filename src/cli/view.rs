//! `zrak view` (and `zrak` alone): the viewer window, training while you
//! watch.

use std::path::PathBuf;

use clap::{Args, FromArgMatches};
use zrak::app::ui::ExportKind;
use zrak::app::viewer::ViewerOptions;
use zrak::engine::EngineKind;
use zrak::field::ModelKind;
use zrak::field::common::Sampling;
use zrak::field::mlp::Precision;
use zrak::scene::crop::CropArg;
use zrak::session::protocol::SceneSource;

use super::{PhotographSwitches, SpaceChoice};

#[derive(Args, Debug)]
pub struct ViewArgs {
    /// A scene folder (default: the built-in demo scene).
    scene: Option<PathBuf>,
    /// Default: gpu on a real GPU, cpu otherwise.
    #[arg(long, value_enum)]
    engine: Option<EngineKind>,
    #[arg(long, value_enum, default_value_t = ModelKind::Ngp)]
    model: ModelKind,
    /// The sampler, for the models that have it (as `zrak train`'s);
    /// default: proposal fields on an unbounded scene where the model has
    /// them, else the occupancy grid.
    #[arg(long, value_enum)]
    sampling: Option<Sampling>,
    /// Save a PNG of the window to this path (after --screenshot-after).
    #[arg(long)]
    screenshot: Option<PathBuf>,
    /// Seconds after opening to take the screenshot.
    #[arg(long, default_value_t = 5.0, requires = "screenshot")]
    screenshot_after: f64,
    /// Close the window by itself after this many seconds.
    #[arg(long)]
    quit_after: Option<f64>,
    /// On exit, write per-frame times (UI update, time between frames; camera
    /// moving or still; median and 95th percentile) as JSON to this path.
    #[arg(long)]
    frame_log: Option<PathBuf>,
    /// Orbit the camera by itself, as if dragged (to measure a moving camera).
    #[arg(long)]
    auto_orbit: bool,
    /// How the cpu engine computes the networks' products: f32, or mixed
    /// (bf16 products, f32 sums, on processors with AVX512-BF16). Default:
    /// mixed where the processor has bf16 kernels, else f32.
    #[arg(long, value_enum)]
    precision: Option<Precision>,
    /// How many of the runs kept on closing (File → Recent runs) stay on
    /// disk: the newest; older ones are removed when another is kept. 0
    /// keeps nothing of this session and removes nothing kept before.
    #[arg(long, default_value_t = zrak::train::kept::DEFAULT_KEPT_RUNS)]
    keep_runs: usize,
    /// Start with this crop box, as `zrak render --crop`: `cx,cy,cz,sx,sy,sz`
    /// (centre and size), optionally `,rx,ry,rz` (degrees); its window opens.
    #[arg(long, value_name = "BOX", allow_hyphen_values = true)]
    crop: Option<CropArg>,
    /// Open the Export window on this kind (e.g. for a screenshot).
    #[arg(long, value_enum, value_name = "KIND")]
    open_export: Option<ExportKind>,
    /// Open this camera path (nerfstudio's camera_path.json) in the path
    /// editor once the scene has loaded.
    #[arg(long)]
    camera_path: Option<PathBuf>,
    /// Put the camera at this time of the path, in seconds (for screenshots).
    #[arg(long, requires = "camera_path")]
    path_time: Option<f64>,
    /// Play the camera path once it has loaded (from --path-time, or the
    /// start).
    #[arg(long, requires = "camera_path")]
    path_play: bool,
    /// What the scene (and every scene opened) is treated as: a bounded
    /// object, unbounded, or a forward-facing capture; auto leaves it to
    /// the scene analysis (the Scene panel shows its choice and why).
    #[arg(long, value_enum, default_value_t = SpaceChoice::Auto)]
    space: SpaceChoice,
    /// Per-image appearance and camera refinement for every scene opened:
    /// auto leaves each to the analysis of its photographs (the Scene panel
    /// shows the choices and why).
    #[command(flatten)]
    photographs: PhotographSwitches,
}

impl Default for ViewArgs {
    /// What `zrak view` with no arguments means, which `zrak` alone runs:
    /// read from the declarations above, so the two cannot drift apart.
    fn default() -> Self {
        let command = <Self as Args>::augment_args(clap::Command::new("view"));
        let matches = command
            .try_get_matches_from(["view"])
            .expect("`zrak view` needs no arguments");
        Self::from_arg_matches(&matches).expect("defaults are valid view arguments")
    }
}

/// Opens the viewer window on the demo scene or a folder.
pub fn view(args: ViewArgs) -> anyhow::Result<()> {
    check_seconds(&args)?;
    zrak::app::viewer::run(ViewerOptions {
        source: match args.scene {
            Some(folder) => SceneSource::Folder(folder),
            None => SceneSource::Demo,
        },
        engine: args.engine,
        model: args.model,
        sampling: args.sampling,
        screenshot: args.screenshot,
        screenshot_after: args.screenshot_after,
        quit_after: args.quit_after,
        frame_log: args.frame_log,
        auto_orbit: args.auto_orbit,
        precision: args.precision.unwrap_or_else(Precision::best_available),
        kept_runs: args.keep_runs,
        crop: match args.crop {
            Some(CropArg::Box(crop)) => Some(crop),
            Some(CropArg::None) | None => None,
        },
        open_export: args.open_export,
        camera_path: args.camera_path,
        path_time: args.path_time,
        path_play: args.path_play,
        space: args.space.space(),
        photographs: zrak::scene::photographs::Switches {
            appearance: args.photographs.appearance,
            refine_cameras: args.photographs.refine_cameras,
        },
    })
}

/// Refuses times the window could never wait for.
fn check_seconds(args: &ViewArgs) -> anyhow::Result<()> {
    for (flag, value) in [
        ("--screenshot-after", Some(args.screenshot_after)),
        ("--quit-after", args.quit_after),
        ("--path-time", args.path_time),
    ] {
        if let Some(value) = value {
            anyhow::ensure!(
                value.is_finite() && value >= 0.0,
                "{flag} must be a number of seconds ≥ 0, got {value}"
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::parse_args;
    use clap::error::ErrorKind;

    #[test]
    fn the_viewer_opens_the_demo_with_instant_ngp_by_default() {
        let args = ViewArgs::default();
        assert_eq!(args.scene, None);
        assert_eq!(args.engine, None);
        assert_eq!(args.model, ModelKind::Ngp);
        assert_eq!(args.sampling, None);
        assert_eq!(args.screenshot, None);
        assert_eq!(args.screenshot_after, 5.0);
        assert_eq!(args.quit_after, None);
        assert_eq!(args.frame_log, None);
        assert!(!args.auto_orbit);
        assert_eq!(args.precision, None);
        assert_eq!(args.keep_runs, zrak::train::kept::DEFAULT_KEPT_RUNS);
        assert_eq!(args.crop, None);
        assert_eq!(args.open_export, None);
        assert_eq!(args.camera_path, None);
        assert_eq!(args.path_time, None);
        assert!(!args.path_play);
    }

    #[test]
    fn the_viewer_takes_a_crop_box_and_an_export_kind() {
        let args: ViewArgs =
            parse_args(&["--crop", "-0.5,0,0,1,2,2", "--open-export", "camera-path"]).unwrap();
        assert!(matches!(args.crop, Some(CropArg::Box(b)) if b.centre.x == -0.5));
        assert_eq!(args.open_export, Some(ExportKind::CameraPath));
        assert!(parse_args::<ViewArgs>(&["--crop", "1,2"]).is_err());
    }

    #[test]
    fn a_camera_path_opens_in_the_editor_at_a_time() {
        let args: ViewArgs = parse_args(&[
            "scene",
            "--camera-path",
            "paths/orbit.json",
            "--path-time",
            "1.5",
        ])
        .unwrap();
        assert_eq!(args.camera_path, Some(PathBuf::from("paths/orbit.json")));
        assert_eq!(args.path_time, Some(1.5));
        assert!(!args.path_play);
        assert!(check_seconds(&args).is_ok());
        let args: ViewArgs = parse_args(&["--camera-path", "p.json", "--path-play"]).unwrap();
        assert!(args.path_play);
        assert_eq!(args.path_time, None);
        // A time needs a path to be a time of, and so does playing.
        for args in [&["--path-time", "2"][..], &["--path-play"][..]] {
            let error = parse_args::<ViewArgs>(args).unwrap_err();
            assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
            assert!(error.to_string().contains("--camera-path"), "{error}");
        }
        let args: ViewArgs = parse_args(&["--camera-path", "p.json", "--path-time=-0.5"]).unwrap();
        assert_eq!(
            check_seconds(&args).unwrap_err().to_string(),
            "--path-time must be a number of seconds ≥ 0, got -0.5"
        );
    }

    #[test]
    fn a_screenshot_time_needs_a_screenshot() {
        let error = parse_args::<ViewArgs>(&["--screenshot-after", "3"]).unwrap_err();
        assert_eq!(error.kind(), ErrorKind::MissingRequiredArgument);
        assert!(
            error.to_string().contains("--screenshot <SCREENSHOT>"),
            "{error}"
        );
        let args: ViewArgs = parse_args(&[
            "scene",
            "--screenshot",
            "docs/viewer.png",
            "--screenshot-after",
            "20",
            "--quit-after",
            "22",
        ])
        .unwrap();
        assert_eq!(args.scene, Some(PathBuf::from("scene")));
        assert_eq!(args.screenshot, Some(PathBuf::from("docs/viewer.png")));
        assert_eq!((args.screenshot_after, args.quit_after), (20.0, Some(22.0)));
        assert!(check_seconds(&args).is_ok());
    }

    #[test]
    fn times_the_window_could_never_wait_for_are_refused() {
        let args: ViewArgs = parse_args(&["--quit-after=-1"]).unwrap();
        assert_eq!(
            check_seconds(&args).unwrap_err().to_string(),
            "--quit-after must be a number of seconds ≥ 0, got -1"
        );
        let args: ViewArgs =
            parse_args(&["--screenshot", "a.png", "--screenshot-after", "inf"]).unwrap();
        assert_eq!(
            check_seconds(&args).unwrap_err().to_string(),
            "--screenshot-after must be a number of seconds ≥ 0, got inf"
        );
    }
}
