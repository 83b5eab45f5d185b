//! Signals that inject a fault into the emulated Teensy link, so the fault-injection suite can
//! hit the link the way it hits processes: SIGUSR1 pulls the USB cable, SIGUSR2 stalls the
//! board's firmware. The handler only records the request; the plant loop acts on it.

use std::sync::atomic::{AtomicU8, Ordering};

use nix::sys::signal::{sigaction, SaFlags, SigAction, SigHandler, SigSet, Signal};

static REQUESTED: AtomicU8 = AtomicU8::new(NONE);
const NONE: u8 = 0;
const UNPLUG: u8 = 1;
const HANG: u8 = 2;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Requested {
    Unplug,
    Hang,
}

extern "C" fn on_signal(signal: nix::libc::c_int) {
    // Only an atomic store: async-signal-safe.
    let request = if signal == Signal::SIGUSR1 as nix::libc::c_int {
        UNPLUG
    } else {
        HANG
    };
    REQUESTED.store(request, Ordering::SeqCst);
}

/// Claims SIGUSR1/SIGUSR2. Call after iceoryx2's signal handler exists (it registers every
/// catchable signal on first use and would silently take these back).
pub fn install() -> nix::Result<()> {
    let action = SigAction::new(
        SigHandler::Handler(on_signal),
        SaFlags::SA_RESTART,
        SigSet::empty(),
    );
    for signal in [Signal::SIGUSR1, Signal::SIGUSR2] {
        // SAFETY: the handler only stores to an atomic.
        unsafe { sigaction(signal, &action) }?;
    }
    Ok(())
}

/// The fault requested since the last call, if any.
pub fn take() -> Option<Requested> {
    match REQUESTED.swap(NONE, Ordering::SeqCst) {
        UNPLUG => Some(Requested::Unplug),
        HANG => Some(Requested::Hang),
        _ => None,
    }
}
