//! File names that look alike but are not the same name: an accented
//! letter can be written as one precomposed character (Unicode NFC, as most
//! editors and Linux tools write it) or as a letter followed by combining
//! marks (NFD, as macOS file systems store names). Both look identical, but
//! the file system compares bytes, so a `file_path` in one form does not
//! find a file named in the other. These helpers find such a file, so that
//! "not found" can name the file that is there.

use std::path::{Component, Path, PathBuf};

use crate::scene::escape_controls;

/// Whether `c` is a combining mark of the block Latin accents use
/// (U+0300 to U+036F: grave, acute, circumflex, tilde, diaeresis, cedilla …).
fn is_combining_mark(c: char) -> bool {
    ('\u{300}'..='\u{36F}').contains(&c)
}

/// `name` with every accented letter, whichever way it is written, replaced
/// by one placeholder: an ASCII character stays as it is, a non-ASCII
/// character and the combining marks after it become one `\u{FFFD}`, and so
/// does an ASCII letter followed by combining marks. "café" written
/// precomposed (NFC) and decomposed (NFD) both give "caf\u{FFFD}"; "cafe"
/// and "caf" give themselves. Without Unicode's tables this cannot tell an
/// "é" from an "è", so two names it equates may differ in their accents.
fn skeleton(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    let mut chars = name.chars().peekable();
    while let Some(c) = chars.next() {
        let mut accented = !c.is_ascii();
        while chars.peek().is_some_and(|&next| is_combining_mark(next)) {
            chars.next();
            accented = true;
        }
        out.push(if accented { '\u{FFFD}' } else { c });
    }
    out
}

/// How `name` writes its accents, for a message.
fn form(name: &str) -> &'static str {
    if name.chars().any(is_combining_mark) {
        "as letters followed by combining marks (Unicode NFD)"
    } else {
        "as precomposed letters (Unicode NFC)"
    }
}

/// Where `path` does not exist, looks at the first of its components that
/// is missing for a name beside it that differs only in how its accented
/// letters are written, and says which file is there. `None` when there is
/// no such name (or the path's names are plain ASCII).
pub fn lookalike_hint(path: &Path) -> Option<String> {
    let mut present = PathBuf::new();
    for component in path.components() {
        let next = present.join(component);
        if crate::files::exists_at_all(&next) {
            present = next;
            continue;
        }
        let Component::Normal(wanted) = component else {
            return None;
        };
        let wanted = wanted.to_str()?;
        if wanted.is_ascii() {
            return None;
        }
        let key = skeleton(wanted);
        let folder = if present.as_os_str().is_empty() {
            Path::new(".")
        } else {
            present.as_path()
        };
        // A folder of photographs holds thousands of names, not millions;
        // the bound keeps a pathological one from stalling the message.
        let found = std::fs::read_dir(folder)
            .ok()?
            .take(1_000_000)
            .flatten()
            .filter_map(|entry| entry.file_name().into_string().ok())
            .find(|name| name != wanted && !name.is_ascii() && skeleton(name) == key)?;
        let how = if form(&found) != form(wanted) {
            format!(
                "it writes its accents {}, the scene file {}",
                form(&found),
                form(wanted)
            )
        } else {
            "its accented letters differ".to_string()
        };
        return Some(format!(
            "{} holds \"{}\", which looks alike but is another name to the file system: \
             {how}; rename the file or change the scene file to match",
            escape_controls(&folder.display().to_string()),
            escape_controls(&found),
        ));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    const NFC: &str = "caf\u{e9}.png";
    const NFD: &str = "cafe\u{301}.png";

    #[test]
    fn both_forms_have_one_skeleton() {
        assert_eq!(skeleton(NFC), skeleton(NFD));
        assert_ne!(skeleton(NFC), skeleton("cafe.png"));
        assert_ne!(skeleton(NFC), skeleton("caf.png"));
        assert_eq!(skeleton("r_0.png"), "r_0.png");
        // A letter with two marks, partly precomposed or not at all.
        assert_eq!(skeleton("\u{fc}\u{304}"), skeleton("u\u{308}\u{304}"));
    }

    #[test]
    fn the_file_in_the_other_form_is_named() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(NFD), b"").unwrap();
        let hint = lookalike_hint(&dir.path().join(NFC)).unwrap();
        assert!(hint.contains(NFD), "{hint}");
        assert!(hint.contains("NFD") && hint.contains("NFC"), "{hint}");
        // The same lookup the other way round.
        std::fs::write(dir.path().join("b\u{e9}.png"), b"").unwrap();
        let hint = lookalike_hint(&dir.path().join("be\u{301}.png")).unwrap();
        assert!(hint.contains("b\u{e9}.png"), "{hint}");
        // A folder in the other form, the file inside it missing too.
        std::fs::create_dir(dir.path().join("r\u{e9}sum\u{e9}")).unwrap();
        let hint = lookalike_hint(&dir.path().join("re\u{301}sume\u{301}/x.png")).unwrap();
        assert!(hint.contains("r\u{e9}sum\u{e9}"), "{hint}");
        // Plain names and names with nothing alike get no hint.
        assert_eq!(lookalike_hint(&dir.path().join("r_0.png")), None);
        assert_eq!(lookalike_hint(&dir.path().join("na\u{ef}ve.png")), None);
    }
}
