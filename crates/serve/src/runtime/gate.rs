//! A gate in front of the workers that tests close to hold jobs in the queue (load shedding,
//! cancelled jobs, drain). Without the `test-hooks` feature it has no state and never closes.

#[cfg(feature = "test-hooks")]
use std::sync::atomic::{AtomicBool, Ordering};
#[cfg(feature = "test-hooks")]
use std::sync::{Arc, Condvar, Mutex};

#[cfg(feature = "test-hooks")]
static START_CLOSED: AtomicBool = AtomicBool::new(false);

/// Runtimes started from now on hold their workers before warm-up until paused and resumed
/// (`drop(runtime.pause())`): lets a test see a server that is not ready yet. Process-wide, so a
/// test that uses it runs in a test binary of its own.
#[cfg(feature = "test-hooks")]
pub fn hold_warm_up(hold: bool) {
    START_CLOSED.store(hold, Ordering::SeqCst);
}

/// Whether workers may take jobs (and, when held, warm up). Without the hooks it is empty.
#[cfg_attr(not(feature = "test-hooks"), derive(Default))]
pub struct Gate {
    #[cfg(feature = "test-hooks")]
    paused: Mutex<bool>,
    #[cfg(feature = "test-hooks")]
    resumed: Condvar,
}

#[cfg(feature = "test-hooks")]
impl Default for Gate {
    fn default() -> Gate {
        Gate { paused: Mutex::new(START_CLOSED.load(Ordering::SeqCst)), resumed: Condvar::new() }
    }
}

impl Gate {
    /// Blocks while the gate is closed.
    pub fn wait_open(&self) {
        #[cfg(feature = "test-hooks")]
        {
            let mut paused = self.paused.lock().unwrap_or_else(|p| p.into_inner());
            while *paused {
                paused = self.resumed.wait(paused).unwrap_or_else(|p| p.into_inner());
            }
        }
    }

    /// Opens the gate (shutdown must never wait on it).
    pub fn open(&self) {
        #[cfg(feature = "test-hooks")]
        self.set(false);
    }

    #[cfg(feature = "test-hooks")]
    fn set(&self, value: bool) {
        *self.paused.lock().unwrap_or_else(|p| p.into_inner()) = value;
        self.resumed.notify_all();
    }
}

/// Holds the workers paused until dropped.
#[cfg(feature = "test-hooks")]
pub struct PauseGuard {
    gate: Arc<Gate>,
}

#[cfg(feature = "test-hooks")]
impl PauseGuard {
    pub(super) fn new(gate: &Arc<Gate>) -> PauseGuard {
        gate.set(true);
        PauseGuard { gate: gate.clone() }
    }
}

#[cfg(feature = "test-hooks")]
impl Drop for PauseGuard {
    fn drop(&mut self) {
        self.gate.set(false);
    }
}
