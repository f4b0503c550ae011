//! Child-process supervision for `nephele up`: start the service's processes, watch them,
//! and stop them all cleanly (SIGTERM, then SIGKILL after a grace period) on Ctrl-C, on
//! SIGTERM, or when any of them exits.

use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use nephele_shutdown::Shutdown;
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

/// One supervised process.
#[derive(Debug)]
pub struct Supervised {
    pub name: String,
    child: Child,
}

/// A set of processes that live and die together.
#[derive(Debug, Default)]
pub struct Supervisor {
    children: Vec<Supervised>,
}

impl Supervisor {
    pub fn new() -> Supervisor {
        Supervisor::default()
    }

    /// Starts `command` (stdin closed, stdout/stderr inherited so that logs reach the
    /// terminal).
    pub fn spawn(&mut self, name: &str, mut command: Command) -> Result<()> {
        command.stdin(Stdio::null());
        let child = command.spawn().with_context(|| format!("starting {name}"))?;
        tracing::info!(process = name, pid = child.id(), "started");
        self.children.push(Supervised { name: name.to_owned(), child });
        Ok(())
    }

    /// The first child that has exited, if any, with its status.
    pub fn exited(&mut self) -> Result<Option<(String, ExitStatus)>> {
        for supervised in &mut self.children {
            if let Some(status) =
                supervised.child.try_wait().with_context(|| format!("waiting for {}", supervised.name))?
            {
                return Ok(Some((supervised.name.clone(), status)));
            }
        }
        Ok(None)
    }

    /// Blocks until `stop` is set (Ctrl-C) or a child exits; returns the child that exited.
    pub fn watch(&mut self, stop: &Shutdown) -> Result<Option<(String, ExitStatus)>> {
        while !stop.is_triggered() {
            if let Some(exited) = self.exited()? {
                return Ok(Some(exited));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(None)
    }

    /// Stops every child still running, in reverse start order: SIGTERM, then SIGKILL for
    /// those still alive after `grace`. Returns the children that had to be killed.
    pub fn shutdown(&mut self, grace: Duration) -> Vec<String> {
        for supervised in self.children.iter_mut().rev() {
            if matches!(supervised.child.try_wait(), Ok(None))
                && let Ok(pid) = i32::try_from(supervised.child.id())
            {
                let _ = kill(Pid::from_raw(pid), Signal::SIGTERM);
            }
        }
        let deadline = Instant::now() + grace;
        let mut killed = Vec::new();
        for supervised in &mut self.children {
            loop {
                match supervised.child.try_wait() {
                    Ok(Some(status)) => {
                        tracing::info!(process = %supervised.name, %status, "stopped");
                        break;
                    }
                    Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                    _ => {
                        tracing::warn!(process = %supervised.name, "did not stop in time; killing it");
                        let _ = supervised.child.kill();
                        let _ = supervised.child.wait();
                        killed.push(supervised.name.clone());
                        break;
                    }
                }
            }
        }
        self.children.clear();
        killed
    }
}

impl Drop for Supervisor {
    fn drop(&mut self) {
        if !self.children.is_empty() {
            self.shutdown(Duration::from_secs(5));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shutdown_terminates_and_kills_stragglers() {
        let mut supervisor = Supervisor::new();
        let mut polite = Command::new("sleep");
        polite.arg("30");
        supervisor.spawn("polite", polite).expect("sleep");
        // A process that ignores SIGTERM must be killed after the grace period.
        let mut stubborn = Command::new("sh");
        stubborn.args(["-c", "trap '' TERM; sleep 30"]);
        supervisor.spawn("stubborn", stubborn).expect("sh");
        std::thread::sleep(Duration::from_millis(200));
        assert!(supervisor.exited().expect("try_wait").is_none());
        let start = Instant::now();
        let killed = supervisor.shutdown(Duration::from_millis(500));
        assert_eq!(killed, vec!["stubborn".to_string()]);
        assert!(start.elapsed() < Duration::from_secs(5));
    }

    #[test]
    fn watch_reports_a_child_that_exits() {
        let mut supervisor = Supervisor::new();
        let mut quick = Command::new("sh");
        quick.args(["-c", "exit 3"]);
        supervisor.spawn("quick", quick).expect("sh");
        let stop = Shutdown::new();
        let (name, status) = supervisor.watch(&stop).expect("watch").expect("an exit");
        assert_eq!((name.as_str(), status.code()), ("quick", Some(3)));
    }
}
