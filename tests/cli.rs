//! The `zrak` binary as a user runs it: resuming from a run folder alone,
//! interrupts, closed pipes and the README's own commands.

use std::path::Path;
use std::process::{Command, Output, Stdio};

use zrak::train::checkpoint::Checkpoint;

fn zrak() -> Command {
    Command::new(env!("CARGO_BIN_EXE_zrak"))
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
