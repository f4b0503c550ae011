//! `nephele-shutdown`: the one shutdown object of every Nephele process (master, worker,
//! composer, `nephele up`).
//!
//! A [`Shutdown`] is a cheap, cloneable handle on one flag. [`Shutdown::trigger`] sets it
//! (tests, a service stopping its own tasks); [`Shutdown::on_signals`] also sets it on Ctrl-C
//! (SIGINT) or SIGTERM, and a second signal exits the process at once (status 130) for when
//! a graceful stop hangs. Async tasks `select!` on [`Shutdown::wait`]; synchronous loops poll
//! [`Shutdown::is_triggered`].
//!
//! Depends on no crate of ours; signals are read on a thread of their own through
//! signal-hook's safe iterator, so no async runtime is needed to notice them.

use std::sync::Arc;

use tokio::sync::watch;

/// A shutdown request: set once, seen by every clone.
#[derive(Debug, Clone)]
pub struct Shutdown {
    requested: Arc<watch::Sender<bool>>,
}

impl Default for Shutdown {
    fn default() -> Self {
        Shutdown::new()
    }
}

impl Shutdown {
    /// A flag that only [`Shutdown::trigger`] sets.
    pub fn new() -> Shutdown {
        Shutdown { requested: Arc::new(watch::Sender::new(false)) }
    }

    /// A flag that SIGINT (Ctrl-C) and SIGTERM set too; a second signal exits the process
    /// with status 130.
    pub fn on_signals() -> std::io::Result<Shutdown> {
        use signal_hook::consts::{SIGINT, SIGTERM};
        let shutdown = Shutdown::new();
        let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM])?;
        let handle = shutdown.clone();
        std::thread::Builder::new().name("signals".into()).spawn(move || {
            let mut seen = 0;
            for signal in signals.forever() {
                seen += 1;
                let name = if signal == SIGTERM { "SIGTERM" } else { "Ctrl-C" };
                if seen == 1 {
                    tracing::info!("{name} received: stopping");
                    handle.trigger();
                } else {
                    tracing::warn!("second signal ({name}): exiting now");
                    std::process::exit(130);
                }
            }
        })?;
        Ok(shutdown)
    }

    /// Requests the shutdown (idempotent).
    pub fn trigger(&self) {
        self.requested.send_replace(true);
    }

    pub fn is_triggered(&self) -> bool {
        *self.requested.borrow()
    }

    /// Resolves once the shutdown is requested (at once if it already is). Cancel-safe: use
    /// it as a `select!` branch as often as needed.
    pub async fn wait(&self) {
        let mut seen = self.requested.subscribe();
        // The sender lives as long as `self`: `wait_for` cannot fail here.
        let _ = seen.wait_for(|requested| *requested).await;
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use super::*;

    #[tokio::test]
    async fn every_clone_sees_one_trigger_and_waiters_wake() {
        let shutdown = Shutdown::new();
        let clone = shutdown.clone();
        assert!(!clone.is_triggered());
        let waiter = tokio::spawn(async move { clone.wait().await });
        tokio::time::sleep(Duration::from_millis(20)).await;
        assert!(!waiter.is_finished());
        shutdown.trigger();
        tokio::time::timeout(Duration::from_secs(5), waiter).await.expect("woken").expect("joined");
        assert!(shutdown.is_triggered());
        // Already triggered: waiting returns at once, triggering again changes nothing.
        shutdown.trigger();
        tokio::time::timeout(Duration::from_secs(1), shutdown.wait()).await.expect("immediate");
    }

    #[tokio::test]
    async fn a_waiter_that_is_dropped_does_not_disturb_the_others() {
        let shutdown = Shutdown::new();
        let other = shutdown.clone();
        tokio::select! {
            _ = shutdown.wait() => panic!("not triggered"),
            _ = tokio::time::sleep(Duration::from_millis(10)) => {}
        }
        other.trigger();
        tokio::time::timeout(Duration::from_secs(1), shutdown.wait()).await.expect("woken");
    }
}
