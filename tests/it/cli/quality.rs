//! `zrak bench quality` as a user runs it: its report, its refusals and
//! its resumption.

use super::*;

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

#[test]
fn bench_quality_writes_its_report_and_holds_the_numbers_the_runs_logged() {
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
    let _cores = crate::common::shared();
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
