//! The `zrak` binary as a user runs it: resuming from a run folder alone,
//! interrupts, closed pipes and the README's own commands.

use crate::common;
mod quality;
mod run_folders;
mod safety;

use std::path::Path;
use std::process::{Command, Output, Stdio};

use common::finish;
use zrak::model::checkpoint::Checkpoint;

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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let readme = include_str!("../../README.md");
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
    let _cores = crate::common::shared();
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
