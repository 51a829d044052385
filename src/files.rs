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

/// Why a path cannot be read as a file, in words that name the real
/// problem rather than "not found": a folder, a named pipe, a symbolic
/// link that points nowhere or at itself. `Display` gives the words that
/// follow the path in a message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Unreadable {
    /// Nothing is at the path.
    #[error("not found")]
    NotFound,
    /// A symbolic link that points nowhere, loops, or leads to something
    /// that is not a file.
    #[error("{0}")]
    Link(String),
    /// Anything else: a folder, a pipe, a device, no permission.
    #[error("{0}")]
    Other(String),
}

/// What is wrong with `path` when it cannot be read as a file: see
/// [`Unreadable`].
pub fn describe_unreadable(path: &Path, error: &std::io::Error) -> String {
    unreadable(path, error).to_string()
}

/// Why `path` cannot be read as a file, by kind: see [`Unreadable`].
pub fn unreadable(path: &Path, error: &std::io::Error) -> Unreadable {
    match std::fs::symlink_metadata(path) {
        Err(_) => match error.kind() {
            std::io::ErrorKind::PermissionDenied => {
                Unreadable::Other(format!("permission denied ({error})"))
            }
            _ => Unreadable::NotFound,
        },
        Ok(meta) if meta.file_type().is_symlink() => {
            Unreadable::Link(match std::fs::metadata(path) {
                Ok(target) => special_file(&target).map_or_else(
                    || format!("cannot read through the symbolic link: {error}"),
                    |what| format!("a symbolic link to {what}"),
                ),
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
            })
        }
        Ok(meta) if meta.is_dir() => Unreadable::Other("a folder, not a file".into()),
        Ok(meta) => {
            Unreadable::Other(special_file(&meta).map_or_else(|| error.to_string(), str::to_string))
        }
    }
}

/// What a file that is neither a regular file nor a folder is.
#[cfg(unix)]
fn special_file(meta: &std::fs::Metadata) -> Option<&'static str> {
    use std::os::unix::fs::FileTypeExt;
    let kind = meta.file_type();
    if kind.is_fifo() {
        Some("a named pipe (FIFO), not a file: zrak reads only regular files")
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
/// broken link deserves its own words. The error says which, and shows
/// as the description ("not found", "a folder, not a file", …).
pub fn check_regular_file(path: &Path) -> Result<(), Unreadable> {
    match std::fs::metadata(path) {
        Ok(meta) if meta.is_file() => Ok(()),
        Ok(_) => Err(unreadable(
            path,
            &std::io::Error::other("not a regular file"),
        )),
        Err(e) => Err(unreadable(path, &e)),
    }
}

/// Opens `path` for reading only if it is a regular file, and returns it
/// with its length. The file is opened without blocking, so a named pipe
/// answers at once instead of waiting forever for a writer, and checked on
/// the open descriptor, so a file swapped for something else between a
/// check and the open is still caught. The error is the description ("not
/// found", "a named pipe (FIFO), not a file", …), as
/// [`check_regular_file`]'s.
pub fn open_regular(path: &Path) -> Result<(File, u64), Unreadable> {
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path).map_err(|e| unreadable(path, &e))?;
    let meta = file.metadata().map_err(|e| unreadable(path, &e))?;
    if !meta.is_file() {
        return Err(unreadable(
            path,
            &std::io::Error::other("not a regular file"),
        ));
    }
    Ok((file, meta.len()))
}

/// Reads the whole of a regular file of at most `max_bytes`, refusing
/// anything else before reading a byte: a named pipe, a device such as
/// `/dev/zero` (which would be read until memory runs out), a folder, and a
/// file larger than `what` can honestly be. The error is a description to
/// follow the path ("a named pipe …", "2.1 GB, more than the 64.0 MB a
/// camera path can be").
pub fn read_regular_bounded(path: &Path, max_bytes: u64, what: &str) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let (file, length) = open_regular(path).map_err(|e| e.to_string())?;
    if length > max_bytes {
        return Err(format!(
            "{}, more than the {} {what} can be",
            human_bytes(length),
            human_bytes(max_bytes)
        ));
    }
    let mut bytes = Vec::with_capacity(length as usize);
    // The length is read again through the bound: a file that grows while
    // it is read stops at the bound plus one byte, and is refused.
    file.take(max_bytes + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("cannot read it: {e}"))?;
    if bytes.len() as u64 > max_bytes {
        return Err(format!(
            "it grew past the {} {what} can be while it was read",
            human_bytes(max_bytes)
        ));
    }
    Ok(bytes)
}

/// The first `max_bytes` of a regular file (all of it when shorter),
/// refusing what [`open_regular`] refuses: for headers of files that may
/// be large (a photograph's EXIF).
pub fn read_regular_prefix(path: &Path, max_bytes: u64) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let (file, length) = open_regular(path).map_err(|e| e.to_string())?;
    let mut bytes = Vec::with_capacity(length.min(max_bytes) as usize);
    file.take(max_bytes)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("cannot read it: {e}"))?;
    Ok(bytes)
}

/// [`read_regular_bounded`] for UTF-8 text.
pub fn read_text_bounded(path: &Path, max_bytes: u64, what: &str) -> Result<String, String> {
    String::from_utf8(read_regular_bounded(path, max_bytes, what)?).map_err(|e| {
        format!(
            "not UTF-8 text (byte {} is not)",
            e.utf8_error().valid_up_to()
        )
    })
}

/// Opens `path` for writing with `options` without following a symbolic
/// link in its last component, and only if what it opens is a regular
/// file. A link there (a run folder downloaded or left in a shared `/tmp`
/// can point its lock or its log at a user's own files) is refused, not
/// written through; so is a named pipe, which would otherwise block. The
/// error names the path and what is there.
pub fn open_for_writing_no_follow(
    path: &Path,
    options: &mut std::fs::OpenOptions,
) -> Result<File, String> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK);
    }
    let refuse_link = || {
        format!(
            "{}: a symbolic link, which zrak does not write through (it could point at \
             any file); remove it and run again",
            path.display()
        )
    };
    // Checked by name first where the system has no O_NOFOLLOW; on Unix
    // the open itself refuses, and this only words the refusal.
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_symlink()) {
        return Err(refuse_link());
    }
    let file = options.open(path).map_err(|e| {
        if is_link_loop(&e) {
            refuse_link()
        } else if std::fs::symlink_metadata(path).is_ok_and(|m| !m.is_file()) {
            format!(
                "{}: cannot write it: it is {}",
                path.display(),
                describe_unreadable(path, &e)
            )
        } else {
            format!("{}: cannot open it for writing: {e}", path.display())
        }
    })?;
    match file.metadata() {
        Ok(meta) if meta.is_file() => Ok(file),
        Ok(_) => Err(format!(
            "{}: cannot write it: it is {}",
            path.display(),
            describe_unreadable(path, &std::io::Error::other("not a regular file"))
        )),
        Err(e) => Err(format!(
            "{}: cannot open it for writing: {e}",
            path.display()
        )),
    }
}

/// Why `path` is not a folder, for a path that was expected to be one.
pub fn describe_not_a_folder(path: &Path) -> String {
    match std::fs::metadata(path) {
        Ok(meta) if meta.is_dir() => "a folder".into(),
        Ok(meta) if meta.is_file() => "not a folder (it is a file)".into(),
        Ok(_) => describe_unreadable(path, &std::io::Error::other("not a folder")),
        Err(e) => match unreadable(path, &e) {
            Unreadable::NotFound => "folder not found".into(),
            problem => problem.to_string(),
        },
    }
}

/// Whether anything (even a dangling link) exists at `path`.
pub fn exists_at_all(path: &Path) -> bool {
    std::fs::symlink_metadata(path).is_ok()
}

/// Memory in bytes this process can still allocate, or `None` where that
/// is unknown: the least of what the machine has free for new allocations
/// (`MemAvailable`), what the process's control group still allows
/// (cgroup v2 `memory.max`, v1 `memory.limit_in_bytes`, less what the group
/// uses) and what its address-space limit (`ulimit -v`) leaves above the
/// address space it already maps. A container or a shell limit is as real
/// as the machine's RAM: an allocation beyond it aborts the process too.
pub fn available_memory() -> Option<u64> {
    [
        machine_available_memory(),
        cgroup_available_memory(),
        address_space_left(),
    ]
    .into_iter()
    .flatten()
    .min()
}

fn machine_available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    kib_field(&text, "MemAvailable:")
}

/// A `NAME: N kB` line's value in bytes, from `/proc` text.
fn kib_field(text: &str, name: &str) -> Option<u64> {
    let line = text.lines().find(|l| l.starts_with(name))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// What the process's memory control group still allows, if it sets a
/// limit.
fn cgroup_available_memory() -> Option<u64> {
    let groups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let read_number =
        |path: PathBuf| -> Option<u64> { std::fs::read_to_string(path).ok()?.trim().parse().ok() };
    let mut least: Option<u64> = None;
    for line in groups.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(group)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let relative = group.trim_start_matches('/');
        let (limit, usage) = if controllers.is_empty() {
            let dir = Path::new("/sys/fs/cgroup").join(relative);
            (dir.join("memory.max"), dir.join("memory.current"))
        } else if controllers.split(',').any(|c| c == "memory") {
            let dir = Path::new("/sys/fs/cgroup/memory").join(relative);
            (
                dir.join("memory.limit_in_bytes"),
                dir.join("memory.usage_in_bytes"),
            )
        } else {
            continue;
        };
        // "max" (v2) does not parse, and v1 writes its "no limit" as a
        // number near 2^63: neither is a limit.
        let Some(limit) = read_number(limit).filter(|&l| l < 1 << 60) else {
            continue;
        };
        let left = limit.saturating_sub(read_number(usage).unwrap_or(0));
        least = Some(least.map_or(left, |l| l.min(left)));
    }
    least
}

/// What `ulimit -v` (`RLIMIT_AS`) leaves above the address space the
/// process already maps.
fn address_space_left() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes one rlimit into the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } != 0
            || limit.rlim_cur == libc::RLIM_INFINITY
        {
            return None;
        }
        let status = std::fs::read_to_string("/proc/self/status").ok()?;
        let mapped = kib_field(&status, "VmSize:").unwrap_or(0);
        Some(limit.rlim_cur.saturating_sub(mapped))
    }
    #[cfg(not(unix))]
    {
        None
    }
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
    fn make_fifo(path: &Path) {
        let name = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
    }

    #[cfg(unix)]
    #[test]
    fn bounded_reads_refuse_pipes_devices_and_large_files_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let fifo = d.join("run.json");
        make_fifo(&fifo);
        let started = std::time::Instant::now();
        let error = read_regular_bounded(&fifo, 1 << 20, "a run's settings").unwrap_err();
        assert!(error.contains("named pipe"), "{error}");
        // Refused at once: a blocking open would wait for a writer forever.
        assert!(started.elapsed() < std::time::Duration::from_secs(1));
        let zero = d.join("zero");
        std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
        let error = read_regular_bounded(&zero, 1 << 20, "a run's settings").unwrap_err();
        assert!(error.contains("a device"), "{error}");
        let big = d.join("big");
        std::fs::write(&big, vec![b' '; 2001]).unwrap();
        let error = read_regular_bounded(&big, 2000, "a run's settings").unwrap_err();
        assert_eq!(
            error,
            "2.0 kB, more than the 2.0 kB a run's settings can be"
        );
        std::fs::write(&big, b"{}").unwrap();
        assert_eq!(read_text_bounded(&big, 2000, "x").unwrap(), "{}");
    }

    #[cfg(unix)]
    #[test]
    fn writing_refuses_links_and_pipes_and_leaves_their_targets_alone() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let target = d.join("bashrc");
        std::fs::write(&target, "user's own").unwrap();
        let link = d.join(".zrak.lock");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create(true).truncate(true);
        let error = open_for_writing_no_follow(&link, &mut options).unwrap_err();
        assert!(error.contains("symbolic link"), "{error}");
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "user's own");
        let fifo = d.join("metrics.jsonl");
        make_fifo(&fifo);
        let mut options = std::fs::OpenOptions::new();
        options.append(true).create(true);
        let error = open_for_writing_no_follow(&fifo, &mut options).unwrap_err();
        assert!(error.contains("named pipe"), "{error}");
        let plain = d.join("plain");
        let mut options = std::fs::OpenOptions::new();
        options.append(true).create(true);
        let mut file = open_for_writing_no_follow(&plain, &mut options).unwrap();
        file.write_all(b"ok").unwrap();
        assert_eq!(std::fs::read_to_string(&plain).unwrap(), "ok");
    }

    #[test]
    fn available_memory_is_at_most_what_the_machine_has_free() {
        if let (Some(all), Some(ours)) = (machine_available_memory(), available_memory()) {
            assert!(ours <= all);
        }
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
        // By kind, for the callers that decide on it.
        assert_eq!(unreadable(&d.join("none"), &error), Unreadable::NotFound);
        assert!(matches!(
            unreadable(&d.join("dangling"), &error),
            Unreadable::Link(_)
        ));
        assert!(matches!(
            unreadable(&d.join("loop"), &error),
            Unreadable::Link(_)
        ));
        assert!(matches!(unreadable(d, &error), Unreadable::Other(_)));
        let fifo = d.join("fifo");
        let name = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
        assert!(describe_unreadable(&fifo, &error).contains("named pipe"));
    }
}
