//! Run folders and checkpoints as untrusted input (issue 43): zrak never
//! writes through a link in a run folder, reads only regular files of a
//! bounded size from it, trains only into its own runs or empty folders,
//! and refuses a crafted checkpoint by name before allocating for it.

use std::time::{Duration, Instant};

use super::*;

/// A demo scene (`scene`, 16 pixels, 3 views) and a run trained 2 steps on
/// it (`run`), the cpu engine's, in `d`.
fn scene_and_run(d: &Path) {
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
}

/// A copy of `d/run` in `d/name` (its checkpoint hard-linked: the copies
/// are changed by replacing files, never by writing into them).
fn copy_run(d: &Path, name: &str) -> std::path::PathBuf {
    let to = d.join(name);
    std::fs::create_dir(&to).unwrap();
    for entry in std::fs::read_dir(d.join("run")).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_name() == "checkpoint.zrak" {
            std::fs::hard_link(entry.path(), target).unwrap();
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
    to
}

fn make_fifo(path: &Path) {
    let _ = std::fs::remove_file(path);
    let name = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
}

/// Replaces `path` with a symbolic link to `target`.
fn link(target: &Path, path: &Path) {
    let _ = std::fs::remove_file(path);
    std::os::unix::fs::symlink(target, path).unwrap();
}

/// Runs `zrak ARGS` in `dir` (through `sh -c` when `shell_prefix` is
/// given, e.g. a `ulimit`), expecting a refusal by zrak itself (status 1,
/// not a signal or a panic) within `seconds`; returns its stderr and how
/// long it took. A command still running then is killed and fails the
/// test: a hang is what several of these cases were.
fn refused_within(
    dir: &Path,
    shell_prefix: Option<&str>,
    args: &[&str],
    seconds: u64,
) -> (String, Duration) {
    let mut command = match shell_prefix {
        Some(prefix) => {
            let mut sh = Command::new("sh");
            sh.arg("-c")
                .arg(format!("{prefix}; exec \"$0\" \"$@\""))
                .arg(crate::common::zrak_bin())
                .args(args);
            sh
        }
        None => {
            let mut zrak = zrak();
            zrak.args(args);
            zrak
        }
    };
    let started = Instant::now();
    let mut child = command
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("zrak starts");
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > Duration::from_secs(seconds) {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "zrak {} still ran after {seconds} s (it should refuse at once)",
                args.join(" ")
            );
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let took = started.elapsed();
    let output = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
    assert_eq!(
        output.status.code(),
        Some(1),
        "zrak {}: {} (expected a refusal, status 1):\n{stderr}",
        args.join(" "),
        output.status
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
    (stderr, took)
}

/// A file of the user's that links in a run folder point at.
fn users_file(d: &Path) -> std::path::PathBuf {
    let path = d.join("bashrc");
    std::fs::write(&path, "export PATH=$HOME/bin:$PATH\n").unwrap();
    path
}

fn assert_untouched(path: &Path) {
    assert_eq!(
        std::fs::read_to_string(path).unwrap(),
        "export PATH=$HOME/bin:$PATH\n",
        "{} was written through a link",
        path.display()
    );
}

#[test]
fn a_lock_file_that_is_a_link_is_never_written_through() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    let target = users_file(d);
    // A new run into a folder holding only a linked lock.
    std::fs::create_dir(d.join("fresh")).unwrap();
    link(&target, &d.join("fresh/.zrak.lock"));
    let error = fail(
        d,
        &[
            "train", "scene", "--steps", "1", "--engine", "cpu", "--out", "fresh",
        ],
    );
    assert!(
        error.contains("fresh/.zrak.lock: a symbolic link, which zrak does not write through")
            && error.contains("remove it"),
        "{error}"
    );
    assert_untouched(&target);
    // A resumed run whose lock is a link.
    let run = copy_run(d, "linked");
    link(&target, &run.join(".zrak.lock"));
    let error = fail(d, &["train", "--resume", "linked", "--steps", "3"]);
    assert!(
        error.contains("linked/.zrak.lock: a symbolic link"),
        "{error}"
    );
    assert_untouched(&target);
    assert_eq!(checkpoint_step(&run), 2, "a refused resume must not train");
}

#[test]
fn a_resumed_log_that_is_a_link_is_not_appended_through() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    let target = users_file(d);
    let run = copy_run(d, "linked-log");
    link(&target, &run.join("metrics.jsonl"));
    let error = fail(d, &["train", "--resume", "linked-log", "--steps", "3"]);
    assert!(
        error.contains(
            "linked-log/metrics.jsonl: a symbolic link, which zrak does not write through"
        ),
        "{error}"
    );
    assert_untouched(&target);
    assert!(
        std::fs::symlink_metadata(run.join("metrics.jsonl"))
            .unwrap()
            .file_type()
            .is_symlink()
    );
    assert_eq!(checkpoint_step(&run), 2);
}

#[test]
fn pipes_and_devices_in_a_run_folder_are_refused_at_once() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    fn eval(run: &str) -> Vec<String> {
        vec!["eval".into(), run.into()]
    }
    fn resume(run: &str) -> Vec<String> {
        ["train", "--resume", run, "--steps", "3"]
            .map(String::from)
            .to_vec()
    }
    fn render(run: &str) -> Vec<String> {
        let out = format!("{run}-frames");
        ["render", run, "--view", "0", "--out", &out]
            .map(String::from)
            .to_vec()
    }
    // (file, command, what the refusal says, whether it comes before the
    // scene loads and the model is built).
    type Args = fn(&str) -> Vec<String>;
    let cases: [(&str, Args, &str, bool); 6] = [
        (
            "run.json",
            eval,
            "run.json: cannot read the run's configuration",
            true,
        ),
        (
            "run.json",
            resume,
            "run.json: cannot read the run's configuration",
            true,
        ),
        (
            "checkpoint.zrak",
            eval,
            "checkpoint.zrak: cannot read the checkpoint",
            true,
        ),
        (
            "checkpoint.zrak",
            resume,
            "checkpoint.zrak: cannot resume from it",
            true,
        ),
        (
            "metrics.jsonl",
            resume,
            "metrics.jsonl: cannot continue the run's log",
            true,
        ),
        (
            "crop.json",
            render,
            "crop.json: cannot read the crop box",
            true,
        ),
    ];
    let mut timings = Vec::new();
    for (index, (file, command, says, early)) in cases.iter().enumerate() {
        for (kind, words) in [("pipe", "named pipe"), ("zero", "a device, not a file")] {
            let name = format!("run-{kind}-{index}");
            let run = copy_run(d, &name);
            if kind == "pipe" {
                make_fifo(&run.join(file));
            } else {
                link(Path::new("/dev/zero"), &run.join(file));
            }
            let args = command(&name);
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let (error, took) = refused_within(d, None, &args, 60);
            // A link is refused as a link where zrak appends (the log).
            let words = if *file == "metrics.jsonl" && kind == "zero" {
                "a symbolic link"
            } else {
                words
            };
            let says = if *file == "metrics.jsonl" && kind == "zero" {
                "metrics.jsonl: a symbolic link"
            } else {
                says
            };
            assert!(
                error.contains(says) && error.contains(words),
                "{file} as a {kind}, zrak {}:\n{error}",
                args.join(" ")
            );
            if *early {
                // The bound: refused within a second (measured:
                // 10 to 30 ms on a busy 2-core Zen 4).
                assert!(
                    took < Duration::from_secs(1),
                    "{file} as a {kind}: refused after {took:?}"
                );
            }
            timings.push(format!("{file} {kind} {}: {took:?}", args[0]));
        }
    }
    eprintln!("refusal times: {timings:#?}");
}

/// `zrak train scene` for one step into `out`, with `--force` if asked.
fn train_into(out: &str, force: bool) -> Vec<&str> {
    let mut args = vec![
        "train", "scene", "--steps", "1", "--engine", "cpu", "--out", out,
    ];
    if force {
        args.push("--force");
    }
    args
}

#[test]
fn a_folder_that_is_no_run_is_not_trained_into_without_force() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    // The user's own run.json and metrics.jsonl.
    std::fs::create_dir(d.join("mine")).unwrap();
    std::fs::write(d.join("mine/run.json"), "{\"my\": \"settings\"}").unwrap();
    std::fs::write(d.join("mine/metrics.jsonl"), "{\"my\": 1}\n").unwrap();
    let error = fail(d, &train_into("mine", false));
    assert!(
        error.contains("mine is not empty and holds no zrak run (metrics.jsonl, run.json)")
            && error.contains("--force to move mine aside"),
        "{error}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("mine/run.json")).unwrap(),
        "{\"my\": \"settings\"}"
    );
    // A zrak run killed before its first checkpoint.
    let partial = copy_run(d, "partial");
    std::fs::remove_file(partial.join("checkpoint.zrak")).unwrap();
    let log = std::fs::read_to_string(partial.join("metrics.jsonl")).unwrap();
    let error = fail(d, &train_into("partial", false));
    assert!(
        error.contains("partial already holds a run that stopped before its first checkpoint")
            && error.contains("--force"),
        "{error}"
    );
    assert_eq!(
        std::fs::read_to_string(partial.join("metrics.jsonl")).unwrap(),
        log
    );
    // --force moves either aside, renamed, and says where.
    let out = run_in(d, &train_into("mine", true));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("moved the files that were in mine aside to mine.old"),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("mine.old/run.json")).unwrap(),
        "{\"my\": \"settings\"}"
    );
    assert_eq!(checkpoint_step(&d.join("mine")), 1);
    let out = run_in(d, &train_into("partial", true));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("moved the run that was in partial aside to partial.old"),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("partial.old/metrics.jsonl")).unwrap(),
        log
    );
    // An empty folder is trained into as it is.
    std::fs::create_dir(d.join("empty")).unwrap();
    succeed(d, &train_into("empty", false));
    assert_eq!(checkpoint_step(&d.join("empty")), 1);
}

#[test]
fn out_must_be_a_folder_of_its_own() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    succeed(
        d,
        &["demo", "--out", "scene", "--size", "16", "--views", "3"],
    );
    let scene_files = std::fs::read_dir(d.join("scene")).unwrap().count();
    for force in [false, true] {
        let error = fail(d, &train_into("scene", force));
        assert!(
            error.contains("--out scene is the scene folder scene")
                && error.contains("give --out a folder of its own"),
            "{error}"
        );
        // The same folder by another path, and a folder holding it.
        let error = fail(d, &train_into("scene/../scene/", force));
        assert!(error.contains("is the scene folder"), "{error}");
        let error = fail(d, &train_into(".", force));
        assert!(error.contains("--out . holds the scene folder"), "{error}");
    }
    assert!(d.join("scene/transforms_train.json").is_file());
    assert!(!d.join("scene.old").exists());
    assert_eq!(
        std::fs::read_dir(d.join("scene")).unwrap().count(),
        scene_files
    );
    // A file.
    std::fs::write(d.join("notes.txt"), "mine").unwrap();
    for force in [false, true] {
        let error = fail(d, &train_into("notes.txt", force));
        assert!(
            error.contains("notes.txt is a file, not a folder")
                && error.contains("give the name of a new folder"),
            "{error}"
        );
    }
    assert_eq!(
        std::fs::read_to_string(d.join("notes.txt")).unwrap(),
        "mine"
    );
    // A link that loops.
    std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
    let error = fail(d, &train_into("loop", false));
    assert!(
        error.contains("loop cannot be the run folder: it is a symbolic link that loops"),
        "{error}"
    );
}

/// Rewrites `run`'s checkpoint with `edit` applied to its header (a new
/// file: the original may be linked elsewhere).
fn edit_checkpoint_header(run: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let path = run.join("checkpoint.zrak");
    let mut checkpoint = Checkpoint::load(&path).unwrap();
    edit(&mut checkpoint.header);
    std::fs::remove_file(&path).unwrap();
    checkpoint.save(&path).unwrap();
}

#[test]
fn a_folder_named_checkpoint_zrak_is_called_a_folder() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    // A folder named checkpoint.zrak.
    let run = copy_run(d, "folder");
    std::fs::remove_file(run.join("checkpoint.zrak")).unwrap();
    std::fs::create_dir(run.join("checkpoint.zrak")).unwrap();
    for args in [
        &["eval", "folder"][..],
        &["train", "--resume", "folder", "--steps", "3"],
    ] {
        let (error, _) = refused_within(d, None, args, 60);
        assert!(
            error.contains("folder/checkpoint.zrak") && error.contains("a folder, not a file"),
            "{error}"
        );
        assert!(!error.contains("too short"), "{error}");
    }
}

#[test]
fn a_checkpoint_step_that_is_no_step_count_is_refused_naming_the_field() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    // A negative step.
    let run = copy_run(d, "negative");
    edit_checkpoint_header(&run, |h| h["trainer"]["step"] = serde_json::json!(-1));
    for args in [
        &["eval", "negative"][..],
        &["train", "--resume", "negative", "--steps", "3"],
    ] {
        let error = fail(d, args);
        assert!(
            error.contains("negative/checkpoint.zrak: the checkpoint's `trainer.step` is -1")
                && error.contains("cannot be negative"),
            "{error}"
        );
        assert!(!error.contains("no trainer state"), "{error}");
    }
    // A step past what zrak counts.
    let run = copy_run(d, "past");
    edit_checkpoint_header(&run, |h| {
        h["trainer"]["step"] = serde_json::json!(1u64 << 32)
    });
    let error = fail(d, &["eval", "past"]);
    assert!(
        error.contains("`trainer.step` is 4294967296, more than the 4294967295 steps"),
        "{error}"
    );
}

#[test]
fn a_run_at_the_last_step_zrak_counts_is_not_continued_from_another() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    // Evaluated as it is, never continued from another step.
    let run = copy_run(d, "last");
    edit_checkpoint_header(&run, |h| h["trainer"]["step"] = serde_json::json!(u32::MAX));
    let log = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let out = succeed(d, &["eval", "last"]);
    assert!(out.contains("step 4294967295"), "{out}");
    let error = fail(d, &["train", "--resume", "last", "--time", "1m"]);
    assert!(
        error.contains("is at step 4294967295, the last step zrak counts")
            && error.contains("cannot be continued"),
        "{error}"
    );
    assert_eq!(checkpoint_step(&run), u32::MAX as u64);
    assert_eq!(
        std::fs::read_to_string(run.join("metrics.jsonl")).unwrap(),
        log
    );
}

#[test]
fn a_checkpoint_claiming_a_huge_tensor_is_refused_before_allocating() {
    let _cores = crate::common::shared();
    let dir = temp_dir();
    let d = dir.path();
    scene_and_run(d);
    let run = copy_run(d, "huge");
    let path = run.join("checkpoint.zrak");
    let bytes = std::fs::read(&path).unwrap();
    let header_length = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    let mut table: serde_json::Value =
        serde_json::from_slice(&bytes[20..20 + header_length]).unwrap();
    // `params` as 2^33 f32 values (32 GiB), stored as a hole in a sparse
    // file, so the file's size vouches for them.
    let huge_values = 1u64 << 33;
    let tensors = table["tensors"].as_array_mut().unwrap();
    let params = tensors.iter_mut().find(|t| t["name"] == "params").unwrap();
    params["values"] = serde_json::json!(huge_values);
    params["encoding"] = serde_json::json!({"kind": "f32"});
    params["bytes"] = serde_json::json!(4 * huge_values);
    let stored: u64 = tensors.iter().map(|t| t["bytes"].as_u64().unwrap()).sum();
    let header = serde_json::to_vec(&table).unwrap();
    let mut crafted = b"ZRAKCKPT".to_vec();
    crafted.extend_from_slice(&2u32.to_le_bytes());
    crafted.extend_from_slice(&(header.len() as u64).to_le_bytes());
    crafted.extend_from_slice(&header);
    crafted.extend_from_slice(&zrak::crc32c::crc32c(&header).to_le_bytes());
    std::fs::remove_file(&path).unwrap();
    let file = std::fs::File::create(&path).unwrap();
    use std::io::Write;
    (&file).write_all(&crafted).unwrap();
    file.set_len(crafted.len() as u64 + stored).unwrap();
    drop(file);
    // 4 GB of address space: an allocation of the claimed 32 GiB would
    // abort the process.
    let limit = Some("ulimit -v 4000000");
    for args in [
        &["eval", "huge"][..],
        &["render", "huge", "--view", "0", "--out", "huge-frames"],
        &["train", "--resume", "huge", "--steps", "3"],
    ] {
        let (error, _) = refused_within(d, limit, args, 120);
        assert!(
            error.contains("huge/checkpoint.zrak")
                && error.contains(
                    "tensor `params` is listed with 8589934592 values where this run's model has"
                ),
            "zrak {}:\n{error}",
            args.join(" ")
        );
    }
    assert!(!d.join("huge-frames").exists());
}
