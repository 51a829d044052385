//! Every test of this crate holds the lock of `common` (`shared` or
//! `alone`): one written without it would run beside the viewer's timing
//! tests, which must run alone, and nothing else would notice.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Whether a line takes the lock.
fn takes_the_lock(line: &str) -> bool {
    line.contains("common::shared()") || line.contains("common::alone()")
}

/// The name of the function a line declares, if it declares one.
fn declared(line: &str) -> Option<&str> {
    let rest = line
        .trim_start()
        .strip_prefix("pub ")
        .unwrap_or(line.trim_start());
    let rest = rest.strip_prefix("fn ")?;
    let end = rest.find(|c: char| !(c.is_alphanumeric() || c == '_'))?;
    Some(&rest[..end])
}

/// The `#[test]` functions of `source` that do not take the lock as their
/// first statement, either themselves or through the function of the same
/// file that their first statement calls.
fn unguarded(source: &str) -> Vec<String> {
    let lines: Vec<&str> = source.lines().collect();
    // Each function's first statement: the first line after its signature's
    // opening brace that is neither blank nor a comment.
    let mut first_statement: HashMap<&str, &str> = HashMap::new();
    let mut tests = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        let Some(name) = declared(line) else {
            continue;
        };
        let Some(open) = (i..lines.len()).find(|&j| lines[j].trim_end().ends_with('{')) else {
            continue;
        };
        let statement = lines[open + 1..]
            .iter()
            .find(|l| !l.trim().is_empty() && !l.trim_start().starts_with("//"))
            .copied()
            .unwrap_or("");
        first_statement.insert(name, statement);
        let attributes = lines[..i]
            .iter()
            .rev()
            .take_while(|l| l.trim_start().starts_with("#[") || l.trim_start().starts_with("//"));
        if attributes.into_iter().any(|l| l.trim() == "#[test]") {
            tests.push(name);
        }
    }
    tests
        .into_iter()
        .filter(|name| {
            let statement = first_statement[name];
            let called = statement.trim_start().split('(').next().unwrap_or("");
            !(takes_the_lock(statement)
                || first_statement
                    .get(called)
                    .is_some_and(|callee| takes_the_lock(callee)))
        })
        .map(str::to_string)
        .collect()
}

fn rust_files(dir: &Path, into: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, into);
        } else if path.extension().is_some_and(|e| e == "rs") {
            into.push(path);
        }
    }
}

#[test]
fn every_test_takes_the_lock_first() {
    let _cores = crate::common::shared();
    // The reader first, on a file whose answer is known: a test that takes
    // the lock, one that does through the helper it calls first, one that
    // takes it too late and one that never does.
    let sample = "#[test]\nfn a() {\n    let _cores = crate::common::shared();\n}\n\
                  fn helper() {\n    // why\n    let _alone = common::alone();\n}\n\
                  #[test]\n#[ignore]\nfn b() {\n    helper();\n}\n\
                  #[test]\nfn c() {\n    let x = 1;\n    let _cores = common::shared();\n}\n\
                  #[test]\nfn d() {\n    assert!(true);\n}\n";
    assert_eq!(unguarded(sample), ["c", "d"]);

    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/it");
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    let mut missing = Vec::new();
    for file in &files {
        let source = std::fs::read_to_string(file).unwrap();
        for name in unguarded(&source) {
            missing.push(format!("{}: {name}", file.display()));
        }
    }
    assert!(
        missing.is_empty(),
        "tests that do not begin by taking common::shared() or common::alone(): {missing:#?}"
    );
}
