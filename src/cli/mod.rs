//! The commands' bodies, one module per command, each with its clap
//! arguments; `main.rs` only parses and dispatches. What several commands
//! share (loading a scene argument, durations, render memory, the kernels
//! line) is here; what runs share (`run.json`, building and restoring a
//! trainer) is in [`run_config`].

/// `println!` that never panics: a failed write to standard output (a full
/// disk, `> /dev/full`) is kept and reported when the command ends, as an
/// error with a non-zero status, instead of a panic. Defined before the
/// modules below so that it replaces the standard macro in all of them.
macro_rules! println {
    () => {
        zrak::interrupt::print_line(format_args!(""))
    };
    ($($arg:tt)*) => {
        zrak::interrupt::print_line(format_args!($($arg)*))
    };
}

pub mod bench;
pub mod convert;
pub mod demo;
pub mod eval;
pub mod export;
pub mod info;
pub mod quality;
pub mod render;
pub mod run_config;
pub mod train;
pub mod view;

use std::path::Path;

use zrak::scene::demo::{
    DemoConfig, {self as demo_scene},
};
use zrak::scene::photographs::{self, PhotographAnalysis, Switch};
use zrak::scene::{LoadOptions, Scene, SceneSpace};

/// A scene argument as the commands take it: `demo` for the built-in demo
/// scene (its views divided by `downscale`), else a folder.
pub fn load_scene(scene: &str, downscale: u32) -> anyhow::Result<Scene> {
    if scene == "demo" {
        anyhow::ensure!(downscale >= 1, "--downscale must be at least 1");
        let mut config = DemoConfig::default();
        anyhow::ensure!(
            downscale <= config.size,
            "--downscale {downscale} leaves no pixels of the demo scene's {size}×{size} \
             views: give at most {size}",
            size = config.size
        );
        config.size /= downscale;
        return Ok(demo_scene::build(&config));
    }
    Ok(Scene::load(Path::new(scene), LoadOptions { downscale })?)
}

/// `--space`: what a scene is treated as, `auto` leaving it to the scene
/// analysis (`zrak info` prints its choice and reasons).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum SpaceChoice {
    #[default]
    Auto,
    Object,
    Unbounded,
    ForwardFacing,
}

impl SpaceChoice {
    /// The space chosen by hand, or `None` for the analysis's.
    pub fn space(self) -> Option<SceneSpace> {
        match self {
            SpaceChoice::Auto => None,
            SpaceChoice::Object => Some(SceneSpace::Object),
            SpaceChoice::Unbounded => Some(SceneSpace::Unbounded),
            SpaceChoice::ForwardFacing => Some(SceneSpace::ForwardFacing),
        }
    }

    /// `scene` treated as chosen: as analysed for `auto` (a forward-facing
    /// LLFF capture then in NDC: [`Scene::in_its_space`]).
    pub fn apply(self, scene: Scene) -> Scene {
        match self.space() {
            Some(space) => scene.with_space(space),
            None => scene,
        }
        .in_its_space()
    }
}

/// `--appearance` and `--refine-cameras`: per-image appearance vectors and
/// camera corrections, `auto` leaving each to the analysis of the
/// photographs (`zrak info` prints its choices and reasons).
#[derive(clap::Args, Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct PhotographSwitches {
    /// A learned appearance vector per training image (exposure and white
    /// balance that change from photograph to photograph): auto turns it on
    /// where the photographs' exposure differs.
    #[arg(long, value_enum, default_value_t = Switch::Auto)]
    pub appearance: Switch,
    /// A learned pose correction per training image: auto turns it on for
    /// cameras estimated by structure from motion.
    #[arg(long = "refine-cameras", value_enum, default_value_t = Switch::Auto)]
    pub refine_cameras: Switch,
}

impl PhotographSwitches {
    /// What `scene`'s photographs call for, as these switches leave it.
    pub fn analyse(self, scene: &Scene) -> PhotographAnalysis {
        photographs::analyse(
            scene,
            photographs::Switches {
                appearance: self.appearance,
                refine_cameras: self.refine_cameras,
            },
        )
    }
}

/// The choices of `analysis`, a line each with its reasons under it, as
/// `zrak info` and `zrak train` print them.
pub fn photograph_lines(analysis: &PhotographAnalysis) -> Vec<String> {
    let mut lines = Vec::new();
    for (name, choice) in [
        ("appearance", &analysis.appearance),
        ("refine cams", &analysis.refine_cameras),
        ("masks", &analysis.masks),
    ] {
        lines.push(format!("{name:<11} {}", choice.summary()));
        lines.extend(choice.reasons.iter().map(|reason| format!("  - {reason}")));
    }
    lines
}

/// A duration argument in seconds: `90s`, `10m`, `2min`, `1h`, or a bare
/// number of seconds.
pub fn parse_duration(text: &str) -> Result<f64, String> {
    let text = text.trim();
    // The unit is the letters at the end, so that a number in exponent
    // form (`1e3s`) keeps its `e`.
    let number = text.trim_end_matches(|c: char| c.is_ascii_alphabetic());
    let (number, unit) = match &text[number.len()..] {
        "" => (number, "s"),
        unit => (number, unit),
    };
    let value: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a duration like 90s, 10m or 1h"))?;
    let scale = match unit {
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        _ => return Err(format!("`{text}`: unknown unit `{unit}` (use s, m or h)")),
    };
    if !(value > 0.0 && value.is_finite()) {
        return Err(format!("`{text}` must be a positive duration"));
    }
    Ok(value * scale)
}

/// The largest image side the commands that render accept: a frame is
/// rendered whole in memory (16384² pixels take ~4 GB as they render).
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// Bytes a view of `width` × `height` takes while it is rendered and
/// written: the rendered pixels (colour, depth, opacity: 5 floats) and the
/// 8-bit image, with the PNG encoder's copy.
pub fn render_bytes_per_view(width: u32, height: u32) -> u64 {
    width as u64 * height as u64 * (5 * 4 + 2 * 4)
}

/// The kernels and precision a cpu model computes with, as one line.
pub struct KernelsLine(pub zrak::model::CpuKernels);

impl std::fmt::Display for KernelsLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "kernels              {}, {} threads; precision: {}",
            self.0.name,
            rayon::current_num_threads(),
            self.0.precision
        )
    }
}

/// Parses `args` (the words after the command's name) as one command's
/// arguments alone, the way `zrak COMMAND args…` would, for the modules'
/// tests of argument handling.
#[cfg(test)]
pub fn parse_args<A: clap::Args>(args: &[&str]) -> Result<A, clap::Error> {
    use clap::Parser;

    #[derive(Parser)]
    #[command(name = "zrak")]
    struct Only<A: clap::Args> {
        #[command(flatten)]
        args: A,
    }
    Only::<A>::try_parse_from(std::iter::once("zrak").chain(args.iter().copied()))
        .map(|only| only.args)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_take_seconds_minutes_and_hours() {
        assert_eq!(parse_duration("90s"), Ok(90.0));
        assert_eq!(parse_duration("10m"), Ok(600.0));
        assert_eq!(parse_duration("2min"), Ok(120.0));
        assert_eq!(parse_duration("1h"), Ok(3600.0));
        assert_eq!(parse_duration("1.5h"), Ok(5400.0));
        // A bare number is seconds; spaces around it do not matter.
        assert_eq!(parse_duration(" 45 "), Ok(45.0));
        assert_eq!(parse_duration("30 s"), Ok(30.0));
        // The exponent's `e` is part of the number, not of the unit.
        assert_eq!(parse_duration("1e3s"), Ok(1000.0));
        assert_eq!(parse_duration("1e3"), Ok(1000.0));
    }

    #[test]
    fn durations_that_are_not_say_why() {
        assert_eq!(
            parse_duration("soon"),
            Err("`soon` is not a duration like 90s, 10m or 1h".into())
        );
        assert_eq!(
            parse_duration("10d"),
            Err("`10d`: unknown unit `d` (use s, m or h)".into())
        );
        assert_eq!(
            parse_duration(""),
            Err("`` is not a duration like 90s, 10m or 1h".into())
        );
        for not_positive in ["0s", "-5m", "0"] {
            assert_eq!(
                parse_duration(not_positive),
                Err(format!("`{not_positive}` must be a positive duration"))
            );
        }
        // `inf` and `nan` parse as floats but are no durations; their
        // letters read as a unit, which is refused first.
        assert!(
            parse_duration("inf")
                .unwrap_err()
                .contains("not a duration")
        );
        assert!(
            parse_duration("1e400s")
                .unwrap_err()
                .contains("positive duration")
        );
    }

    #[test]
    fn the_demo_scene_divides_its_views_by_the_downscale() {
        let full = DemoConfig::default().size;
        let scene = load_scene("demo", 16).unwrap();
        assert_eq!(scene.resolution(), Some((full / 16, full / 16)));
        assert_eq!(
            load_scene("demo", 0).unwrap_err().to_string(),
            "--downscale must be at least 1"
        );
        assert_eq!(
            load_scene("demo", full + 1).unwrap_err().to_string(),
            format!(
                "--downscale {} leaves no pixels of the demo scene's {full}×{full} views: \
                 give at most {full}",
                full + 1
            )
        );
    }

    #[test]
    fn space_choices_override_the_analysis_or_leave_it() {
        use clap::ValueEnum;
        let names: Vec<String> = SpaceChoice::value_variants()
            .iter()
            .map(|v| v.to_possible_value().unwrap().get_name().to_string())
            .collect();
        assert_eq!(names, ["auto", "object", "unbounded", "forward-facing"]);
        let scene = load_scene("demo", 16).unwrap();
        assert_eq!(scene.space.space, SceneSpace::Object);
        let kept = SpaceChoice::Auto.apply(scene.clone());
        assert_eq!(kept.space, scene.space);
        let chosen = SpaceChoice::Unbounded.apply(scene);
        assert_eq!(chosen.space.space, SceneSpace::Unbounded);
        assert!(chosen.space.overridden);
    }

    #[test]
    fn a_view_renders_in_28_bytes_a_pixel() {
        assert_eq!(render_bytes_per_view(1, 1), 28);
        assert_eq!(render_bytes_per_view(800, 800), 800 * 800 * 28);
        // No overflow at the largest side the commands accept.
        assert_eq!(
            render_bytes_per_view(MAX_IMAGE_SIDE, MAX_IMAGE_SIDE),
            28 * (MAX_IMAGE_SIDE as u64).pow(2)
        );
    }
}
