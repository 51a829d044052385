//! The source's layers import one way: a module may use those below it,
//! never one above (docs/design.md, "Shape"). The test reads `src/`, counts
//! every path into another top-level module (`crate::x`, or `zrak::x` from
//! the binary's modules, `use` groups included, comments left out) and
//! fails on an upward import that is not one of today's known ones, or on
//! more of a known kind than are left: the known ones may only go away.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Bottom to top. Utilities (checksums, files, interrupts, random
/// numbers) sit below everything; image metrics just above the scene's
/// images.
const LAYERS: &[&[&str]] = &[
    &["crc32c", "files", "interrupt", "isa", "rng"],
    &["scene"],
    &["metrics"],
    &["field"],
    &["model"],
    &["engine"],
    &["train"],
    &["render", "mesh"],
    &["bench"],
    &["session"],
    &["app"],
    &["cli"],
];

/// Upward imports that remain, as (from, to, how many paths at most).
/// Lower a count when a change removes some; remove the row at zero.
const KNOWN_UPWARD: &[(&str, &str, usize)] = &[];

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|layer| layer.contains(&module))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The top-level module a file of `src/` belongs to (`None` for the crate
/// roots, which only declare modules).
fn module_of(src: &Path, file: &Path) -> Option<String> {
    let relative = file.strip_prefix(src).unwrap();
    let first = relative.components().next()?.as_os_str().to_str()?;
    let name = first.strip_suffix(".rs").unwrap_or(first);
    (!matches!(name, "lib" | "main")).then(|| name.to_string())
}

/// The source without its comments (line comments, doc comments and block
/// comments); string contents are kept, which no import resembles.
fn without_comments(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars().peekable();
    let mut in_string = false;
    while let Some(c) = chars.next() {
        if in_string {
            out.push(c);
            if c == '\\' {
                if let Some(next) = chars.next() {
                    out.push(next);
                }
            } else if c == '"' {
                in_string = false;
            }
            continue;
        }
        match (c, chars.peek()) {
            ('"', _) => {
                in_string = true;
                out.push(c);
            }
            ('/', Some('/')) => {
                for skipped in chars.by_ref() {
                    if skipped == '\n' {
                        out.push('\n');
                        break;
                    }
                }
            }
            ('/', Some('*')) => {
                chars.next();
                let mut previous = ' ';
                for skipped in chars.by_ref() {
                    if previous == '*' && skipped == '/' {
                        break;
                    }
                    previous = skipped;
                }
            }
            _ => out.push(c),
        }
    }
    out
}

fn identifier_at(text: &str, at: usize) -> &str {
    let rest = &text[at..];
    let end = rest
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(rest.len());
    &rest[..end]
}

/// The top-level modules named by each path that starts with `root::`: a
/// plain path names one; a `use root::{a::x, b}` group names each of its
/// first-level entries.
fn modules_named(text: &str, root: &str) -> Vec<String> {
    paths_from(text, &format!("{root}::"), &[])
        .into_iter()
        .filter_map(|path| path.into_iter().next())
        .collect()
}

/// Paths from each module into every other, counted.
fn imports(src: &Path) -> BTreeMap<(String, String), usize> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut counts = BTreeMap::new();
    for file in files {
        let Some(module) = module_of(src, &file) else {
            continue;
        };
        let text = without_comments(&std::fs::read_to_string(&file).unwrap());
        for root in ["crate", "zrak"] {
            for named in modules_named(&text, root) {
                if named != module && layer_of(&named).is_some() {
                    *counts.entry((module.clone(), named)).or_insert(0) += 1;
                }
            }
        }
    }
    counts
}

#[test]
fn every_module_of_src_has_a_layer() {
    let _cores = crate::common::shared();
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    for file in files {
        if let Some(module) = module_of(&src, &file) {
            assert!(
                layer_of(&module).is_some(),
                "{} is in no layer of tests/it/layering.rs: give src/{module} its place",
                file.display()
            );
        }
    }
}

#[test]
fn no_module_imports_one_above_it_beyond_the_known_ones() {
    let _cores = crate::common::shared();
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let counts = imports(&src);
    let mut upward = Vec::new();
    for ((from, to), &count) in &counts {
        if layer_of(to) > layer_of(from) {
            upward.push(format!("{from} -> {to}: {count}"));
        }
    }
    eprintln!("upward imports: {upward:?}");
    let mut problems = Vec::new();
    for ((from, to), &count) in &counts {
        if layer_of(to) <= layer_of(from) {
            continue;
        }
        match KNOWN_UPWARD.iter().find(|(f, t, _)| f == from && t == to) {
            None => problems.push(format!(
                "src/{from} imports src/{to}, a layer above it ({count} paths)"
            )),
            Some(&(_, _, known)) if count > known => problems.push(format!(
                "src/{from} imports src/{to} {count} times, {known} are known: no new ones"
            )),
            Some(&(_, _, known)) if count < known => problems.push(format!(
                "src/{from} imports src/{to} {count} times now, fewer than {known}: \
                 lower its row in KNOWN_UPWARD"
            )),
            Some(_) => {}
        }
    }
    for (from, to, known) in KNOWN_UPWARD {
        if !counts.contains_key(&(from.to_string(), to.to_string())) {
            problems.push(format!(
                "src/{from} no longer imports src/{to} ({known} known): remove its row"
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_reader_finds_plain_paths_and_use_groups_and_skips_comments() {
    let _cores = crate::common::shared();
    let text = without_comments(
        "use crate::{engine::cpu, train::{a, b}, render};\n\
         // crate::app::x in a comment\n\
         /* crate::cli */ let s = \"// not a comment\"; crate::scene::load();\n\
         notcrate::field::x; zrak::bench::run();",
    );
    assert_eq!(
        modules_named(&text, "crate"),
        vec!["engine", "train", "render", "scene"]
    );
    assert_eq!(modules_named(&text, "zrak"), vec!["bench"]);
}

/// The source without its `#[cfg(test)]` modules: each `#[cfg(test)]`
/// followed by a `mod name { … }` loses the block (braces in string
/// literals are skipped); a `#[cfg(test)] mod name;` is kept, its file
/// being a test file of its own (see [`test_module_files`]).
fn without_test_modules(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(found) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..found]);
        let after = &rest[found + "#[cfg(test)]".len()..];
        let item = after.trim_start();
        let item = item.strip_prefix("pub(crate)").unwrap_or(item).trim_start();
        let body = item
            .strip_prefix("mod ")
            .and_then(|m| m.find(['{', ';']).map(|end| (m, end)))
            .filter(|(m, end)| m.as_bytes()[*end] == b'{');
        let Some((module, open)) = body else {
            out.push_str("#[cfg(test)]");
            rest = after;
            continue;
        };
        let (mut depth, mut in_string, mut escaped) = (0usize, false, false);
        let mut end = module.len();
        for (offset, c) in module[open..].char_indices() {
            match c {
                _ if escaped => escaped = false,
                '\\' if in_string => escaped = true,
                '"' => in_string = !in_string,
                '{' if !in_string => depth += 1,
                '}' if !in_string => {
                    depth -= 1;
                    if depth == 0 {
                        end = open + offset + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        rest = &module[end..];
    }
    out.push_str(rest);
    out
}

/// Files of `dir` that only tests compile: every `tests.rs`, and the file
/// of each module declared `#[cfg(test)] mod name;`.
fn test_module_files(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    rust_files(dir, &mut files);
    let mut tests: Vec<PathBuf> = files
        .iter()
        .filter(|f| f.file_name().is_some_and(|n| n == "tests.rs"))
        .cloned()
        .collect();
    for file in &files {
        let text = without_comments(&std::fs::read_to_string(file).unwrap());
        // A module's children sit beside `mod.rs` and under a folder named
        // after any other file.
        let folder = if file.file_name().is_some_and(|n| n == "mod.rs") {
            file.parent().unwrap().to_path_buf()
        } else {
            file.with_extension("")
        };
        for part in text.split("#[cfg(test)]").skip(1) {
            let item = part.trim_start();
            let item = item.strip_prefix("pub(crate)").unwrap_or(item).trim_start();
            if let Some(module) = item.strip_prefix("mod ") {
                let name = identifier_at(module.trim_start(), 0);
                if module.trim_start()[name.len()..]
                    .trim_start()
                    .starts_with(';')
                {
                    tests.push(folder.join(format!("{name}.rs")));
                    tests.push(folder.join(name).join("mod.rs"));
                }
            }
        }
    }
    tests
}

/// How many paths of `text` (comments already removed) lead into the cpu
/// engine: `engine::cpu`, `super::cpu` (from the engine's own modules),
/// or `cpu` in a `use crate::engine::{…}` group.
fn paths_into_cpu_engine(text: &str) -> usize {
    let text: String = text.chars().filter(|c| !c.is_whitespace()).collect();
    let plain = text.matches("engine::cpu").count() + text.matches("super::cpu").count();
    let grouped = text
        .match_indices("engine::{")
        .filter(|&(at, _)| modules_named(&text[at..], "engine").contains(&"cpu".to_string()))
        .count();
    plain + grouped
}

/// zrak issue 28: the gpu engine takes what both engines use from
/// `engine::shared` and `field`, never from the cpu engine. Tests may
/// compare against the cpu engine: `tests.rs` files, `#[cfg(test)]`
/// modules and the files they declare are left out.
#[test]
fn the_gpu_engine_names_nothing_in_the_cpu_engine_outside_its_tests() {
    let _cores = crate::common::shared();
    let gpu = Path::new(env!("CARGO_MANIFEST_DIR")).join("src/engine/gpu");
    let tests = test_module_files(&gpu);
    let mut files = Vec::new();
    rust_files(&gpu, &mut files);
    let mut offenders = Vec::new();
    let mut checked = 0;
    for file in files.iter().filter(|f| !tests.contains(f)) {
        checked += 1;
        let text = std::fs::read_to_string(file).unwrap();
        let count = paths_into_cpu_engine(&without_test_modules(&without_comments(&text)));
        if count > 0 {
            offenders.push(format!(
                "{} names engine::cpu {count} times: take it from engine::shared or field",
                file.display()
            ));
        }
    }
    assert!(
        checked > 20,
        "only {checked} files of {} read",
        gpu.display()
    );
    assert!(offenders.is_empty(), "{}", offenders.join("\n"));
}

#[test]
fn the_cpu_engine_check_sees_paths_and_groups_and_skips_test_modules() {
    let _cores = crate::common::shared();
    let text = without_comments(
        "use crate::engine::cpu::march::march;\n\
         // crate::engine::cpu::sh in a comment\n\
         use crate::engine::{cpu::dense, shared};\n\
         use crate::engine::{gpu, shared::march};\n\
         let s = \"}\"; fn f() { super::cpu::x(); }\n\
         #[cfg(test)]\nmod tests {\n    use crate::engine::cpu::sh;\n    \
         fn g() { let s = \"{ }}\"; }\n}\n\
         #[cfg(test)]\nmod mirror;\n\
         crate::engine::gpu::march::x();",
    );
    assert_eq!(paths_into_cpu_engine(&text), 4);
    let kept = without_test_modules(&text);
    assert_eq!(paths_into_cpu_engine(&kept), 3);
    assert!(kept.contains("mod mirror;"), "{kept}");
    assert!(kept.contains("crate::engine::gpu::march::x();"), "{kept}");
}

/// The module a file of `src/` holds, as its path from the crate root:
/// `src/engine/cpu/march.rs` and `src/engine/cpu/march/mod.rs` are both
/// `engine::cpu::march`.
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let relative = file.strip_prefix(src).unwrap().with_extension("");
    let mut path: Vec<String> = relative
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    if path.last().is_some_and(|last| last == "mod") {
        path.pop();
    }
    path
}

/// The identifiers of a path from `at` on (`a::b::c`), up to the first
/// character that continues no path, and where a `use` group opens there
/// (`a::b::{`, or a `{` at `at` itself, right after a root's `::`): its
/// brace's position.
fn path_at(text: &str, at: usize) -> (Vec<String>, Option<usize>) {
    let mut segments = Vec::new();
    let mut at = at;
    loop {
        let name = identifier_at(text, at);
        if name.is_empty() {
            return (segments, text[at..].starts_with('{').then_some(at));
        }
        segments.push(name.to_string());
        at += name.len();
        if !text[at..].starts_with("::") {
            return (segments, None);
        }
        at += 2;
    }
}

/// Every path in `text` that starts with `root` (`crate::`, `super::`,
/// `engine::` …) where no identifier or `::` runs into it, as its
/// segments after `base` (the module `root` stands for); a `use` group
/// gives one path per entry. More `super::`s after `super::` climb from
/// `base`.
fn paths_from(text: &str, root: &str, base: &[String]) -> Vec<Vec<String>> {
    let mut named = Vec::new();
    let mut from = 0;
    while let Some(found) = text[from..].find(root) {
        let start = from + found;
        from = start + root.len();
        let boundary = text[..start]
            .chars()
            .next_back()
            .is_none_or(|c| !(c.is_alphanumeric() || c == '_' || c == ':'));
        if !boundary {
            continue;
        }
        let mut path = base.to_vec();
        let mut at = from;
        while root == "super::" && text[at..].starts_with("super::") {
            path.pop();
            at += "super::".len();
        }
        let (prefix, group) = path_at(text, at);
        path.extend(prefix);
        let Some(brace) = group else {
            named.push(path);
            continue;
        };
        // A group: each entry at the first depth.
        let entries = brace + 1;
        let mut depth = 1;
        let mut expecting = true;
        for (offset, c) in text[entries..].char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        break;
                    }
                }
                ',' if depth == 1 => expecting = true,
                c if expecting && depth == 1 && (c.is_alphanumeric() || c == '_') => {
                    let mut entry = path.clone();
                    entry.extend(path_at(text, entries + offset).0);
                    named.push(entry);
                    expecting = false;
                }
                _ => {}
            }
        }
    }
    named
}

/// Every module path that `text` (a file of module `here`) names, from
/// `crate::` or `zrak::` or relative to its own module (`super::`,
/// `self::`); a `use` group names each of its entries.
fn paths_named(text: &str, here: &[String]) -> Vec<Vec<String>> {
    let parent = &here[..here.len().saturating_sub(1)];
    let mut named = paths_from(text, "crate::", &[]);
    named.extend(paths_from(text, "zrak::", &[]));
    named.extend(paths_from(text, "super::", parent));
    named.extend(paths_from(text, "self::", here));
    named
}

/// Inside every module folder of `src/`, which of its parts import which:
/// for each folder, edges between its children (files and folders, and
/// `mod` for the folder's own `mod.rs` and the items it defines). Test
/// files and `#[cfg(test)]` modules are left out.
fn imports_inside_modules(src: &Path) -> BTreeMap<String, BTreeMap<String, Vec<String>>> {
    let tests = test_module_files(src);
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut edges: BTreeMap<String, BTreeMap<String, Vec<String>>> = BTreeMap::new();
    for file in files.iter().filter(|f| !tests.contains(f)) {
        let here = module_path(src, file);
        if here.is_empty() || matches!(here[0].as_str(), "lib" | "main") {
            continue;
        }
        let text = without_test_modules(&without_comments(&std::fs::read_to_string(file).unwrap()));
        for target in paths_named(&text, &here) {
            let common = here.iter().zip(&target).take_while(|(a, b)| a == b).count();
            // Between top-level modules the layers rule.
            if common == 0 {
                continue;
            }
            let folder = src.join(here[..common].join("/"));
            if !folder.is_dir() {
                continue;
            }
            let part = |path: &[String]| -> String {
                match path.get(common) {
                    Some(name)
                        if folder.join(format!("{name}.rs")).is_file()
                            || folder.join(name).join("mod.rs").is_file() =>
                    {
                        name.clone()
                    }
                    _ => "mod".to_string(),
                }
            };
            let (from, to) = (part(&here), part(&target));
            if from != to {
                let targets = edges
                    .entry(here[..common].join("::"))
                    .or_default()
                    .entry(from)
                    .or_default();
                if !targets.contains(&to) {
                    targets.push(to);
                }
            }
        }
    }
    edges
}

/// The circles of a graph: each set of two or more nodes that reach each
/// other, as a sorted list.
fn circles(edges: &BTreeMap<String, Vec<String>>) -> Vec<Vec<String>> {
    let reaches = |from: &String| {
        let mut seen = vec![from.clone()];
        let mut todo = vec![from.clone()];
        while let Some(node) = todo.pop() {
            for next in edges.get(&node).into_iter().flatten() {
                if !seen.contains(next) {
                    seen.push(next.clone());
                    todo.push(next.clone());
                }
            }
        }
        seen
    };
    let mut found: Vec<Vec<String>> = Vec::new();
    for node in edges.keys() {
        let forward = reaches(node);
        let mut circle: Vec<String> = forward
            .iter()
            .filter(|other| reaches(other).contains(node))
            .cloned()
            .collect();
        circle.sort();
        if circle.len() > 1 && !found.contains(&circle) {
            found.push(circle);
        }
    }
    found
}

/// Inside a module, parts import one way too: `field`'s generic files
/// (params, common, encoding, mlp) sit below the models' files, `mod.rs`
/// on top; `engine`'s shared stages below both engines. A circle (two
/// parts that reach each other through their imports) fails.
#[test]
fn no_module_has_a_circle_of_imports_inside_it() {
    let _cores = crate::common::shared();
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let edges = imports_inside_modules(&src);
    assert!(
        edges.get("field").is_some_and(|e| e.contains_key("ngp")),
        "the reader found no import inside field: {edges:?}"
    );
    let mut problems = Vec::new();
    for (folder, graph) in &edges {
        for circle in circles(graph) {
            let links: Vec<String> = circle
                .iter()
                .flat_map(|from| {
                    graph[from]
                        .iter()
                        .filter(|to| circle.contains(to))
                        .map(move |to| format!("{from} -> {to}"))
                })
                .collect();
            problems.push(format!("src/{folder}: {}", links.join(", ")));
        }
    }
    assert!(
        problems.is_empty(),
        "circles of imports:\n{}",
        problems.join("\n")
    );
}

#[test]
fn the_circle_reader_resolves_relative_paths_and_groups() {
    let _cores = crate::common::shared();
    let here: Vec<String> = ["engine", "cpu", "model"].map(String::from).to_vec();
    let text = "use super::march::{MarchParams, march};\n\
                use crate::engine::{shared::driver::X, gpu};\n\
                use self::fixed::*; super::super::shared::Y;";
    let named: Vec<String> = paths_named(text, &here)
        .into_iter()
        .map(|p| p.join("::"))
        .collect();
    for expected in [
        "engine::cpu::march::MarchParams",
        "engine::cpu::march::march",
        "engine::shared::driver::X",
        "engine::gpu",
        "engine::cpu::model::fixed",
        "engine::shared::Y",
    ] {
        assert!(
            named.contains(&expected.to_string()),
            "{expected}: {named:?}"
        );
    }
    // A brace after a plain path opens no group (a block, a struct).
    let plain = paths_named("use crate::engine;\n{ let a = 1; }", &here);
    assert_eq!(plain, vec![vec!["engine".to_string()]]);
    let graph: BTreeMap<String, Vec<String>> = [
        ("a", vec!["b"]),
        ("b", vec!["c"]),
        ("c", vec!["a"]),
        ("d", vec!["a"]),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v.into_iter().map(String::from).collect()))
    .collect();
    assert_eq!(circles(&graph), vec![vec!["a", "b", "c"]]);
}

/// Whether code (comments removed) names the GUI toolkit.
fn names_the_gui_toolkit(code: &str) -> bool {
    code.contains("egui") || code.contains("eframe")
}

/// Whether a file only declares modules (a folder's `mod.rs`).
fn only_declares_modules(code: &str) -> bool {
    code.lines()
        .map(str::trim)
        .filter(|line| !line.is_empty())
        .all(|line| line.starts_with("pub mod ") || line.starts_with("mod "))
}

/// zrak issue 44: `session/` is the viewer without its window, so it names
/// neither egui nor eframe; what of the viewer needs neither lives there,
/// so every file of `app/` names one of them.
#[test]
fn the_session_knows_no_gui_toolkit_and_the_app_is_only_the_gui() {
    let _cores = crate::common::shared();
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut problems = Vec::new();
    let mut checked = 0;
    for (folder, wants_toolkit) in [("session", false), ("app", true)] {
        let mut files = Vec::new();
        rust_files(&src.join(folder), &mut files);
        for file in files {
            checked += 1;
            let code = without_comments(&std::fs::read_to_string(&file).unwrap());
            if only_declares_modules(&code) || names_the_gui_toolkit(&code) == wants_toolkit {
                continue;
            }
            problems.push(if wants_toolkit {
                format!(
                    "{} names neither egui nor eframe: it belongs in src/session",
                    file.display()
                )
            } else {
                format!(
                    "{} names egui or eframe: the GUI belongs in src/app",
                    file.display()
                )
            });
        }
    }
    assert!(checked > 15, "only {checked} files read");
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_toolkit_check_reads_code_and_knows_a_folders_module_list() {
    let _cores = crate::common::shared();
    let code = without_comments("//! The eframe viewer.\npub mod ui;\n\npub mod viewer;\n");
    assert!(only_declares_modules(&code));
    assert!(!names_the_gui_toolkit(&code));
    let code = without_comments("use eframe::egui;\npub mod ui;\n");
    assert!(!only_declares_modules(&code));
    assert!(names_the_gui_toolkit(&code));
}
