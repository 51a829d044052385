//! Ctrl-C (SIGINT) and SIGTERM for the long commands, and closed pipes.
//!
//! The first interrupt asks the work to stop at its next safe point (after
//! the current training step, turntable frame or evaluated view), so a run
//! keeps everything it has trained; a second one ends the process at once,
//! for when that point is too far away. The viewer closes its window on the
//! first, as its close button does, and so keeps what it has trained.

use std::io::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

/// The exit status of a command stopped by an interrupt: 128 + SIGINT, what
/// shells report for a program ended by Ctrl-C, so scripts can tell an
/// interrupted run (its checkpoint is complete) from a finished (0) or a
/// failed one (1, 2 for usage errors).
pub const EXIT_STATUS: u8 = 130;

static REQUESTED: AtomicBool = AtomicBool::new(false);

type Wake = Box<dyn Fn() + Send>;

/// What the first interrupt calls besides setting the flag, for work that
/// sleeps until woken rather than polling [`requested`] (the viewer's
/// window waits for events).
static WAKE: Mutex<Option<Wake>> = Mutex::new(None);

/// Installs the handler for SIGINT, SIGTERM and SIGHUP. `what_happens`
/// finishes the sentence "interrupted: …" printed on the first one.
pub fn install(what_happens: &'static str) -> Result<(), String> {
    ctrlc::set_handler(move || {
        if REQUESTED.swap(true, Ordering::SeqCst) {
            note("\ninterrupted again: stopping at once");
            std::process::exit(EXIT_STATUS.into());
        }
        note(&format!(
            "\ninterrupted: {what_happens} (interrupt again to stop at once)"
        ));
        if let Ok(wake) = WAKE.lock()
            && let Some(wake) = wake.as_ref()
        {
            wake();
        }
    })
    .map_err(|e| format!("cannot install the interrupt handler: {e}"))
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

/// A line on standard output; a reader that went away is not an error
/// worth stopping (or panicking) for.
pub fn say(line: &str) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{line}").and_then(|()| out.flush());
}

/// A line on standard error, ignoring a closed or full stream.
pub fn note(line: &str) {
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}
