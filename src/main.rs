//! The `zrak` command line: which commands there are and how each ends.
//! Each command's arguments and body are in its own module under `cli/`.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use zrak::interrupt;

mod cli;
use cli::bench::{DenseArgs, GpuBenchArgs, ThroughputArgs};
use cli::convert::ConvertArgs;
use cli::demo::DemoArgs;
use cli::eval::EvalArgs;
use cli::export::ExportCommand;
use cli::info::InfoArgs;
use cli::quality::QualityArgs;
use cli::render::RenderArgs;
use cli::train::TrainArgs;
use cli::view::ViewArgs;

/// Train neural radiance fields (NeRF, Mip-NeRF, Instant-NGP) while you watch.
#[derive(Parser)]
#[command(name = "zrak", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Subcommand)]
enum Command {
    /// Print a scene's splits, resolution, intrinsics and bounds.
    Info(InfoArgs),
    /// Write the built-in demo scene to a folder in the NeRF-synthetic layout.
    Demo(DemoArgs),
    /// Convert a COLMAP model (sparse/0 and images/) into an instant-ngp /
    /// nerfstudio transforms.json, centred and scaled as zrak loads it.
    Convert(ConvertArgs),
    /// Train a model on a scene, writing checkpoints and metrics to a run folder.
    Train(TrainArgs),
    /// Score a trained run on a split: per-image and mean PSNR and SSIM on white.
    Eval(EvalArgs),
    /// Render views of a trained run to PNG files.
    Render(RenderArgs),
    /// Export a trained run's surface as a mesh or a point cloud.
    #[command(subcommand)]
    Export(ExportCommand),
    /// Benchmarks that print figures (throughput per stage, peak memory).
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Open the viewer window and train while you watch (the default).
    View(ViewArgs),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// GFLOP/s of NeRF's dense networks (forward, backward) against the
    /// machine's measured f32 matrix-multiply peak.
    Dense(DenseArgs),
    /// Training-step throughput per stage on a scene (default: lego_400 when
    /// present beside the checkout, else the demo scene).
    Throughput(ThroughputArgs),
    /// The gpu engine on this machine's GPU: the adapter, its limits and
    /// features; a self-check of each model against the cpu engine (one
    /// training step and one render, with the parity tests' tolerances);
    /// then each model's stage times for a training step. Exits with
    /// status 1 if a check fails.
    Gpu(GpuBenchArgs),
    /// The accuracy-versus-time experiment: trains each model on each scene
    /// for a budget of training time, scores PSNR and SSIM at marks along
    /// the way, and writes results.json, results.csv, report.md and plots
    /// into --out. Run it again to continue an interrupted experiment.
    Quality(QualityArgs),
}

impl Command {
    /// Whether the command keeps running when its output pipe closes.
    /// Training keeps SIGPIPE ignored and prints without panicking, so
    /// that a closed pipe (`zrak train … 2>&1 | head`) never ends it before
    /// its checkpoint is written; the viewer has windows, not pipes, to
    /// care about; every other command only prints and may end with its
    /// reader.
    fn outlives_its_reader(&self) -> bool {
        matches!(
            self,
            Command::Train(_) | Command::Bench(BenchCommand::Quality(_)) | Command::View(_)
        )
    }

    /// What a first Ctrl-C does, as said when it comes; `None`: it ends
    /// the command at once.
    fn on_interrupt(&self) -> Option<&'static str> {
        match self {
            Command::Train(_) => Some("finishing the current step, then writing the checkpoint"),
            Command::Eval(_) => Some("finishing the current view"),
            Command::Render(_) => Some("finishing the current frame"),
            Command::Bench(BenchCommand::Throughput(_)) => {
                Some("finishing the current step, then reporting the steps measured")
            }
            Command::View(_) => {
                Some("closing the window, keeping every model trained since its last save")
            }
            Command::Bench(BenchCommand::Quality(_)) => Some(
                "finishing the current step or scored view, then writing the checkpoint and \
                 the report so far",
            ),
            Command::Info(_)
            | Command::Demo(_)
            | Command::Convert(_)
            | Command::Export(_)
            | Command::Bench(BenchCommand::Dense(_) | BenchCommand::Gpu(_)) => None,
        }
    }

    fn run(self) -> anyhow::Result<()> {
        match self {
            Command::Info(args) => cli::info::info(args),
            Command::Demo(args) => cli::demo::write_demo(args),
            Command::Convert(args) => cli::convert::convert(args),
            Command::Train(args) => cli::train::train(args),
            Command::Eval(args) => cli::eval::eval(args),
            Command::Render(args) => cli::render::render(args),
            Command::Export(command) => cli::export::export(command),
            Command::Bench(BenchCommand::Dense(args)) => cli::bench::bench_dense(args),
            Command::Bench(BenchCommand::Throughput(args)) => cli::bench::bench_throughput(args),
            Command::Bench(BenchCommand::Gpu(args)) => cli::bench::bench_gpu(args),
            Command::Bench(BenchCommand::Quality(args)) => cli::quality::bench_quality(args),
            Command::View(args) => cli::view::view(args),
        }
    }
}

/// Help, a version or a usage error, as clap prints them, except that
/// help or a version that cannot be written (`zrak --help > /dev/full`)
/// is an error rather than a success.
fn report_parse_outcome(outcome: clap::Error) -> ExitCode {
    use std::io::{IsTerminal, Write};
    if outcome.use_stderr() || std::io::stdout().is_terminal() {
        // Usage errors, and help for a terminal (in colour): clap's own.
        outcome.exit();
    }
    // Help piped into `head` ends quietly, as every other command's output.
    interrupt::end_quietly_on_closed_pipe();
    let mut stdout = std::io::stdout().lock();
    let written = write!(stdout, "{}", outcome.render()).and_then(|()| stdout.flush());
    match written {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            interrupt::note(&format!("error: cannot write to standard output: {error}"));
            ExitCode::FAILURE
        }
    }
}

fn main() -> ExitCode {
    // `zrak` alone opens the viewer, as `zrak view` does.
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(outcome) => return report_parse_outcome(outcome),
    };
    let command = cli
        .command
        .unwrap_or_else(|| Command::View(ViewArgs::default()));
    if !command.outlives_its_reader() {
        interrupt::end_quietly_on_closed_pipe();
    }
    if let Some(what_happens) = command.on_interrupt()
        && let Err(error) = interrupt::install(what_happens)
    {
        interrupt::note(&format!("error: {error}"));
        return ExitCode::FAILURE;
    }
    let result = command.run();
    // What the command printed did not all arrive: the work is done (and
    // saved), but the output is incomplete, which the status must say.
    let result = match (result, interrupt::stdout_error()) {
        (Ok(()), Some(error)) => Err(anyhow::anyhow!(error)),
        (result, _) => result,
    };
    match result {
        // The command has said what it kept; the status tells scripts it
        // did not run to its end.
        Ok(()) if interrupt::requested() => ExitCode::from(interrupt::EXIT_STATUS),
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            interrupt::note(&format!("error: {error:#}"));
            ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    fn parse(args: &[&str]) -> Result<Cli, clap::Error> {
        Cli::try_parse_from(std::iter::once("zrak").chain(args.iter().copied()))
    }

    #[test]
    fn the_command_line_is_well_formed() {
        // clap's own check of every argument's definition: names, defaults
        // that parse, conflicts and requirements that name real arguments.
        Cli::command().debug_assert();
    }

    #[test]
    fn zrak_alone_opens_the_viewer() {
        assert!(parse(&[]).unwrap().command.is_none());
        let bare = Command::View(ViewArgs::default());
        assert!(bare.outlives_its_reader());
        assert_eq!(
            bare.on_interrupt(),
            Some("closing the window, keeping every model trained since its last save")
        );
    }

    #[test]
    fn every_command_is_reached_by_its_name() {
        let named = |args: &[&str]| parse(args).unwrap().command.expect("a command");
        assert!(matches!(named(&["info", "lego"]), Command::Info(_)));
        assert!(matches!(named(&["demo", "--out", "d"]), Command::Demo(_)));
        assert!(matches!(
            named(&["convert", "c", "--out", "t.json"]),
            Command::Convert(_)
        ));
        assert!(matches!(
            named(&["train", "--resume", "R"]),
            Command::Train(_)
        ));
        assert!(matches!(named(&["eval", "R"]), Command::Eval(_)));
        assert!(matches!(
            named(&["render", "R", "--out", "f"]),
            Command::Render(_)
        ));
        assert!(matches!(named(&["view"]), Command::View(_)));
        assert!(matches!(
            named(&["bench", "dense"]),
            Command::Bench(BenchCommand::Dense(_))
        ));
        assert!(matches!(
            named(&["bench", "throughput"]),
            Command::Bench(BenchCommand::Throughput(_))
        ));
        assert!(matches!(
            named(&["bench", "gpu"]),
            Command::Bench(BenchCommand::Gpu(_))
        ));
        assert!(matches!(
            named(&["bench", "quality", "demo", "--out", "D"]),
            Command::Bench(BenchCommand::Quality(_))
        ));
        let error = parse(&["bench"]).err().expect("bench needs a benchmark");
        assert_eq!(
            error.kind(),
            clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
        );
        let error = parse(&["fit"]).err().expect("no such command");
        assert_eq!(error.kind(), clap::error::ErrorKind::InvalidSubcommand);
    }

    #[test]
    fn only_long_running_commands_outlive_a_closed_pipe() {
        let command = |args: &[&str]| parse(args).unwrap().command.expect("a command");
        for outlives in [
            &["train", "--resume", "R"][..],
            &["bench", "quality", "demo", "--out", "D"],
            &["view"],
        ] {
            assert!(command(outlives).outlives_its_reader(), "{outlives:?}");
        }
        for ends in [
            &["info", "lego"][..],
            &["eval", "R"],
            &["render", "R", "--out", "f"],
            &["bench", "throughput"],
            &["bench", "gpu"],
        ] {
            assert!(!command(ends).outlives_its_reader(), "{ends:?}");
        }
        // Commands with nothing to finish end at once on Ctrl-C.
        for at_once in [
            &["info", "lego"][..],
            &["demo", "--out", "d"],
            &["convert", "c", "--out", "t.json"],
            &["bench", "dense"],
            &["bench", "gpu"],
        ] {
            assert_eq!(command(at_once).on_interrupt(), None, "{at_once:?}");
        }
        assert_eq!(
            command(&["eval", "R"]).on_interrupt(),
            Some("finishing the current view")
        );
    }
}
