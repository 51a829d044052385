//! Writing files without losing what is already on disk, and saying what
//! is wrong with a path that cannot be read.
//!
//! Every file zrak writes goes to a temporary file beside its destination,
//! is flushed to disk and then renamed over it: a full disk, a crash or an
//! interrupt leaves either the old file whole or the new one whole, never
//! a truncated mix. The temporary names are unique per process and call,
//! so two writers never write into one temporary file.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A temporary file name beside `path`, unique to this process and call:
/// `.NAME.PID.N.tmp` (hidden, so a folder listing shows the real files).
pub fn temporary_beside(path: &Path) -> PathBuf {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".into());
    path.with_file_name(format!(".{name}.{}.{n}.tmp", std::process::id()))
}

/// Writes `path` through `write` into a temporary file beside it, flushes
/// it to disk and renames it into place. On any error the temporary file
/// is removed and `path` is left as it was.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let temporary = temporary_beside(path);
    let result = (|| {
        let mut out = BufWriter::new(File::create_new(&temporary)?);
        write(&mut out)?;
        let file = out.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&temporary, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&temporary);
    }
    result
}

/// [`write_atomically`] for bytes already in memory.
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomically(path, |out| out.write_all(bytes))
}

/// What is wrong with `path` when it cannot be read as a file, in words
/// that name the real problem rather than "not found": a folder, a named
/// pipe, a symbolic link that points nowhere or at itself.
pub fn describe_unreadable(path: &Path, error: &std::io::Error) -> String {
    match std::fs::symlink_metadata(path) {
        Err(_) => match error.kind() {
            std::io::ErrorKind::PermissionDenied => format!("permission denied ({error})"),
            _ => "not found".into(),
        },
        Ok(meta) if meta.file_type().is_symlink() => match std::fs::metadata(path) {
            Ok(_) => format!("cannot read through the symbolic link: {error}"),
            Err(e) if is_link_loop(&e) => {
                "a symbolic link that loops (it leads back to itself)".into()
            }
            Err(_) => match std::fs::read_link(path) {
                Ok(target) => format!(
                    "a dangling symbolic link (it points to {}, which does not exist)",
                    target.display()
                ),
                Err(_) => "a dangling symbolic link".into(),
            },
        },
        Ok(meta) if meta.is_dir() => "a folder, not a file".into(),
        Ok(meta) => special_file(&meta).map_or_else(|| error.to_string(), str::to_string),
    }
}

/// What a file that is neither a regular file nor a folder is.
#[cfg(unix)]
fn special_file(meta: &std::fs::Metadata) -> Option<&'static str> {
    use std::os::unix::fs::FileTypeExt;
    let kind = meta.file_type();
    if kind.is_fifo() {
        Some("a named pipe (FIFO), not a file: zrak reads scenes from files")
    } else if kind.is_socket() {
        Some("a socket, not a file")
    } else if kind.is_block_device() || kind.is_char_device() {
        Some("a device, not a file")
    } else {
        None
    }
}

#[cfg(not(unix))]
fn special_file(_meta: &std::fs::Metadata) -> Option<&'static str> {
    None
}

/// Whether opening failed on a chain of symbolic links that never ends.
fn is_link_loop(error: &std::io::Error) -> bool {
    #[cfg(unix)]
    {
        error.raw_os_error() == Some(libc::ELOOP)
    }
    #[cfg(not(unix))]
    {
        let _ = error;
        false
    }
}

/// Checks that `path` is a regular file (through any links) before it is
/// opened: a named pipe would block the reader forever, and a folder or a
/// broken link deserves its own words. The error is the description
/// ("not found", "a folder, not a file", …).
pub fn check_regular_file(path: &Path) -> Result<(), String> {
    match std::fs::metadata(path) {
        Ok(meta) if meta.is_file() => Ok(()),
        Ok(_) => Err(describe_unreadable(
            path,
            &std::io::Error::other("not a regular file"),
        )),
        Err(e) => Err(describe_unreadable(path, &e)),
    }
}

/// Why `path` is not a folder, for a path that was expected to be one.
pub fn describe_not_a_folder(path: &Path) -> String {
    match std::fs::metadata(path) {
        Ok(meta) if meta.is_dir() => "a folder".into(),
        Ok(meta) if meta.is_file() => "not a folder (it is a file)".into(),
        Ok(_) => describe_unreadable(path, &std::io::Error::other("not a folder")),
        Err(e) => {
            let problem = describe_unreadable(path, &e);
            if problem == "not found" {
                "folder not found".into()
            } else {
                problem
            }
        }
    }
}

/// Whether anything (even a dangling link) exists at `path`.
pub fn exists_at_all(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok()
}

/// Free memory in bytes as the kernel estimates it for new allocations
/// (`MemAvailable`), or `None` where that is unknown.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Bytes in words: `12.3 MB`, `4.0 GB`.
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= 1e9 {
        format!("{:.1} GB", b / 1e9)
    } else if b >= 1e6 {
        format!("{:.1} MB", b / 1e6)
    } else if b >= 1e3 {
        format!("{:.1} kB", b / 1e3)
    } else {
        format!("{bytes} bytes")
    }
}

/// Refuses work whose memory (`bytes`, estimated before anything is
/// allocated) is more than the machine has free, naming `what` needs it:
/// an allocation that fails aborts the process, losing anything unsaved.
pub fn check_memory(what: &str, bytes: u64) -> Result<(), String> {
    let Some(available) = available_memory() else {
        return Ok(());
    };
    if bytes > available {
        return Err(format!(
            "{what} needs about {} of memory; this machine has {} available",
            human_bytes(bytes),
            human_bytes(available)
        ));
    }
    Ok(())
}

/// Refuses an output file that could not be written, before any work: an
/// existing one unless `replace`, a missing or read-only folder (probed by
/// creating, then removing, a file beside it as an atomic write would).
pub fn check_new_file(out: &Path, replace: bool) -> Result<(), String> {
    if !replace && exists_at_all(out) {
        return Err(format!(
            "{} already exists and replacing it was not asked for",
            out.display()
        ));
    }
    let folder = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !folder.is_dir() {
        return Err(format!(
            "{}: cannot write there ({})",
            out.display(),
            describe_not_a_folder(folder)
        ));
    }
    let probe = temporary_beside(out);
    std::fs::File::create_new(&probe)
        .map_err(|e| format!("{}: cannot write there: {e}", out.display()))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_atomic_write_replaces_the_file_whole_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.json");
        std::fs::write(&path, "old").unwrap();
        write_bytes_atomically(&path, b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "new");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }

    #[test]
    fn a_failed_write_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.json");
        std::fs::write(&path, "old").unwrap();
        let error = write_atomically(&path, |out| {
            out.write_all(b"half")?;
            Err(std::io::Error::other("disk full"))
        })
        .unwrap_err();
        assert_eq!(error.to_string(), "disk full");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn temporary_names_differ_per_call() {
        let path = Path::new("/x/checkpoint.zrak");
        assert_ne!(temporary_beside(path), temporary_beside(path));
        assert_eq!(temporary_beside(path).parent(), Some(Path::new("/x")));
    }

    #[cfg(unix)]
    #[test]
    fn unreadable_paths_are_described_by_what_they_are() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let error = std::io::Error::from(std::io::ErrorKind::NotFound);
        assert_eq!(describe_unreadable(&d.join("none"), &error), "not found");
        assert!(describe_unreadable(d, &error).contains("a folder"));
        std::os::unix::fs::symlink(d.join("gone"), d.join("dangling")).unwrap();
        let text = describe_unreadable(&d.join("dangling"), &error);
        assert!(text.contains("dangling symbolic link"), "{text}");
        assert!(text.contains("gone"), "{text}");
        std::os::unix::fs::symlink(d.join("loop"), d.join("loop")).unwrap();
        let text = describe_unreadable(&d.join("loop"), &error);
        assert!(text.contains("loops"), "{text}");
        let fifo = d.join("fifo");
        let name = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
        assert!(describe_unreadable(&fifo, &error).contains("named pipe"));
    }
}
