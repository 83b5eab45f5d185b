//! A termination request (SIGTERM or SIGINT) that no later signal can erase.
//!
//! iceoryx2 keeps only the *last* signal a process received, and reading it clears it. A
//! SIGCONT that lands after the SIGTERM (the supervisor sends both when it stops a child, in
//! case the child was stopped; systemd does the same; the kernel delivers a pending SIGTERM
//! before a pending SIGCONT) overwrites the request, and a later `Node::wait` or WaitSet sees
//! nothing: the service ran on until it was SIGKILLed, with its recording unflushed. Its
//! shared-memory code also clears the slot around `memset`. So the kit keeps its own flag:
//! a handler on SIGTERM and SIGINT sets it and then calls iceoryx2's own handler, which keeps
//! interrupting waits as before.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Once;

use iceoryx2_bb_posix::signal::SignalHandler;
use nix::libc::c_int;
use nix::sys::signal::{sigaction, SigAction, SigHandler, SigSet, Signal};

static REQUESTED: AtomicBool = AtomicBool::new(false);
static WATCHING: AtomicBool = AtomicBool::new(false);
static INSTALL: Once = Once::new();
/// iceoryx2's handlers for SIGTERM and SIGINT (function addresses; 0 when there was none).
static PREVIOUS_TERM: AtomicUsize = AtomicUsize::new(0);
static PREVIOUS_INT: AtomicUsize = AtomicUsize::new(0);

extern "C" fn on_termination(signal: c_int) {
    // Only atomics and a call of the previous handler: async-signal-safe.
    REQUESTED.store(true, Ordering::SeqCst);
    let previous = if signal == Signal::SIGTERM as c_int {
        PREVIOUS_TERM.load(Ordering::SeqCst)
    } else {
        PREVIOUS_INT.load(Ordering::SeqCst)
    };
    if previous != 0 {
        // SAFETY: `previous` was stored from a `SigHandler::Handler`, an `extern "C" fn(c_int)`.
        let handler: extern "C" fn(c_int) = unsafe { std::mem::transmute(previous) };
        handler(signal);
    }
}

/// Installs the flag's handler once per process (every port and loop of the kit calls it, so a
/// service needs nothing of its own). iceoryx2's own handlers are installed first, so that it
/// cannot replace this one later; a request it had already recorded is kept.
pub fn watch() {
    INSTALL.call_once(|| {
        if SignalHandler::termination_requested() {
            REQUESTED.store(true, Ordering::SeqCst);
        }
        let mut installed = true;
        for (signal, previous) in [
            (Signal::SIGTERM, &PREVIOUS_TERM),
            (Signal::SIGINT, &PREVIOUS_INT),
        ] {
            // No SA_RESTART: a blocking wait still ends with EINTR on the signal.
            let action = SigAction::new(
                SigHandler::Handler(on_termination),
                nix::sys::signal::SaFlags::empty(),
                SigSet::empty(),
            );
            // SAFETY: the handler is async-signal-safe (see `on_termination`).
            match unsafe { sigaction(signal, &action) } {
                Ok(old) => {
                    if let SigHandler::Handler(handler) = old.handler() {
                        previous.store(handler as usize, Ordering::SeqCst);
                    }
                }
                Err(error) => {
                    installed = false;
                    tracing::warn!(
                        "termination handler for {signal} not installed ({error}); \
                         a SIGCONT after SIGTERM may be missed"
                    );
                }
            }
        }
        WATCHING.store(installed, Ordering::SeqCst);
    });
}

/// True once SIGTERM or SIGINT has arrived (and stays true).
pub fn requested() -> bool {
    REQUESTED.load(Ordering::SeqCst)
}

/// Records a termination request that reached the process another way (iceoryx2 reported it).
pub fn mark_requested() {
    REQUESTED.store(true, Ordering::SeqCst);
}

/// Whether a WaitSet's result ends a loop: a termination request, or a wait interrupted by
/// SIGTERM / SIGINT (and not by another signal; see `interrupted_by_termination`).
pub fn waitset_says_stop(result: &iceoryx2::waitset::WaitSetRunResult) -> bool {
    use iceoryx2::waitset::WaitSetRunResult;
    match result {
        WaitSetRunResult::TerminationRequest => true,
        WaitSetRunResult::Interrupt => interrupted_by_termination(),
        _ => requested(),
    }
}

/// Whether a wait that a signal interrupted (EINTR) should end the service: yes for SIGTERM or
/// SIGINT; no for any other signal (SIGCONT, SIGUSR1, ...) once the flag is watched. Without
/// the flag's handler any interruption counts, as iceoryx2 itself treats it.
pub fn interrupted_by_termination() -> bool {
    !WATCHING.load(Ordering::SeqCst) || requested()
}
