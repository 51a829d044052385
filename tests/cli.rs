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
fn a_second_interrupt_ends_the_process_at_once() {
    let dir = temp_dir();
    let d = dir.path();
    let mut child = start_long_training(d);
    wait_for_metrics(d, 1, &mut child);
    send(&child, libc::SIGINT);
    send(&child, libc::SIGINT);
    let output = finish(child, 60);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(130), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
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
    for close_stderr in [false, true] {
        let output = with_closed_pipe(
            d,
            &[
                "train", "scene", "--steps", "3", "--engine", "cpu", "--out", "run3",
            ],
            close_stderr,
        );
        assert!(output.status.success(), "{}", output.status);
        assert_eq!(checkpoint_step(&d.join("run3")), 3);
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
        if matches!(token, "--time" | "--turntable" | "--budget") {
            let value = tokens.next().expect("a value after the flag");
            let budget = match token {
                "--turntable" => "2",
                "--budget" => "1s",
                _ if command.contains("--resume") => "4s",
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
        let words = as_tested(command, &d.join("tmp"), &mut runs_made);
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
