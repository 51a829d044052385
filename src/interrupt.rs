//! Ctrl-C (SIGINT), SIGTERM and SIGHUP for the long commands, and closed
//! pipes.
//!
//! The first interrupt asks the work to stop at its next safe point (after
//! the current training step, turntable frame or evaluated view), so a run
//! keeps everything it has trained; a second one ends the process at once,
//! for when that point is too far away. The viewer closes its window on the
//! first, as its close button does, and so keeps what it has trained.
//!
//! Signals as users send them:
//!
//! - A second signal counts only as a new request: one that comes at
//!   least [`GRACE`] after the first. GNU `timeout` sends its signal to
//!   the child and then to the child's whole process group, so two arrive
//!   together; a shell's Ctrl-C reaches every process of the foreground
//!   group at once, too. Neither is a user asking twice.
//! - A signal the process inherited as ignored stays ignored: `nohup`
//!   ignores SIGHUP so that a closing terminal does not end the run, and a
//!   shell without job control starts background jobs (`cmd &`) with
//!   SIGINT ignored.
//!
//! The handler itself only writes the signal's number into a pipe (about
//! all a signal handler may safely do); a thread reads it and does the
//! rest.

use std::io::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The exit status of a command stopped by an interrupt: 128 + SIGINT, what
/// shells report for a program ended by Ctrl-C, so scripts can tell an
/// interrupted run (its checkpoint is complete) from a finished (0) or a
/// failed one (1, 2 for usage errors).
pub const EXIT_STATUS: u8 = 130;

/// How long after the first interrupt a second one is taken as the same
/// request (and ignored) rather than a new one.
pub const GRACE: Duration = Duration::from_secs(1);

static REQUESTED: AtomicBool = AtomicBool::new(false);

/// When the first interrupt came.
static FIRST: Mutex<Option<Instant>> = Mutex::new(None);

type Wake = Box<dyn Fn() + Send>;

/// What the first interrupt calls besides setting the flag, for work that
/// sleeps until woken rather than polling [`requested`] (the viewer's
/// window waits for events).
static WAKE: Mutex<Option<Wake>> = Mutex::new(None);

/// Installs the handler for SIGINT, SIGTERM and SIGHUP (each one not
/// inherited as ignored; Ctrl-C and closing the console on Windows).
/// `what_happens` finishes the sentence "interrupted: …" printed on the
/// first one.
pub fn install(what_happens: &'static str) -> Result<(), String> {
    #[cfg(unix)]
    {
        signals::install(what_happens)
    }
    #[cfg(not(unix))]
    {
        ctrlc::set_handler(move || on_interrupt(what_happens))
            .map_err(|e| format!("cannot install the interrupt handler: {e}"))
    }
}

/// What an interrupt does, outside any signal handler: the first asks the
/// work to stop; one within [`GRACE`] of it is the same request; a later
/// one ends the process.
fn on_interrupt(what_happens: &str) {
    let first = FIRST.lock().map(|mut first| {
        let at = *first;
        first.get_or_insert_with(Instant::now);
        at
    });
    match first {
        Ok(None) => {
            REQUESTED.store(true, Ordering::SeqCst);
            note(&format!(
                "\ninterrupted: {what_happens} (interrupt again to stop at once)"
            ));
            if let Ok(wake) = WAKE.lock()
                && let Some(wake) = wake.as_ref()
            {
                wake();
            }
        }
        // The same request delivered twice (see the module notes).
        Ok(Some(at)) if at.elapsed() < GRACE => {}
        _ => {
            note("\ninterrupted again: stopping at once");
            std::process::exit(EXIT_STATUS.into());
        }
    }
}

/// The unix signal handling: a handler that only writes the signal's
/// number into a pipe, and a thread that reads it and calls
/// [`on_interrupt`].
#[cfg(unix)]
mod signals {
    use std::sync::atomic::{AtomicI32, Ordering};

    /// The pipe's write end, for the signal handler (-1 until installed).
    static SIGNAL_PIPE: AtomicI32 = AtomicI32::new(-1);

    /// The signals that ask zrak to stop.
    const SIGNALS: [libc::c_int; 3] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP];

    extern "C" fn on_signal(signal: libc::c_int) {
        let fd = SIGNAL_PIPE.load(Ordering::Relaxed);
        if fd >= 0 {
            let byte = signal as u8;
            // SAFETY: write(2) is async-signal-safe; the byte outlives the
            // call. A full pipe (signals faster than the thread reads) drops
            // the byte, which is fine: enough are queued to act on. (That
            // failure sets errno, which the interrupted code does not read
            // across a signal it cannot see.)
            unsafe {
                libc::write(fd, (&byte as *const u8).cast(), 1);
            }
        }
    }

    /// Whether `signal`'s disposition is "ignore", as inherited from the
    /// parent (`nohup`, background jobs of a non-interactive shell).
    fn is_ignored(signal: libc::c_int) -> Result<bool, String> {
        // SAFETY: a zeroed sigaction is a valid out-parameter; no handler is
        // installed by this query.
        unsafe {
            let mut current: libc::sigaction = std::mem::zeroed();
            if libc::sigaction(signal, std::ptr::null(), &mut current) != 0 {
                return Err(format!(
                    "cannot read the signal disposition: {}",
                    std::io::Error::last_os_error()
                ));
            }
            Ok(current.sa_sigaction == libc::SIG_IGN)
        }
    }

    /// Sets `flags` on a descriptor this module owns.
    fn set_flags(fd: libc::c_int, get: libc::c_int, set: libc::c_int, flags: libc::c_int) {
        // SAFETY: fcntl on a descriptor from pipe(2), with no pointers.
        unsafe {
            let current = libc::fcntl(fd, get);
            libc::fcntl(fd, set, current | flags);
        }
    }

    pub fn install(what_happens: &'static str) -> Result<(), String> {
        let fail = |what: &str| {
            format!(
                "cannot install the interrupt handler: {what}: {}",
                std::io::Error::last_os_error()
            )
        };
        let mut fds = [0 as libc::c_int; 2];
        // SAFETY: pipe writes two descriptors into the array it is given.
        if unsafe { libc::pipe(fds.as_mut_ptr()) } != 0 {
            return Err(fail("pipe"));
        }
        let [read_end, write_end] = fds;
        for fd in fds {
            set_flags(fd, libc::F_GETFD, libc::F_SETFD, libc::FD_CLOEXEC);
        }
        // The handler must never block; the thread sleeps on its end until
        // a signal comes.
        set_flags(write_end, libc::F_GETFL, libc::F_SETFL, libc::O_NONBLOCK);
        if SIGNAL_PIPE
            .compare_exchange(-1, write_end, Ordering::SeqCst, Ordering::SeqCst)
            .is_err()
        {
            return Err("the interrupt handler is already installed".into());
        }
        std::thread::Builder::new()
            .name("zrak-signals".into())
            .spawn(move || watch(read_end, what_happens))
            .map_err(|e| format!("cannot install the interrupt handler: {e}"))?;
        for signal in SIGNALS {
            if is_ignored(signal)? {
                continue;
            }
            // SAFETY: the handler only calls write(2), which is
            // async-signal-safe; the sigaction struct is fully initialised.
            unsafe {
                let mut action: libc::sigaction = std::mem::zeroed();
                action.sa_sigaction = on_signal as *const () as libc::sighandler_t;
                action.sa_flags = libc::SA_RESTART;
                libc::sigemptyset(&mut action.sa_mask);
                if libc::sigaction(signal, &action, std::ptr::null_mut()) != 0 {
                    return Err(fail("sigaction"));
                }
            }
        }
        Ok(())
    }

    /// The thread that acts on signals read from the pipe.
    fn watch(read_end: libc::c_int, what_happens: &'static str) {
        loop {
            let mut byte = 0u8;
            // SAFETY: reads one byte into a local.
            let read = unsafe { libc::read(read_end, (&mut byte as *mut u8).cast(), 1) };
            match read {
                1 => super::on_interrupt(what_happens),
                n if n < 0
                    && std::io::Error::last_os_error().kind()
                        == std::io::ErrorKind::Interrupted => {}
                _ => return,
            }
        }
    }
}

/// Has `wake` called on the first interrupt, after [`requested`] turns
/// true, replacing any earlier one. (An interrupt that came before is seen
/// by polling [`requested`].)
pub fn on_request(wake: impl Fn() + Send + 'static) {
    if let Ok(mut slot) = WAKE.lock() {
        *slot = Some(Box::new(wake));
    }
}

/// The flag the handler sets, for loops that poll it.
pub fn flag() -> &'static AtomicBool {
    &REQUESTED
}

/// Whether an interrupt has arrived.
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}

/// Makes writing to a closed pipe end the process quietly, as it does for
/// other command-line tools (`zrak info SCENE | head -1`). Rust ignores
/// SIGPIPE, so a write fails instead and `println!` panics with a message.
/// Not for commands that must save their work first (training): those keep
/// SIGPIPE ignored and print with [`say`] and [`note`].
pub fn end_quietly_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: `signal` with SIG_DFL installs no Rust code as a handler; it is
    // called at start-up, before any thread that might write is spawned.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// The first error writing to standard output (other than a closed pipe),
/// kept so the command can end with it instead of a panic.
static STDOUT_ERROR: Mutex<Option<String>> = Mutex::new(None);

/// Prints a line on standard output without ever panicking: `println!`
/// panics when the write fails (`zrak info SCENE > /dev/full`). A closed
/// pipe is ignored (the reader went away, as with [`say`]); any other
/// error is kept for [`stdout_error`], and the command goes on to save
/// what it must.
pub fn print_line(args: std::fmt::Arguments) {
    let mut out = std::io::stdout().lock();
    if let Err(error) = out.write_fmt(args).and_then(|()| out.write_all(b"\n")) {
        remember_stdout_error(error);
    }
}

fn remember_stdout_error(error: std::io::Error) {
    if error.kind() == std::io::ErrorKind::BrokenPipe {
        return;
    }
    if let Ok(mut slot) = STDOUT_ERROR.lock()
        && slot.is_none()
    {
        *slot = Some(error.to_string());
    }
}

/// Flushes standard output and returns the first error any write to it
/// met, as "cannot write to standard output: …".
pub fn stdout_error() -> Option<String> {
    if let Err(error) = std::io::stdout().lock().flush() {
        remember_stdout_error(error);
    }
    let slot = STDOUT_ERROR.lock().ok()?;
    slot.as_ref()
        .map(|e| format!("cannot write to standard output: {e}"))
}

/// A line on standard output; a reader that went away is not an error
/// worth stopping (or panicking) for. Another failure (a full disk) is
/// kept for [`stdout_error`], which the command ends with once its work is
/// saved.
pub fn say(line: &str) {
    let mut out = std::io::stdout().lock();
    if let Err(error) = writeln!(out, "{line}").and_then(|()| out.flush()) {
        remember_stdout_error(error);
    }
}

/// A line on standard error, ignoring a closed or full stream.
pub fn note(line: &str) {
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}
