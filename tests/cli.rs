//! The `zrak` binary as a user runs it: resuming from a run folder alone,
//! interrupts, closed pipes and the README's own commands.

mod common;

use std::path::Path;
use std::process::{Command, Output, Stdio};

use common::finish;
use zrak::train::checkpoint::Checkpoint;

fn zrak() -> Command {
    Command::new(common::zrak_bin())
}

/// Runs `zrak ARGS` in `dir` and returns its output, whatever the status.
fn run_in(dir: &Path, args: &[&str]) -> Output {
    zrak()
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .output()
        .expect("the zrak binary starts")
}

/// Runs `zrak ARGS` in `dir`, failing the test with its output unless it
/// succeeds; returns its stdout.
fn succeed(dir: &Path, args: &[&str]) -> String {
    let output = run_in(dir, args);
    assert!(
        output.status.success(),
        "zrak {} failed ({}):\nstdout:\n{}\nstderr:\n{}",
        args.join(" "),
        output.status,
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// Runs `zrak ARGS` in `dir`, expecting it to fail; returns its stderr.
fn fail(dir: &Path, args: &[&str]) -> String {
    let output = run_in(dir, args);
    assert!(
        !output.status.success(),
        "zrak {} should have failed:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&output.stdout)
    );
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// The trainer's part of a run's checkpoint header.
fn checkpoint_header(run: &Path) -> serde_json::Value {
    let checkpoint = Checkpoint::load(&run.join("checkpoint.zrak"))
        .unwrap_or_else(|e| panic!("the run's checkpoint loads: {e}"));
    checkpoint.header
}

fn checkpoint_step(run: &Path) -> u64 {
    checkpoint_header(run)["trainer"]["step"]
        .as_u64()
        .expect("the checkpoint records its step")
}

fn temp_dir() -> tempfile::TempDir {
    tempfile::tempdir().expect("a temporary folder")
}

#[test]
fn resume_takes_everything_from_the_run_folder() {
    let dir = temp_dir();
    let d = dir.path();
    // Settings that differ from every default, so the resumed run can only
    // match them by reading run.json.
    succeed(
        d,
        &[
            "train",
            "demo",
            "--steps",
            "2",
            "--downscale",
            "4",
            "--loss",
            "l2",
            "--seed",
            "7",
            "--engine",
            "cpu",
            "--out",
            "run",
        ],
    );
    let run = d.join("run");
    assert_eq!(checkpoint_step(&run), 2);

    // The README's form: the run folder alone.
    let out = succeed(d, &["train", "--resume", "run", "--steps", "3"]);
    assert!(out.contains("trained 3 steps"), "{out}");
    let header = checkpoint_header(&run);
    assert_eq!(header["trainer"]["step"], 3);
    assert_eq!(header["trainer"]["seed"], 7);
    assert_eq!(header["run"]["downscale"], 4);
    assert_eq!(header["run"]["loss"], "L2");
    assert_eq!(header["run"]["engine"], "cpu");

    // The same scene named explicitly is fine.
    succeed(d, &["train", "demo", "--resume", "run", "--steps", "4"]);
    assert_eq!(checkpoint_step(&run), 4);

    // Another scene is refused, naming both.
    succeed(
        d,
        &["demo", "--out", "other", "--size", "16", "--views", "2"],
    );
    let error = fail(d, &["train", "other", "--resume", "run", "--steps", "5"]);
    assert!(
        error.contains("was trained on `demo`") && error.contains("other"),
        "{error}"
    );
    // So is a setting that only a new run can choose.
    let error = fail(
        d,
        &[
            "train", "--resume", "run", "--model", "nerf", "--steps", "5",
        ],
    );
    assert!(error.contains("--model"), "{error}");
    assert_eq!(checkpoint_step(&run), 4, "a refused resume must not train");
}

/// Trains the demo scene (small, fast) into `run` until told to stop.
fn start_long_training(dir: &Path) -> std::process::Child {
    zrak()
        .args([
            "train",
            "demo",
            "--downscale",
            "4",
            "--engine",
            "cpu",
            "--time",
            "10m",
            "--out",
            "run",
        ])
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the zrak binary starts")
}

/// Waits until training has logged `lines` lines of metrics (every 16
/// steps, or at an evaluation), so a signal arrives mid-run, not during
/// start-up; returns the last logged step.
fn wait_for_metrics(dir: &Path, lines: usize, child: &mut std::process::Child) -> u64 {
    let metrics = dir.join("run").join("metrics.jsonl");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    loop {
        let text = std::fs::read_to_string(&metrics).unwrap_or_default();
        let complete: Vec<&str> = text.lines().filter(|l| l.ends_with('}')).collect();
        let logged = complete.len();
        if logged >= lines {
            let last: serde_json::Value =
                serde_json::from_str(complete[logged - 1]).expect("a metrics line is JSON");
            return last["step"].as_u64().expect("a metrics line has its step");
        }
        if let Some(status) = child.try_wait().expect("waiting on zrak") {
            panic!("training ended ({status}) before it logged {lines} lines");
        }
        assert!(
            std::time::Instant::now() < deadline,
            "training logged {logged} lines in 120 s"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// Signals a child we have not yet waited for.
fn send(child: &std::process::Child, signal: i32) {
    common::send_signal(child.id(), signal);
}

#[test]
fn an_interrupt_finishes_the_step_writes_the_checkpoint_and_says_how_to_resume() {
    for signal in [libc::SIGINT, libc::SIGTERM] {
        let dir = temp_dir();
        let d = dir.path();
        let mut child = start_long_training(d);
        let logged_step = wait_for_metrics(d, 1, &mut child);
        send(&child, signal);
        let output = finish(child, 60);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(130), "signal {signal}: {stderr}");
        let run = d.join("run");
        assert!(
            stderr.contains("checkpoint written to")
                && stderr.contains("continue with: zrak train --resume run --time 600s"),
            "{stderr}"
        );
        assert!(!stderr.contains("panicked"), "{stderr}");
        // The checkpoint holds every step taken, at least those logged.
        let step = checkpoint_step(&run);
        assert!(
            step >= logged_step,
            "the checkpoint is at step {step}, the log at {logged_step}"
        );
        assert!(!run.join("checkpoint.tmp").exists());
        // And the run continues from it.
        let out = succeed(
            d,
            &[
                "train",
                "--resume",
                "run",
                "--steps",
                &(step + 1).to_string(),
            ],
        );
        assert!(
            out.contains(&format!("trained {} steps", step + 1)),
            "{out}"
        );
    }
}

#[test]
fn a_second_interrupt_a_second_later_ends_the_process_at_once() {
    let dir = temp_dir();
    let d = dir.path();
    let mut child = start_long_training(d);
    wait_for_metrics(d, 1, &mut child);
    send(&child, libc::SIGINT);
    // After the grace: a new request.
    std::thread::sleep(std::time::Duration::from_millis(1500));
    if child.try_wait().unwrap().is_none() {
        send(&child, libc::SIGINT);
    }
    let output = finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// Two signals at once (GNU `timeout` signals the child and then its
/// process group; a terminal's Ctrl-C reaches the whole foreground group)
/// are one request: the run still finishes its step and keeps it.
#[test]
fn two_signals_at_once_are_one_request() {
    for signal in [libc::SIGINT, libc::SIGTERM] {
        let dir = temp_dir();
        let d = dir.path();
        let mut child = start_long_training(d);
        wait_for_metrics(d, 1, &mut child);
        send(&child, signal);
        // Sent back to back, the kernel may merge the two into one pending
        // signal; 0.3 s apart both arrive, the second well inside the
        // grace, as the group's copy from `timeout` does on a busy machine.
        std::thread::sleep(std::time::Duration::from_millis(300));
        send(&child, signal);
        let output = finish(child, 60);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(130), "{stderr}");
        assert!(!stderr.contains("stopping at once"), "{stderr}");
        assert!(stderr.contains("checkpoint written to"), "{stderr}");
        assert!(checkpoint_step(&d.join("run")) > 0);
    }
}

/// `timeout DURATION zrak train …`, as the issue ran it (4 runs of 7 lost
/// everything): every run keeps its checkpoint.
#[test]
fn gnu_timeout_ends_a_run_with_its_checkpoint() {
    for attempt in 0..3 {
        let dir = temp_dir();
        let d = dir.path();
        let output = Command::new("timeout")
            .args(["--preserve-status", "4"])
            .arg(common::zrak_bin())
            .args([
                "train",
                "demo",
                "--downscale",
                "4",
                "--engine",
                "cpu",
                "--time",
                "10m",
                "--out",
                "run",
            ])
            .current_dir(d)
            .stdin(Stdio::null())
            .output()
            .expect("GNU timeout runs");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(
            output.status.code(),
            Some(130),
            "attempt {attempt}: {stderr}"
        );
        assert!(
            !stderr.contains("stopping at once"),
            "attempt {attempt}: {stderr}"
        );
        assert!(
            checkpoint_step(&d.join("run")) > 0,
            "attempt {attempt}: {stderr}"
        );
    }
}

/// Under `nohup` a closing terminal's SIGHUP is ignored, as nohup asks;
/// SIGTERM still stops the run with its checkpoint.
#[test]
fn nohup_keeps_a_run_alive_through_a_hangup() {
    let dir = temp_dir();
    let d = dir.path();
    let mut child = Command::new("nohup")
        .arg(common::zrak_bin())
        .args([
            "train",
            "demo",
            "--downscale",
            "4",
            "--engine",
            "cpu",
            "--time",
            "10m",
            "--out",
            "run",
        ])
        .current_dir(d)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("nohup runs");
    // nohup execs zrak: the child's pid is zrak's.
    wait_for_metrics(d, 1, &mut child);
    send(&child, libc::SIGHUP);
    std::thread::sleep(std::time::Duration::from_millis(1500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "zrak under nohup ended on SIGHUP"
    );
    send(&child, libc::SIGTERM);
    let output = finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(checkpoint_step(&d.join("run")) > 0);
    // Without nohup, a hangup stops the run the same careful way.
    let dir = temp_dir();
    let d = dir.path();
    let mut child = start_long_training(d);
    wait_for_metrics(d, 1, &mut child);
    send(&child, libc::SIGHUP);
    let output = finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("checkpoint written to"), "{stderr}");
}

/// The lock: while a run trains, a second writer is refused naming the
/// trainer's process; readers are not. SIGKILL then leaves the early
/// first checkpoint (after ~10 s, not 120 s), and the kernel's release of
/// the lock lets the run continue.
#[test]
fn one_writer_per_run_folder_and_an_early_first_checkpoint() {
    let dir = temp_dir();
    let d = dir.path();
    let mut child = start_long_training(d);
    let run = d.join("run");
    let started = std::time::Instant::now();
    while !run.join("checkpoint.zrak").is_file() {
        assert!(
            started.elapsed() < std::time::Duration::from_secs(60),
            "no checkpoint within 60 s of starting"
        );
        assert!(child.try_wait().unwrap().is_none(), "training ended early");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let pid = child.id().to_string();
    for args in [
        &["train", "--resume", "run", "--steps", "100000"][..],
        &["train", "demo", "--steps", "1", "--out", "run", "--force"],
    ] {
        let error = fail(d, args);
        assert!(
            error.contains("is using this run folder") && error.contains(&pid),
            "zrak {args:?}: {error}"
        );
    }
    // A reader needs no lock.
    succeed(d, &["eval", "run"]);
    send(&child, libc::SIGKILL);
    let _ = finish(child, 60);
    let step = checkpoint_step(&run);
    assert!(step > 0);
    let out = succeed(
        d,
        &[
            "train",
            "--resume",
            "run",
            "--steps",
            &(step + 1).to_string(),
        ],
    );
    assert!(
        out.contains(&format!("trained {} steps", step + 1)),
        "{out}"
    );
}

/// `--checkpoint-every` sets the interval (and so the first checkpoint, when
/// shorter than 10 s).
#[test]
fn checkpoint_every_sets_the_interval() {
    let dir = temp_dir();
    let d = dir.path();
    let mut child = zrak()
        .args([
            "train",
            "demo",
            "--downscale",
            "4",
            "--engine",
            "cpu",
            "--time",
            "10m",
            "--out",
            "run",
            "--checkpoint-every",
            "1s",
        ])
        .current_dir(d)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let run = d.join("run");
    let started = std::time::Instant::now();
    let mut steps = Vec::new();
    while steps.len() < 3 {
        assert!(
            started.elapsed() < std::time::Duration::from_secs(60),
            "{steps:?}"
        );
        assert!(child.try_wait().unwrap().is_none());
        if let Ok(checkpoint) = Checkpoint::load_header(&run.join("checkpoint.zrak")) {
            let step = checkpoint["trainer"]["step"].as_u64().unwrap();
            if steps.last() != Some(&step) {
                steps.push(step);
            }
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    assert!(
        started.elapsed() < std::time::Duration::from_secs(30),
        "{steps:?}"
    );
    send(&child, libc::SIGKILL);
    let _ = finish(child, 60);
    let error = fail(
        d,
        &[
            "train",
            "demo",
            "--checkpoint-every",
            "0s",
            "--steps",
            "1",
            "--out",
            "x",
        ],
    );
    assert!(error.contains("--checkpoint-every"), "{error}");
}

/// Runs `zrak ARGS` in `dir` with its standard output (or error) closed
/// before it writes anything, as `zrak … | head -0` would.
fn with_closed_pipe(dir: &Path, args: &[&str], close_stderr: bool) -> Output {
    let mut child = zrak()
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the zrak binary starts");
    // Dropping our end of the pipe closes it: the child's next write fails.
    if close_stderr {
        drop(child.stderr.take());
    } else {
        drop(child.stdout.take());
    }
    child.wait_with_output().expect("collecting zrak's output")
}

#[test]
fn printing_to_a_closed_pipe_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    for args in [
        &["info", "scene"][..],
        &["demo", "--out", "scene2", "--size", "16", "--views", "2"],
        &["eval", "run", "--split", "val"],
        &["render", "run", "--view", "0", "--out", "frames"],
        &["--help"],
    ] {
        let output = with_closed_pipe(d, args, false);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!stderr.contains("panicked"), "zrak {args:?}: {stderr}");
        // Ended by SIGPIPE (quietly, as `cat` would be) or finished.
        assert!(
            output.status.success() || output.status.signal() == Some(libc::SIGPIPE),
            "zrak {args:?}: {} {stderr}",
            output.status
        );
    }
    // Training must not die of a closed pipe before its checkpoint: it
    // keeps going and ends normally whichever stream is closed.
    for (close_stderr, out) in [(false, "run3"), (true, "run4")] {
        let output = with_closed_pipe(
            d,
            &[
                "train", "scene", "--steps", "3", "--engine", "cpu", "--out", out,
            ],
            close_stderr,
        );
        assert!(output.status.success(), "{}", output.status);
        assert_eq!(checkpoint_step(&d.join(out)), 3);
    }
}

/// The commands of the README's "On the command line" block, one per
/// line, comments and the leading `zrak` removed.
fn readme_commands() -> Vec<String> {
    let readme = include_str!("../README.md");
    let block = readme
        .split("On the command line:")
        .nth(1)
        .and_then(|rest| rest.split("```sh").nth(1))
        .and_then(|rest| rest.split("```").next())
        .expect("README.md has a ```sh block after \"On the command line:\"");
    block
        .lines()
        .map(|line| line.split('#').next().unwrap_or("").trim())
        .filter(|line| !line.is_empty())
        .map(|line| {
            line.strip_prefix("zrak ")
                .unwrap_or_else(|| panic!("README command `{line}` does not start with zrak"))
                .to_string()
        })
        .collect()
}

/// A README command as the test runs it, with `/tmp/` as `tmp`: SCENE is
/// a small demo scene (`scene`: one 32×32 view per held-out split keeps
/// evaluation quick), COLMAP_DIR a COLMAP model of demo cameras, optional `[--flag a|b]` groups are given with their
/// first choice, and budgets become tiny (`bench quality` trains Instant-NGP
/// alone). `runs_made`
/// counts the `--out RUN` seen so far: the first is RUN, later ones write
/// beside it (`RUN2`, …) so that the commands reading RUN read the first,
/// an Instant-NGP run, quick to evaluate and render.
fn as_tested(command: &str, tmp: &Path, runs_made: &mut usize) -> Vec<String> {
    let tmp = format!("{}/", tmp.display());
    let mut words: Vec<String> = Vec::new();
    let mut tokens = command.split_whitespace().peekable();
    while let Some(token) = tokens.next() {
        let token = token.trim_start_matches('[').trim_end_matches(']');
        // `a|b` offers choices: take the first.
        let token = token.split('|').next().unwrap_or(token);
        words.push(token.replace("/tmp/", &tmp));
        if matches!(
            token,
            "--time" | "--turntable" | "--budget" | "--resolution"
        ) {
            let value = tokens.next().expect("a value after the flag");
            let budget = match token {
                "--turntable" => "2",
                "--resolution" => "24",
                "--budget" => "1s",
                _ => "2s",
            };
            let _ = value;
            words.push(budget.to_string());
        }
    }
    for i in 0..words.len() {
        let previous = if i > 0 { words[i - 1].as_str() } else { "" };
        match words[i].as_str() {
            "SCENE" => words[i] = "scene".into(),
            "COLMAP_DIR" => words[i] = "colmap".into(),
            "RUN" if previous == "--out" => {
                *runs_made += 1;
                words[i] = match *runs_made {
                    1 => "RUN".into(),
                    n => format!("RUN{n}"),
                };
            }
            _ => {}
        }
    }
    match (
        words.first().map(String::as_str),
        words.get(1).map(String::as_str),
    ) {
        (Some("bench"), Some("throughput")) => {
            words.extend(["--scene", "scene", "--warmup", "0", "--steps", "1"].map(String::from))
        }
        (Some("bench"), Some("dense")) => {
            words.extend(["--rows", "512", "--repeats", "1"].map(String::from))
        }
        // Instant-NGP's self-check and one timed step (a software adapter
        // runs NeRF's step in seconds, the self-check of all three in a
        // minute).
        (Some("bench"), Some("gpu")) => {
            words.extend(["--models", "ngp", "--warmup", "0", "--steps", "1"].map(String::from))
        }
        // Instant-NGP alone, scored on SCENE's one test view at 16×16.
        (Some("bench"), Some("quality")) => words.extend(
            [
                "--models",
                "ngp",
                "--engine",
                "cpu",
                "--eval-downscale",
                "2",
            ]
            .map(String::from),
        ),
        _ => {}
    }
    words
}

#[test]
fn the_readme_commands_work_as_written() {
    let dir = temp_dir();
    let d = dir.path();
    std::fs::create_dir_all(d.join("tmp")).unwrap();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "32", "--views", "10"],
    );
    // COLMAP_DIR: a demo scene's cameras as a COLMAP text model.
    let demo = zrak::scene::demo::build(&zrak::scene::demo::DemoConfig {
        size: 32,
        train_views: 6,
        val_views: 1,
        test_views: 1,
    });
    let cameras: Vec<_> = demo.train.iter().map(|f| f.camera).collect();
    let model = zrak::scene::colmap::model_from_cameras(&cameras, |i| format!("{i:03}.png"));
    let sparse = d.join("colmap/sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    zrak::scene::colmap::write_text(&model, &sparse).unwrap();
    let commands = readme_commands();
    assert!(commands.len() >= 10, "{commands:?}");
    let mut runs_made = 0;
    for command in &commands {
        let mut words = as_tested(command, &d.join("tmp"), &mut runs_made);
        // A resume must ask for more than the run has trained (a limit it
        // has reached is refused): 2 s more than its checkpoint holds.
        if let Some(at) = words.iter().position(|w| w == "--resume") {
            let trained = checkpoint_header(&d.join(&words[at + 1]))["trainer"]["train_seconds"]
                .as_f64()
                .expect("the checkpoint records its training time");
            if let Some(time) = words.iter().position(|w| w == "--time") {
                words[time + 1] = format!("{:.1}s", trained + 2.0);
            }
        }
        let args: Vec<&str> = words.iter().map(String::as_str).collect();
        let started = std::time::Instant::now();
        let output = run_in(d, &args);
        eprintln!(
            "README `zrak {command}` ran as `zrak {}` in {:.1} s",
            args.join(" "),
            started.elapsed().as_secs_f64()
        );
        assert!(
            output.status.success(),
            "README `zrak {command}` failed as `zrak {}` ({}):\n{}\n{}",
            args.join(" "),
            output.status,
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
    }
    // What the block promises on disk.
    assert!(d.join("RUN/checkpoint.zrak").is_file());
    assert!(d.join("RUN/eval_val.json").is_file());
    assert!(d.join("frames/turntable.gif").is_file());
    assert!(d.join("DIR/report.md").is_file());
}

/// `bench quality` on the 32×32 demo scene with batches of 1024 samples
/// (steps of milliseconds for Instant-NGP, tens of them for NeRF), scored
/// on one 16×16 test view: seconds of work for two models.
const QUALITY_TINY: [&str; 14] = [
    "--downscale",
    "4",
    "--every",
    "10",
    "--eval-downscale",
    "2",
    "--engine",
    "cpu",
    "--split",
    "test",
    "--targets",
    "8,200",
    "--batch-samples",
    "1024",
];

fn read_json(path: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn metrics_lines(run: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).expect("a metrics line is JSON"))
        .collect()
}

#[test]
fn bench_quality_writes_its_report_and_holds_the_numbers_the_runs_logged() {
    let dir = temp_dir();
    let d = dir.path();
    // NeRF with the paper's sampler: no occupancy grid to fill first.
    let mut args = vec![
        "bench",
        "quality",
        "demo",
        "--models",
        "ngp,nerf",
        "--sampling",
        "paper",
        "--budget",
        "1s",
        "--marks",
        "0.5s",
        "--out",
        "q",
    ];
    args.extend(QUALITY_TINY);
    let started = std::time::Instant::now();
    let out = succeed(d, &args);
    eprintln!(
        "bench quality ran in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    let q = d.join("q");
    for file in [
        "experiment.json",
        "results.json",
        "results.csv",
        "report.md",
        "psnr_demo.png",
        "psnr_demo.svg",
        "time_to_quality_demo.png",
        "time_to_quality_demo.svg",
    ] {
        assert!(q.join(file).is_file(), "{file} missing; stdout:\n{out}");
    }
    let png = image::open(q.join("psnr_demo.png")).expect("the plot is a PNG");
    assert_eq!((png.width(), png.height()), (1000, 620));
    let svg = std::fs::read_to_string(q.join("time_to_quality_demo.svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("Instant-NGP") && svg.contains("NeRF"));

    let results = read_json(&q.join("results.json"));
    assert_eq!(results["zrak_version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(results["engine"]["engine"], "cpu");
    assert!(results["machine"]["threads"].as_u64().unwrap() >= 1);
    let settings = &results["settings"];
    assert_eq!(settings["marks_seconds"], serde_json::json!([0.5, 1.0]));
    assert_eq!(settings["budget_seconds"], 1.0);
    assert_eq!(settings["split"], "test");
    assert_eq!(settings["every"], 10);
    assert_eq!(settings["eval_downscale"], 2);
    assert!(
        settings["scenes"][0]["scored"]
            .as_str()
            .unwrap()
            .contains("1 of 10: views 0)")
    );
    let cells = results["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 2);
    let csv = std::fs::read_to_string(q.join("results.csv")).unwrap();
    let csv_rows: Vec<&str> = csv.lines().skip(1).collect();
    assert_eq!(csv_rows.len(), 4, "{csv}");
    let report = std::fs::read_to_string(q.join("report.md")).unwrap();
    let expected = [
        ("ngp", "occupancy", "Instant-NGP", "demo-ngp"),
        ("nerf", "paper", "NeRF (paper sampler)", "demo-nerf-paper"),
    ];
    for (cell, (key, sampling, label, folder)) in cells.iter().zip(expected) {
        assert_eq!(cell["model"], key);
        assert_eq!(cell["finished"], true);
        assert_eq!(cell["sampling"], sampling);
        let run = q.join("runs").join(folder);
        assert_eq!(cell["run_folder"], format!("runs/{folder}"));
        assert_eq!(read_json(&run.join("run.json"))["batch_samples"], 1024);
        let logged = metrics_lines(&run);
        let marks = cell["marks"].as_array().unwrap();
        assert_eq!(marks.len(), 2);
        let mut row = format!("| {label} |");
        for (mark, nominal) in marks.iter().zip([0.5, 1.0]) {
            let step = mark["step"].as_u64().unwrap();
            let seconds = mark["train_seconds"].as_f64().unwrap();
            assert_eq!(mark["mark_seconds"], nominal);
            assert!(seconds >= nominal, "scored at {seconds} s, before its mark");
            // The step that passed the mark was logged, with the same clock.
            let line = logged
                .iter()
                .find(|l| l["step"] == step)
                .unwrap_or_else(|| panic!("step {step} of {key} was not logged"));
            assert_eq!(line["train_seconds"].as_f64().unwrap(), seconds);
            // The mark's score is the mean of its views (view 0 alone).
            let views = mark["views"].as_array().unwrap();
            let indices: Vec<u64> = views.iter().map(|v| v["index"].as_u64().unwrap()).collect();
            assert_eq!(indices, [0]);
            let mean = views
                .iter()
                .map(|v| v["psnr"].as_f64().unwrap())
                .sum::<f64>()
                / views.len() as f64;
            let psnr = mark["psnr"].as_f64().unwrap();
            assert!((psnr - mean).abs() < 1e-9 && psnr.is_finite());
            let ssim = mark["ssim"].as_f64().unwrap();
            assert!(
                csv_rows.iter().any(|r| r.starts_with(&format!(
                    "demo,{key},{sampling},{nominal},{seconds:.3},{step},{psnr:.4},{ssim:.5},1,2,"
                ))),
                "{key} at {nominal} s not in results.csv:\n{csv}"
            );
            row.push_str(&format!(" {psnr:.2} / {ssim:.3} |"));
        }
        assert!(report.contains(&row), "`{row}` not in report.md:\n{report}");
        // The checkpoint holds the last mark's training.
        let header = checkpoint_header(&run);
        let last = &marks[1];
        assert_eq!(header["trainer"]["step"], last["step"]);
        assert_eq!(header["trainer"]["train_seconds"], last["train_seconds"]);
        assert_eq!(cell["steps"], last["step"]);
        // 8 dB is reached (the first mark's bound at most); 200 dB never.
        let psnrs: Vec<f64> = marks.iter().map(|m| m["psnr"].as_f64().unwrap()).collect();
        let to_200 = &cell["time_to_targets"][1];
        assert_eq!(to_200["status"], "not_reached");
        assert_eq!(to_200["seconds"], last["train_seconds"]);
        if psnrs[0] >= 8.0 {
            assert_eq!(cell["time_to_targets"][0]["status"], "at_most");
        }
    }

    // Run again: every cell is finished, so nothing trains or is scored
    // again, and the outputs are written anew from the same records.
    let before: Vec<String> = ["ngp", "nerf-paper"]
        .iter()
        .map(|k| std::fs::read_to_string(q.join(format!("runs/demo-{k}/marks.json"))).unwrap())
        .collect();
    let steps_before = checkpoint_step(&q.join("runs/demo-nerf-paper"));
    succeed(d, &args);
    for (k, text) in ["ngp", "nerf-paper"].iter().zip(&before) {
        let now = std::fs::read_to_string(q.join(format!("runs/demo-{k}/marks.json"))).unwrap();
        assert_eq!(&now, text, "{k}'s scores changed on a second run");
    }
    assert_eq!(
        checkpoint_step(&q.join("runs/demo-nerf-paper")),
        steps_before
    );
    assert_eq!(
        read_json(&q.join("results.json"))["cells"],
        results["cells"]
    );
}

#[test]
fn bench_quality_refuses_bad_input_by_name() {
    let dir = temp_dir();
    let d = dir.path();
    let quality = |extra: &[&str]| {
        let mut args = vec!["bench", "quality", "demo"];
        args.extend(extra);
        fail(d, &args)
    };
    let error = quality(&["--models", "ngp,gaussians", "--out", "q"]);
    assert!(
        error.contains("gaussians") && error.contains("--models"),
        "{error}"
    );
    let error = quality(&["--budget", "1m", "--marks", "30s,2m", "--out", "q"]);
    assert!(
        error.contains("2 min is past the budget of 1 min"),
        "{error}"
    );
    let error = quality(&["--marks", "30x", "--out", "q"]);
    assert!(
        error.contains("30x") && error.contains("--marks"),
        "{error}"
    );
    let error = quality(&["--every", "0", "--out", "q"]);
    assert!(error.contains("--every"), "{error}");
    std::fs::write(d.join("a-file"), "").unwrap();
    let error = quality(&["--out", "a-file/q"]);
    assert!(
        error.contains("a-file/q") && error.contains("cannot create the experiment folder"),
        "{error}"
    );
    let error = fail(
        d,
        &[
            "bench",
            "quality",
            "no-such-scene",
            "--out",
            "q2",
            "--engine",
            "cpu",
        ],
    );
    assert!(error.contains("no-such-scene"), "{error}");
    let error = quality(&["--eval-downscale", "64", "--engine", "cpu", "--out", "q4"]);
    assert!(
        error.contains("--eval-downscale 64 leaves 2×2 pixels"),
        "{error}"
    );
    // A folder holding an experiment with other settings is not mixed into.
    std::fs::create_dir_all(d.join("q3")).unwrap();
    let settings = zrak::bench::quality::Protocol::new(60.0, None, "test", 25, 4, 1, 0).unwrap();
    std::fs::write(
        d.join("q3/experiment.json"),
        serde_json::to_string(&settings).unwrap(),
    )
    .unwrap();
    let error = quality(&["--budget", "2m", "--out", "q3"]);
    assert!(
        error.contains("q3 holds an experiment with other settings")
            && error.contains("budget 1 min"),
        "{error}"
    );
}

#[test]
fn an_interrupted_bench_quality_continues_where_it_stopped() {
    let dir = temp_dir();
    let d = dir.path();
    // The first step passes the first mark; training to the budget takes
    // many more.
    let mut args = vec![
        "bench", "quality", "demo", "--models", "ngp", "--budget", "3s", "--marks", "0.01s",
        "--out", "q",
    ];
    args.extend(QUALITY_TINY);
    let child = zrak()
        .args(&args)
        .current_dir(d)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the zrak binary starts");
    let run = d.join("q/runs/demo-ngp");
    // Interrupt once the first mark is scored, while training for the
    // second.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let first = loop {
        if let Ok(Some(record)) = zrak::bench::quality::CellRecord::load(&run)
            && !record.marks.is_empty()
        {
            break record.marks[0].clone();
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no mark scored in 120 s"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    send(&child, libc::SIGINT);
    let output = finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(
        stderr.contains("continue with: zrak bench quality demo"),
        "{stderr}"
    );
    let record = zrak::bench::quality::CellRecord::load(&run)
        .unwrap()
        .unwrap();
    assert_eq!(
        record.marks,
        std::slice::from_ref(&first),
        "only the first mark is scored"
    );
    let stopped_at = checkpoint_step(&run);
    assert!(stopped_at >= first.step as u64);
    let report = std::fs::read_to_string(d.join("q/report.md")).unwrap();
    assert!(report.contains("**Unfinished**"), "{report}");

    // The same command continues from the checkpoint and scores the rest.
    succeed(d, &args);
    let record = zrak::bench::quality::CellRecord::load(&run)
        .unwrap()
        .unwrap();
    assert_eq!(record.marks.len(), 2);
    assert_eq!(record.marks[0], first, "a scored mark is not scored again");
    assert!(record.marks[1].step as u64 > stopped_at);
    assert!(record.marks[1].train_seconds >= 3.0);
    let report = std::fs::read_to_string(d.join("q/report.md")).unwrap();
    assert!(!report.contains("**Unfinished**"), "{report}");
}

// ---------------------------------------------------------------------
// Issue 31: nothing a user already has is lost, bad input is refused by
// name, nothing panics.
// ---------------------------------------------------------------------

/// Copies the folder `from` to `to` (files and folders only).
fn copy_folder(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_folder(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// An instant-ngp scene in `d/name`: the demo `scene`'s training views
/// (their images copied), with `edit` applied to the transforms.json.
fn instant_ngp_variant(d: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) {
    let blender = read_json(&d.join("scene/transforms_train.json"));
    let frames: Vec<serde_json::Value> = blender["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let file = f["file_path"].as_str().unwrap().trim_start_matches("./");
            serde_json::json!({
                "file_path": format!("{file}.png"),
                "transform_matrix": f["transform_matrix"],
            })
        })
        .collect();
    let mut json = serde_json::json!({
        "camera_angle_x": blender["camera_angle_x"],
        "frames": frames,
    });
    edit(&mut json);
    let folder = d.join(name);
    copy_folder(&d.join("scene/train"), &folder.join("train"));
    std::fs::write(
        folder.join("transforms.json"),
        serde_json::to_string_pretty(&json).unwrap(),
    )
    .unwrap();
}

/// A COLMAP model of the demo's cameras with their photographs, in
/// `d/name`; `edit` may change images.txt's text.
fn colmap_scene(d: &Path, name: &str, edit: impl FnOnce(String) -> String) {
    let demo = zrak::scene::demo::build(&zrak::scene::demo::DemoConfig {
        size: 16,
        train_views: 9,
        val_views: 1,
        test_views: 1,
    });
    let cameras: Vec<_> = demo.train.iter().map(|f| f.camera).collect();
    let model = zrak::scene::colmap::model_from_cameras(&cameras, |i| format!("{i:03}.png"));
    let sparse = d.join(name).join("sparse/0");
    zrak::scene::colmap::write_text(&model, &sparse).unwrap();
    let images = sparse.join("images.txt");
    let text = std::fs::read_to_string(&images).unwrap();
    std::fs::write(&images, edit(text)).unwrap();
    std::fs::create_dir_all(d.join(name).join("images")).unwrap();
    for (i, frame) in demo.train.iter().enumerate() {
        frame
            .image
            .save_png(&d.join(name).join(format!("images/{i:03}.png")))
            .unwrap();
    }
}

/// Sum of the split counts `zrak info` prints on its `frames` line.
fn frames_in_info(stdout: &str) -> usize {
    let line = stdout
        .lines()
        .find(|l| l.starts_with("frames"))
        .unwrap_or_else(|| panic!("no frames line in {stdout}"));
    line.split(',')
        .filter_map(|part| part.split_whitespace().last()?.parse::<usize>().ok())
        .sum()
}

fn make_fifo(path: &Path) {
    let name = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
}

/// One refusal (or acceptance) as a user meets it: the command, whether it
/// must succeed, and words its standard error (or output) must hold.
struct Case {
    args: &'static [&'static str],
    succeeds: bool,
    says: &'static [&'static str],
}

const fn refused(args: &'static [&'static str], says: &'static [&'static str]) -> Case {
    Case {
        args,
        succeeds: false,
        says,
    }
}

const fn accepted(args: &'static [&'static str], says: &'static [&'static str]) -> Case {
    Case {
        args,
        succeeds: true,
        says,
    }
}

/// The issue's cases, each run against the built binary in a folder set
/// up by [`bad_input_fixture`].
const CASES: &[Case] = &[
    // A folder holding a run is not trained over.
    refused(
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run",
        ],
        &[
            "run already holds a run (step 2",
            "--resume run",
            "--force",
            "nothing deleted",
        ],
    ),
    // `1e9h` is a duration (the refusal is the run's, not the unit's).
    refused(
        &[
            "train", "scene", "--time", "1e9h", "--engine", "cpu", "--out", "run",
        ],
        &["already holds a run"],
    ),
    refused(
        &["train", "scene", "--time", "5x", "--out", "new"],
        &["unknown unit `x`"],
    ),
    // Resume targets the run has reached.
    refused(
        &["train", "--resume", "run", "--steps", "2"],
        &["already at step 2", "give more than 2"],
    ),
    refused(
        &["train", "--resume", "run", "--time", "0.001s"],
        &["--time", "leaves nothing to train"],
    ),
    refused(
        &["train", "--resume", "nowhere", "--steps", "9"],
        &["nowhere: no such run folder"],
    ),
    refused(
        &["train", "--resume", "scene", "--steps", "9"],
        &["no checkpoint to resume from"],
    ),
    // convert never destroys its input, nor overwrites without --force.
    refused(
        &["convert", "colmap", "--out", "colmap/sparse/0/images.txt"],
        &["the COLMAP model's own images.txt", "convert reads it"],
    ),
    refused(
        &[
            "convert",
            "colmap",
            "--out",
            "colmap/sparse/0/../0/cameras.txt",
            "--force",
        ],
        &["own cameras.txt"],
    ),
    refused(
        &["convert", "colmap", "--out", "colmap/images/x.json"],
        &["photographs folder"],
    ),
    refused(
        &["convert", "colmap", "--out", "existing.json"],
        &["existing.json already exists", "--force"],
    ),
    refused(
        &["convert", "colmap", "--out", "scene"],
        &["scene: is a folder"],
    ),
    refused(
        &["convert", "nowhere", "--out", "n.json"],
        &["nowhere: folder not found"],
    ),
    refused(&["convert", "fifo", "--out", "n.json"], &["named pipe"]),
    // demo and render do not write over what is there.
    refused(
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
        &["scene is not empty", "--force"],
    ),
    refused(
        &["render", "run", "--view", "0", "--out", "rendered"],
        &["rendered/val_000.png already exists", "--force"],
    ),
    refused(
        &["render", "run", "--turntable", "3", "--out", "rendered"],
        &["turntable_0000.png already exists (and 1 more"],
    ),
    // Training that would do nothing.
    refused(
        &[
            "train", "noviews", "--steps", "1", "--engine", "cpu", "--out", "r1",
        ],
        &["noviews: nothing to train: the scene has no training views"],
    ),
    refused(
        &[
            "train", "far", "--steps", "1", "--engine", "cpu", "--out", "r2",
        ],
        &[
            "far: nothing to train",
            "no training camera's rays cross the scene's box",
        ],
    ),
    // A field of view of nearly 180°: every ray leaves sideways.
    refused(
        &[
            "train", "wide", "--steps", "1", "--engine", "cpu", "--out", "r5",
        ],
        &["wide: nothing to train", "rays cross"],
    ),
    refused(
        &["info", "tiny-scale"],
        &["transforms.json", "`scale` = ", "not a finite box"],
    ),
    refused(
        &["info", "huge-aabb"],
        &["transforms.json", "`aabb_scale` = 40000 is more than 32768"],
    ),
    // Sizes, counts and scales bounded before any work.
    refused(
        &[
            "train",
            "demo",
            "--downscale",
            "200",
            "--steps",
            "1",
            "--out",
            "r3",
        ],
        &["--downscale 200 leaves no pixels", "at most 128"],
    ),
    refused(
        &["render", "run", "--turntable", "4294967296", "--out", "t1"],
        &["--turntable must be 1 to 100000"],
    ),
    refused(
        &[
            "render",
            "run",
            "--turntable",
            "2",
            "--size",
            "65535",
            "--gif",
            "--out",
            "t2",
        ],
        &["--size must be 1 to 16384"],
    ),
    refused(
        &["demo", "--size", "100000", "--out", "big"],
        &["--size must be 8 to 16384"],
    ),
    refused(
        &[
            "train",
            "scene",
            "--training-scales",
            "8",
            "--steps",
            "1",
            "--engine",
            "cpu",
            "--out",
            "r4",
        ],
        &[
            "--training-scales 8",
            "the smallest here is 16",
            "give at most 5",
        ],
    ),
    // Silent misreads and the messages that named the wrong problem.
    refused(
        &["info", "folding"],
        &[
            "transforms.json",
            "folds over inside its 16×16 image",
            "k1 -10",
        ],
    ),
    refused(&["info", "folding-huge"], &["folds over"]),
    refused(&["info", "fifo"], &["fifo", "named pipe"]),
    refused(
        &["info", "dangling"],
        &["dangling", "dangling symbolic link", "gone"],
    ),
    refused(&["info", "loop"], &["loop", "symbolic link that loops"]),
    refused(
        &["info", "folder-image"],
        &["r_0.png", "a folder, not a file"],
    ),
    refused(&["info", "pipe-json/transforms.json"], &["named pipe"]),
    accepted(&["info", "bom"], &["frames ", "images      16×16"]),
    accepted(&["info", "utf16"], &["frames ", "images      16×16"]),
    // A damaged or diverged checkpoint is refused by name; nothing panics.
    refused(
        &["eval", "run-flipped"],
        &["damaged", "tensor `params` fails its checksum"],
    ),
    refused(
        &["eval", "run-nan"],
        &["tensor `params` holds NaN at index 0", "diverged"],
    ),
    refused(
        &["render", "run-nan", "--view", "0", "--out", "nan-frames"],
        &["holds NaN"],
    ),
    refused(
        &["train", "--resume", "run-nan", "--steps", "9"],
        &["holds NaN"],
    ),
    // Views under SSIM's window are said to be, not left as a bare NaN.
    accepted(
        &["eval", "run", "--downscale", "2"],
        &["SSIM is NaN for 1 of the 1 views", "11×11 window"],
    ),
];

/// The folder the cases run in: a demo scene, a run trained 2 steps on it,
/// a COLMAP model, and the broken inputs the cases name.
fn bad_input_fixture(d: &Path) {
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    succeed(
        d,
        &["render", "run", "--turntable", "2", "--out", "rendered"],
    );
    succeed(d, &["render", "run", "--view", "0", "--out", "rendered"]);
    colmap_scene(d, "colmap", |text| text);
    std::fs::write(d.join("existing.json"), "{\"mine\": true}").unwrap();
    // A Blender folder with held-out views only.
    std::fs::create_dir_all(d.join("noviews")).unwrap();
    std::fs::copy(
        d.join("scene/transforms_val.json"),
        d.join("noviews/transforms_val.json"),
    )
    .unwrap();
    copy_folder(&d.join("scene/val"), &d.join("noviews/val"));
    instant_ngp_variant(d, "far", |j| {
        j["offset"] = serde_json::json!([1e6, 1e6, 1e6])
    });
    instant_ngp_variant(d, "wide", |j| {
        j["camera_angle_x"] = serde_json::json!(std::f64::consts::PI * 0.99999)
    });
    instant_ngp_variant(d, "tiny-scale", |j| j["scale"] = serde_json::json!(1e-45));
    instant_ngp_variant(d, "huge-aabb", |j| {
        j["aabb_scale"] = serde_json::json!(40000)
    });
    instant_ngp_variant(d, "folding", |j| j["k1"] = serde_json::json!(-10.0));
    instant_ngp_variant(d, "folding-huge", |j| j["k1"] = serde_json::json!(1e30));
    instant_ngp_variant(d, "bom", |_| {});
    let text = std::fs::read(d.join("bom/transforms.json")).unwrap();
    let mut with_bom = vec![0xEF, 0xBB, 0xBF];
    with_bom.extend_from_slice(&text);
    std::fs::write(d.join("bom/transforms.json"), with_bom).unwrap();
    instant_ngp_variant(d, "utf16", |_| {});
    let text = std::fs::read_to_string(d.join("utf16/transforms.json")).unwrap();
    let mut utf16 = vec![0xFF, 0xFE];
    for unit in text.encode_utf16() {
        utf16.extend_from_slice(&unit.to_le_bytes());
    }
    std::fs::write(d.join("utf16/transforms.json"), utf16).unwrap();
    instant_ngp_variant(d, "folder-image", |_| {});
    std::fs::remove_file(d.join("folder-image/train/r_0.png")).unwrap();
    std::fs::create_dir(d.join("folder-image/train/r_0.png")).unwrap();
    std::fs::create_dir(d.join("pipe-json")).unwrap();
    make_fifo(&d.join("pipe-json/transforms.json"));
    make_fifo(&d.join("fifo"));
    std::os::unix::fs::symlink(d.join("gone"), d.join("dangling")).unwrap();
    std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
    // A run whose checkpoint has one flipped bit in its parameters.
    copy_folder(&d.join("run"), &d.join("run-flipped"));
    let path = d.join("run-flipped/checkpoint.zrak");
    let mut bytes = std::fs::read(&path).unwrap();
    let header_length = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    bytes[20 + header_length + 4 + 1000] ^= 0x04;
    std::fs::write(&path, bytes).unwrap();
    // A run whose model diverged (written as a version 1 file: version 2
    // refuses to save it).
    copy_folder(&d.join("run"), &d.join("run-nan"));
    let mut checkpoint = Checkpoint::load(&d.join("run/checkpoint.zrak")).unwrap();
    checkpoint.tensors[0].1[0] = f32::NAN;
    assert_eq!(checkpoint.tensors[0].0, "params");
    let table = serde_json::json!({
        "header": checkpoint.header,
        "tensors": checkpoint.tensors.iter().map(|(n, v)| serde_json::json!([n, v.len()])).collect::<Vec<_>>(),
    });
    let header = serde_json::to_vec(&table).unwrap();
    let mut bytes = b"ZRAKCKPT".to_vec();
    bytes.extend_from_slice(&1u32.to_le_bytes());
    bytes.extend_from_slice(&(header.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&header);
    for (_, values) in &checkpoint.tensors {
        for v in values {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(d.join("run-nan/checkpoint.zrak"), bytes).unwrap();
}

/// A snapshot of every regular file under `dir` (path and bytes), to show
/// that refused commands changed nothing.
fn snapshot(dir: &Path) -> Vec<(std::path::PathBuf, Vec<u8>)> {
    let mut files = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(folder) = stack.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let entry = entry.unwrap();
            let kind = entry.file_type().unwrap();
            if kind.is_dir() {
                stack.push(entry.path());
            } else if kind.is_file() && entry.file_name() != ".zrak.lock" {
                files.push((entry.path(), std::fs::read(entry.path()).unwrap()));
            }
        }
    }
    files.sort();
    files
}

#[test]
fn bad_input_is_refused_by_name_and_nothing_on_disk_is_lost() {
    let dir = temp_dir();
    let d = dir.path();
    bad_input_fixture(d);
    let before = snapshot(d);
    let mut failures = Vec::new();
    for case in CASES {
        let output = run_in(d, case.args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        let stdout = String::from_utf8_lossy(&output.stdout);
        let both = format!("{stdout}{stderr}");
        // Refusals end with status 1 (zrak's) or 2 (a usage error clap
        // reports), never by a signal.
        let status_ok = output.status.success() == case.succeeds
            && (case.succeeds || matches!(output.status.code(), Some(1 | 2)));
        let missing: Vec<&&str> = case.says.iter().filter(|s| !both.contains(**s)).collect();
        if !status_ok || !missing.is_empty() || both.contains("panicked") {
            failures.push(format!(
                "zrak {}: {} (expected {}), missing {missing:?}:\n{both}",
                case.args.join(" "),
                output.status,
                if case.succeeds {
                    "success"
                } else {
                    "status 1 or 2"
                }
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
    // Refused commands wrote nothing over what was there (the accepted
    // eval wrote its own scores).
    let after: Vec<_> = snapshot(d)
        .into_iter()
        .filter(|(p, _)| !p.ends_with("run/eval_val_d2.json"))
        .collect();
    let changed: Vec<_> = before
        .iter()
        .filter(|(p, bytes)| !after.iter().any(|(q, b)| q == p && b == bytes))
        .map(|(p, _)| p.display().to_string())
        .collect();
    assert!(changed.is_empty(), "changed or removed: {changed:?}");
    let added: Vec<_> = after
        .iter()
        .filter(|(p, _)| !before.iter().any(|(q, _)| q == p))
        .map(|(p, _)| p.display().to_string())
        .collect();
    assert!(added.is_empty(), "left behind: {added:?}");
}

#[test]
fn force_moves_the_old_run_aside_and_never_deletes_it() {
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    succeed(d, &["eval", "run"]);
    let out = run_in(
        d,
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run", "--force",
        ],
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("moved the run that was in run aside to run.old"),
        "{stderr}"
    );
    assert_eq!(checkpoint_step(&d.join("run")), 1);
    assert_eq!(checkpoint_step(&d.join("run.old")), 2);
    // The old scores went with the model they describe.
    assert!(d.join("run.old/eval_val.json").is_file());
    assert!(!d.join("run/eval_val.json").exists());
    // Again: the next name.
    succeed(
        d,
        &[
            "train", "scene", "--steps", "3", "--engine", "cpu", "--out", "run", "--force",
        ],
    );
    assert_eq!(checkpoint_step(&d.join("run.old-2")), 1);
    assert_eq!(checkpoint_step(&d.join("run")), 3);
}

#[test]
fn a_resumed_log_is_cut_back_to_the_checkpoint() {
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "20", "--engine", "cpu", "--out", "run",
        ],
    );
    // Lines logged after the last checkpoint by a run that was then killed.
    let metrics = d.join("run/metrics.jsonl");
    let mut text = std::fs::read_to_string(&metrics).unwrap();
    let last = text.lines().last().unwrap().to_string();
    text.push_str(&last.replace("\"step\":20", "\"step\":32"));
    text.push('\n');
    text.push_str("{\"step\":48,\"wall");
    std::fs::write(&metrics, text).unwrap();
    let out = run_in(d, &["train", "--resume", "run", "--steps", "24"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("dropped 2 lines logged after the checkpoint's step 20"),
        "{stderr}"
    );
    let steps: Vec<u64> = metrics_lines(&d.join("run"))
        .iter()
        .map(|l| l["step"].as_u64().unwrap())
        .collect();
    assert!(steps.windows(2).all(|w| w[0] < w[1]), "{steps:?}");
    assert_eq!(steps.last(), Some(&24));
}

#[test]
fn a_colmap_images_txt_without_point_lines_loads_every_image() {
    let dir = temp_dir();
    let d = dir.path();
    colmap_scene(d, "with-points", |text| text);
    colmap_scene(d, "without-points", |text| {
        text.lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| format!("{l}\n"))
            .collect()
    });
    let with = frames_in_info(&succeed(d, &["info", "with-points"]));
    let without = frames_in_info(&succeed(d, &["info", "without-points"]));
    assert_eq!(with, 9);
    assert_eq!(without, 9);
}

#[test]
fn a_refused_bench_quality_leaves_nothing_that_blocks_its_corrected_run() {
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    let error = fail(
        d,
        &[
            "bench",
            "quality",
            "scene",
            "--eval-downscale",
            "64",
            "--engine",
            "cpu",
            "--out",
            "q",
        ],
    );
    assert!(error.contains("--eval-downscale 64"), "{error}");
    assert!(!d.join("q/experiment.json").exists());
    let mut args = vec![
        "bench",
        "quality",
        "scene",
        "--models",
        "ngp",
        "--budget",
        "0.2s",
        "--out",
        "q",
        "--eval-downscale",
        "1",
        "--every",
        "1",
        "--engine",
        "cpu",
        "--split",
        "val",
        "--batch-samples",
        "1024",
    ];
    succeed(d, &args);
    assert!(d.join("q/experiment.json").is_file());
    // The same folder under other settings is still refused by name.
    args[6] = "0.3s";
    let error = fail(d, &args);
    assert!(
        error.contains("holds an experiment with other settings"),
        "{error}"
    );
}

/// `zrak ARGS` with its standard output on /dev/full.
fn with_full_stdout(dir: &Path, args: &[&str]) -> Output {
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .expect("/dev/full");
    zrak()
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(full)
        .stderr(Stdio::piped())
        .output()
        .expect("the zrak binary starts")
}

#[test]
fn a_full_standard_output_is_an_error_not_a_panic() {
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    succeed(
        d,
        &[
            "train", "scene", "--steps", "2", "--engine", "cpu", "--out", "run",
        ],
    );
    colmap_scene(d, "colmap", |text| text);
    for args in [
        &["info", "scene"][..],
        &["eval", "run"],
        &["demo", "--out", "demo2", "--size", "16", "--views", "2"],
        &["convert", "colmap", "--out", "converted.json"],
        &["render", "run", "--view", "0", "--out", "frames"],
        &[
            "bench",
            "throughput",
            "--scene",
            "scene",
            "--warmup",
            "0",
            "--steps",
            "1",
            "--engine",
            "cpu",
        ],
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "run2",
        ],
        &["--help"],
        &["train", "--help"],
        &["--version"],
    ] {
        let output = with_full_stdout(d, args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "zrak {args:?}: {stderr}");
        assert!(
            stderr.contains("cannot write to standard output: No space left on device"),
            "zrak {args:?}: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "zrak {args:?}: {stderr}");
    }
    // Their files were written all the same.
    assert_eq!(checkpoint_step(&d.join("run2")), 1);
    assert!(d.join("converted.json").is_file());
    assert!(d.join("frames/val_000.png").is_file());
}

/// A small tmpfs mounted for a test, unmounted when dropped.
struct SmallDisk(std::path::PathBuf);

impl SmallDisk {
    /// Mounts a tmpfs of `bytes` at `at`, where the machine allows it
    /// (root, a kernel that lets this container mount): `None` otherwise.
    fn mount(at: &Path, bytes: usize) -> Option<Self> {
        std::fs::create_dir_all(at).unwrap();
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={bytes}"), "tmpfs"])
            .arg(at)
            .stderr(Stdio::null())
            .status()
            .ok()?;
        status.success().then(|| Self(at.to_path_buf()))
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).status();
    }
}

/// Fills the file system holding `folder` to the last byte.
fn fill_disk(folder: &Path) {
    use std::io::Write;
    let mut filler = std::fs::File::create(folder.join("filler")).unwrap();
    let block = vec![0u8; 4096];
    while filler.write_all(&block).is_ok() {}
    while filler.write_all(&block[..1]).is_ok() {}
}

/// On a full disk a write fails with the reason and leaves the file that
/// was there whole (convert once left a user's transforms.json cut off
/// at 4 KiB).
#[test]
fn a_full_disk_never_cuts_a_file_short() {
    let dir = temp_dir();
    let d = dir.path();
    let Some(_disk) = SmallDisk::mount(&d.join("full"), 256 * 1024) else {
        eprintln!("skipped: this machine does not let the test mount a tmpfs");
        return;
    };
    colmap_scene(d, "colmap", |text| text);
    let old = format!("{{\"mine\": \"{}\"}}", "x".repeat(6000));
    let transforms = d.join("full/transforms.json");
    std::fs::write(&transforms, &old).unwrap();
    fill_disk(&d.join("full"));
    let error = fail(
        d,
        &[
            "convert",
            "colmap",
            "--out",
            "full/transforms.json",
            "--force",
        ],
    );
    assert!(
        error.contains("full/transforms.json") && error.contains("No space left on device"),
        "{error}"
    );
    assert_eq!(std::fs::read_to_string(&transforms).unwrap(), old);
    let mut left: Vec<String> = std::fs::read_dir(d.join("full"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(
        left,
        ["filler", "transforms.json"],
        "a temporary file was left"
    );
}
