//! Ctrl-C and `kill`: a training run finishes its step, writes a checkpoint and says how to
//! resume; a second Ctrl-C ends the process at once.

use std::sync::atomic::AtomicUsize;
use std::sync::Arc;

use signal_hook::consts::{SIGINT, SIGTERM};

/// Stores the signal's number in `stop` when SIGINT or SIGTERM arrives; a second one while
/// `stop` is set exits at once (status 1).
pub fn stop_on_interrupt(stop: &Arc<AtomicUsize>) -> std::io::Result<()> {
    for signal in [SIGINT, SIGTERM] {
        let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
        // Order matters: the conditional exit is armed by the first signal's flag.
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&flag))?;
        signal_hook::flag::register(signal, flag)?;
        signal_hook::flag::register_usize(signal, Arc::clone(stop), signal as usize)?;
    }
    Ok(())
}

pub fn name(signal: usize) -> &'static str {
    match signal as i32 {
        SIGINT => "SIGINT (Ctrl-C)",
        SIGTERM => "SIGTERM",
        _ => "a signal",
    }
}

/// The shell's convention: 128 + the signal number (130 for SIGINT, 143 for SIGTERM).
pub fn exit_code(signal: usize) -> i32 {
    128 + signal as i32
}
