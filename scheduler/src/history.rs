//! The history table: recent results by (object, quantised camera), bounded in size and age.

use std::collections::{HashMap, VecDeque};
use std::time::Duration;

use crate::assign::CameraKey;
use crate::{ObjectId, TaskId, Time};

pub(crate) type ResultKey = (ObjectId, CameraKey);

#[derive(Debug)]
pub(crate) struct History {
    capacity: usize,
    entries: HashMap<ResultKey, (TaskId, Time)>,
    /// Insertion order (= completion order, time only moves forward); entries replaced since
    /// are skipped when they reach the front.
    order: VecDeque<(ResultKey, TaskId)>,
}

impl History {
    pub(crate) fn new(capacity: usize) -> History {
        History { capacity, entries: HashMap::new(), order: VecDeque::new() }
    }

    pub(crate) fn enabled(&self) -> bool {
        self.capacity > 0
    }

    pub(crate) fn len(&self) -> usize {
        self.entries.len()
    }

    /// The task whose results for `key` are at most `max_age` old.
    pub(crate) fn get(&self, key: &ResultKey, now: Time, max_age: Duration) -> Option<TaskId> {
        let &(task, completed) = self.entries.get(key)?;
        (now.since(completed) <= max_age).then_some(task)
    }

    /// Records `task` as the newest result for `key`; returns the tasks that left the table
    /// (the one it replaced, and the oldest when full).
    pub(crate) fn insert(&mut self, key: ResultKey, task: TaskId, now: Time) -> Vec<TaskId> {
        let mut evicted = Vec::new();
        if !self.enabled() {
            return evicted;
        }
        if let Some((old, _)) = self.entries.insert(key, (task, now)) {
            evicted.push(old);
        }
        self.order.push_back((key, task));
        while self.entries.len() > self.capacity {
            match self.pop_front() {
                Some(old) => evicted.push(old),
                None => break,
            }
        }
        if self.order.len() > 2 * self.capacity + 16 {
            let entries = &self.entries;
            self.order.retain(|(k, t)| entries.get(k).is_some_and(|(current, _)| current == t));
        }
        evicted
    }

    /// Drops entries older than `max_age`; returns their tasks.
    pub(crate) fn expire(&mut self, now: Time, max_age: Duration) -> Vec<TaskId> {
        let mut evicted = Vec::new();
        while let Some((key, task)) = self.order.front().copied() {
            match self.entries.get(&key) {
                Some(&(current, completed)) if current == task => {
                    if now.since(completed) <= max_age {
                        break;
                    }
                    self.entries.remove(&key);
                    evicted.push(task);
                }
                _ => {}
            }
            self.order.pop_front();
        }
        evicted
    }

    fn pop_front(&mut self) -> Option<TaskId> {
        while let Some((key, task)) = self.order.pop_front() {
            if self.entries.get(&key).is_some_and(|(current, _)| *current == task) {
                self.entries.remove(&key);
                return Some(task);
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ShareTolerance;
    use glam::Vec3;
    use nephele_geometry::camera::Camera;

    fn key(x: f32) -> ResultKey {
        let cam = Camera::look_at(8, 8, 1.0, Vec3::new(x, -3.0, 0.0), Vec3::ZERO, Vec3::Z).expect("camera");
        (ObjectId(1), CameraKey::new(&cam, &ShareTolerance::default()))
    }

    #[test]
    fn bounded_by_size_and_age() {
        let mut h = History::new(2);
        let t = |ms: u64| Time::from_micros(ms * 1000);
        assert!(h.insert(key(0.0), TaskId(1), t(0)).is_empty());
        assert!(h.insert(key(1.0), TaskId(2), t(1)).is_empty());
        assert_eq!(h.insert(key(2.0), TaskId(3), t(2)), vec![TaskId(1)]);
        assert_eq!(h.len(), 2);
        assert_eq!(h.get(&key(0.0), t(2), Duration::from_secs(1)), None);
        assert_eq!(h.get(&key(1.0), t(2), Duration::from_secs(1)), Some(TaskId(2)));
        // Replacing a key evicts the old result.
        assert_eq!(h.insert(key(1.0), TaskId(4), t(3)), vec![TaskId(2)]);
        assert_eq!(h.get(&key(1.0), t(600), Duration::from_millis(500)), None, "too old");
        assert_eq!(h.expire(t(503), Duration::from_millis(500)), vec![TaskId(3)]);
        assert_eq!(h.len(), 1);
        let mut off = History::new(0);
        assert!(off.insert(key(0.0), TaskId(1), t(0)).is_empty());
        assert_eq!(off.len(), 0);
    }
}
