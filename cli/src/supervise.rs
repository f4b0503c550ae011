//! Child-process supervision for `nephele up`: start the service's processes, watch them,
//! restart the ones that may come back (render workers, the composer) with exponential
//! backoff, and stop them all cleanly (SIGTERM, then SIGKILL after a grace period) on
//! Ctrl-C, on SIGTERM, when a process that must not die (the master) exits, or when a
//! process keeps crashing (a crash loop).

use std::collections::VecDeque;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use nephele_shutdown::Shutdown;
use nix::sys::signal::{Signal, kill};
use nix::unistd::Pid;

/// What happens when a supervised process exits on its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Restart {
    /// The service cannot go on without it: everything stops.
    Never,
    /// Start it again after a backoff (it rejoins the farm by itself).
    OnExit,
}

/// Backoff and crash-loop limits of restarts.
#[derive(Debug, Clone, Copy)]
pub struct RestartPolicy {
    /// Wait before the first restart; doubled after each quick exit, up to `max_backoff`.
    pub first_backoff: Duration,
    pub max_backoff: Duration,
    /// A process that ran this long before exiting starts again from `first_backoff`.
    pub healthy_after: Duration,
    /// More than `max_restarts` restarts of one process within `window` is a crash loop.
    pub max_restarts: usize,
    pub window: Duration,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        RestartPolicy {
            first_backoff: Duration::from_millis(500),
            max_backoff: Duration::from_secs(10),
            healthy_after: Duration::from_secs(30),
            max_restarts: 5,
            window: Duration::from_secs(120),
        }
    }
}

/// One supervised process.
#[derive(Debug)]
pub struct Supervised {
    pub name: String,
    command: Command,
    restart: Restart,
    /// `None` while waiting for a restart.
    child: Option<Child>,
    started: Instant,
    /// When the pending restart is due.
    restart_at: Option<Instant>,
    backoff: Duration,
    /// Times of recent restarts (within the policy's window).
    recent: VecDeque<Instant>,
    restarts: u64,
}

/// Why [`Supervisor::watch`] returned.
#[derive(Debug)]
pub enum WatchEnd {
    /// Ctrl-C or SIGTERM.
    Stopped,
    /// A process started with [`Restart::Never`] exited.
    Exited { name: String, status: ExitStatus },
    /// A restartable process exited more than the policy allows within its window.
    CrashLoop { name: String, status: ExitStatus, restarts: usize, window: Duration },
}

/// A set of processes that live together; see the module docs.
#[derive(Debug, Default)]
pub struct Supervisor {
    children: Vec<Supervised>,
    policy: RestartPolicy,
}

/// A copy of `command` (program, arguments, environment changes and working directory;
/// standard streams are set again by [`Supervisor`]).
fn copy_command(command: &Command) -> Command {
    let mut copy = Command::new(command.get_program());
    copy.args(command.get_args());
    for (key, value) in command.get_envs() {
        match value {
            Some(value) => copy.env(key, value),
            None => copy.env_remove(key),
        };
    }
    if let Some(dir) = command.get_current_dir() {
        copy.current_dir(dir);
    }
    copy
}

impl Supervisor {
    pub fn new() -> Supervisor {
        Supervisor::default()
    }

    #[cfg(test)]
    pub fn with_policy(policy: RestartPolicy) -> Supervisor {
        Supervisor { children: Vec::new(), policy }
    }

    /// Starts `command` (stdin closed, stdout/stderr inherited so that logs reach the
    /// terminal); `restart` says what happens when it exits on its own.
    pub fn spawn(&mut self, name: &str, command: Command, restart: Restart) -> Result<()> {
        let child = start(name, &command)?;
        self.children.push(Supervised {
            name: name.to_owned(),
            command,
            restart,
            child: Some(child),
            started: Instant::now(),
            restart_at: None,
            backoff: self.policy.first_backoff,
            recent: VecDeque::new(),
            restarts: 0,
        });
        Ok(())
    }

    /// Process ids of the running children, by name.
    #[cfg(test)]
    pub fn pids(&self) -> Vec<(String, u32)> {
        self.children.iter().filter_map(|s| Some((s.name.clone(), s.child.as_ref()?.id()))).collect()
    }

    /// The processes restarted so far, with their number of restarts.
    pub fn restart_counts(&self) -> Vec<(String, u64)> {
        self.children.iter().filter(|s| s.restarts > 0).map(|s| (s.name.clone(), s.restarts)).collect()
    }

    /// The first child that has exited, if any, with its status (no restart: for the
    /// start-up phase, where any exit is a configuration error).
    pub fn exited(&mut self) -> Result<Option<(String, ExitStatus)>> {
        for supervised in &mut self.children {
            if let Some(child) = &mut supervised.child
                && let Some(status) = child.try_wait().with_context(|| format!("waiting for {}", supervised.name))?
            {
                return Ok(Some((supervised.name.clone(), status)));
            }
        }
        Ok(None)
    }

    /// One supervision step at `now`: reaps exited children, schedules or refuses their
    /// restarts, and starts the restarts that are due. `Some` when the service must stop.
    pub fn step(&mut self, now: Instant) -> Result<Option<WatchEnd>> {
        let policy = self.policy;
        for s in &mut self.children {
            let Some(child) = &mut s.child else { continue };
            let Some(status) = child.try_wait().with_context(|| format!("waiting for {}", s.name))? else { continue };
            s.child = None;
            if s.restart == Restart::Never {
                return Ok(Some(WatchEnd::Exited { name: s.name.clone(), status }));
            }
            while s.recent.front().is_some_and(|&t| now.duration_since(t) > policy.window) {
                s.recent.pop_front();
            }
            if s.recent.len() >= policy.max_restarts {
                return Ok(Some(WatchEnd::CrashLoop {
                    name: s.name.clone(),
                    status,
                    restarts: s.recent.len(),
                    window: policy.window,
                }));
            }
            if now.duration_since(s.started) >= policy.healthy_after {
                s.backoff = policy.first_backoff;
            }
            tracing::warn!(process = %s.name, %status, backoff_ms = s.backoff.as_millis() as u64, "exited; restarting it");
            s.restart_at = Some(now + s.backoff);
            s.backoff = (s.backoff * 2).min(policy.max_backoff);
        }
        for s in &mut self.children {
            if s.restart_at.is_some_and(|at| at <= now) {
                s.restart_at = None;
                s.recent.push_back(now);
                s.restarts += 1;
                s.started = now;
                s.child = Some(start(&s.name, &s.command)?);
                tracing::warn!(process = %s.name, restarts = s.restarts, "restarted");
            }
        }
        Ok(None)
    }

    /// Blocks until `stop` is set (Ctrl-C), a process that must not die exits, or a
    /// process crash-loops; restarts the others meanwhile.
    pub fn watch(&mut self, stop: &Shutdown) -> Result<WatchEnd> {
        while !stop.is_triggered() {
            if let Some(end) = self.step(Instant::now())? {
                // A Ctrl-C at a terminal reaches the children too: their exits are part of
                // stopping, not a failure.
                return Ok(if stop.is_triggered() { WatchEnd::Stopped } else { end });
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        Ok(WatchEnd::Stopped)
    }

    /// Stops every child still running, in reverse start order: SIGTERM, then SIGKILL for
    /// those still alive after `grace`. Returns the children that had to be killed.
    pub fn shutdown(&mut self, grace: Duration) -> Vec<String> {
        for supervised in self.children.iter_mut().rev() {
            if let Some(child) = &mut supervised.child
                && matches!(child.try_wait(), Ok(None))
                && let Ok(pid) = i32::try_from(child.id())
            {
                let _ = kill(Pid::from_raw(pid), Signal::SIGTERM);
            }
        }
        let deadline = Instant::now() + grace;
        let mut killed = Vec::new();
        for supervised in &mut self.children {
            let Some(child) = &mut supervised.child else { continue };
            loop {
                match child.try_wait() {
                    Ok(Some(status)) => {
                        tracing::info!(process = %supervised.name, %status, "stopped");
                        break;
                    }
                    Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(20)),
                    _ => {
                        tracing::warn!(process = %supervised.name, "did not stop in time; killing it");
                        let _ = child.kill();
                        let _ = child.wait();
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

fn start(name: &str, command: &Command) -> Result<Child> {
    let mut command = copy_command(command);
    command.stdin(Stdio::null());
    let child = command.spawn().with_context(|| format!("starting {name}"))?;
    tracing::info!(process = name, pid = child.id(), "started");
    Ok(child)
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
        supervisor.spawn("polite", polite, Restart::OnExit).expect("sleep");
        // A process that ignores SIGTERM must be killed after the grace period.
        let mut stubborn = Command::new("sh");
        stubborn.args(["-c", "trap '' TERM; sleep 30"]);
        supervisor.spawn("stubborn", stubborn, Restart::OnExit).expect("sh");
        std::thread::sleep(Duration::from_millis(200));
        assert!(supervisor.exited().expect("try_wait").is_none());
        let start = Instant::now();
        let killed = supervisor.shutdown(Duration::from_millis(500));
        assert_eq!(killed, vec!["stubborn".to_string()]);
        assert!(start.elapsed() < Duration::from_secs(5));
    }

    #[test]
    fn watch_stops_when_a_process_that_must_not_die_exits() {
        let mut supervisor = Supervisor::new();
        let mut quick = Command::new("sh");
        quick.args(["-c", "exit 3"]);
        supervisor.spawn("quick", quick, Restart::Never).expect("sh");
        let stop = Shutdown::new();
        let WatchEnd::Exited { name, status } = supervisor.watch(&stop).expect("watch") else {
            panic!("expected the exit")
        };
        assert_eq!((name.as_str(), status.code()), ("quick", Some(3)));
    }

    fn quick_policy() -> RestartPolicy {
        RestartPolicy {
            first_backoff: Duration::from_millis(20),
            max_backoff: Duration::from_millis(80),
            healthy_after: Duration::from_secs(60),
            max_restarts: 3,
            window: Duration::from_secs(60),
        }
    }

    #[test]
    fn a_killed_process_is_restarted_and_the_others_keep_running() {
        let mut supervisor = Supervisor::with_policy(quick_policy());
        let mut worker = Command::new("sleep");
        worker.arg("30");
        supervisor.spawn("worker", worker, Restart::OnExit).expect("sleep");
        let mut master = Command::new("sleep");
        master.arg("30");
        supervisor.spawn("master", master, Restart::Never).expect("sleep");
        let pids = supervisor.pids();
        let (old, master_pid) = (pids[0].1, pids[1].1);
        kill(Pid::from_raw(old as i32), Signal::SIGKILL).expect("kill -9");
        let deadline = Instant::now() + Duration::from_secs(10);
        while supervisor.restart_counts().is_empty() {
            assert!(Instant::now() < deadline, "no restart within 10 s");
            assert!(supervisor.step(Instant::now()).expect("step").is_none());
            std::thread::sleep(Duration::from_millis(10));
        }
        let pids = supervisor.pids();
        assert_eq!(pids.len(), 2);
        assert!(pids.iter().any(|(n, p)| n == "worker" && *p != old), "{pids:?}");
        assert!(pids.iter().any(|(n, p)| n == "master" && *p == master_pid), "{pids:?}");
        assert!(supervisor.shutdown(Duration::from_secs(5)).is_empty());
    }

    #[test]
    fn a_crash_loop_stops_the_service_after_backing_off() {
        let mut supervisor = Supervisor::with_policy(quick_policy());
        let mut broken = Command::new("sh");
        broken.args(["-c", "exit 7"]);
        supervisor.spawn("broken", broken, Restart::OnExit).expect("sh");
        let started = Instant::now();
        let stop = Shutdown::new();
        let WatchEnd::CrashLoop { name, status, restarts, .. } = supervisor.watch(&stop).expect("watch") else {
            panic!("expected a crash loop")
        };
        assert_eq!((name.as_str(), status.code(), restarts), ("broken", Some(7), 3));
        assert_eq!(supervisor.restart_counts(), vec![("broken".to_string(), 3)]);
        // Backoffs of 20, 40 and 80 ms came before the three restarts.
        assert!(started.elapsed() >= Duration::from_millis(140), "{:?}", started.elapsed());
    }

    #[test]
    fn a_copied_command_keeps_arguments_and_environment() {
        let mut command = Command::new("sh");
        command.args(["-c", "test \"$A\" = one && test -z \"$HOME\" && exit 5"]).env("A", "one").env_remove("HOME");
        let status = copy_command(&command).status().expect("sh");
        assert_eq!(status.code(), Some(5));
    }
}
