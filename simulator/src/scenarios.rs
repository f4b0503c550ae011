//! The built-in scenarios: the hard cases of issue 4, each a small world, a farm and a crowd.
//!
//! Worker throughputs are in rays/s of a cost-1 kernel (i-NOLF renders 800x800 in 2.07 ms on
//! an RTX 4090, about 3e8 rays/s, NEPHELE table 5; the farms here are smaller so that the
//! scenarios load them). Objects with cost 5 stand for i-NGP-like kernels (96.4 vs 18.4 ms at
//! 4K, NEPHELE table 3).

use glam::Vec3;

use crate::model::{CameraPath, Detect, Scenario, SimObject, SimParams, SimUser, SimWorker, ViewMode};

/// Names and one-line descriptions of the built-in scenarios.
pub const SCENARIOS: [(&str, &str); 8] = [
    (
        "many-objects",
        "one user, 12 objects: 2 close heavy ones (one with an i-NGP-like cost 5) and 10 small light ones, 60 FPS",
    ),
    ("many-users", "24 users on one object from 6 adjacent angles (4 users at each spot), 60 FPS, 4 workers"),
    ("quilt", "four 45-view quilt displays (420x560 per view), two pairs showing the same rig, 20 FPS, 8 workers"),
    (
        "overload",
        "20 users arriving every 0.5 s at 60 FPS on a farm that holds about 9: starvation and admission control",
    ),
    (
        "worker-death",
        "6 stereo users at 60 FPS, 5 workers; one dies mid-frame at 3 s (its connection drops), another hangs silently at 6 s",
    ),
    ("straggler", "6 users at 30 FPS; one of 4 workers runs 10x slower from 2 s to 7 s"),
    (
        "adjacent",
        "8 users orbiting one object 3 degrees apart (adjacent, never identical), 30 FPS, 4 workers: what sharing of identical cameras leaves",
    ),
    ("stereo-crowd", "12 headset users (two 1000x1000 eyes) around one object, 30 FPS, 8 workers"),
];

pub fn names() -> Vec<&'static str> {
    SCENARIOS.iter().map(|(n, _)| *n).collect()
}

fn object(name: &str, center: Vec3, half_size: f32, cost_per_ray: f64) -> SimObject {
    SimObject { name: name.to_string(), center, half_size, cost_per_ray }
}

#[allow(clippy::too_many_arguments)]
fn user(
    name: String,
    arrive_s: f64,
    depart_s: f64,
    fps: f64,
    size: (u32, u32),
    fov_deg: f32,
    views: ViewMode,
    objects: Vec<usize>,
    path: CameraPath,
) -> SimUser {
    SimUser { name, arrive_s, depart_s, fps, width: size.0, height: size.1, fov_deg, views, objects, path }
}

fn orbit(radius_m: f32, height_m: f32, speed_deg_s: f32, start_deg: f32) -> CameraPath {
    CameraPath { target: Some(Vec3::ZERO), radius_m, height_m, speed_deg_s, start_deg }
}

fn farm(count: usize, rays_per_s: f64) -> Vec<SimWorker> {
    (1..=count).map(|i| SimWorker::new(&format!("w{i}"), rays_per_s)).collect()
}

/// A built-in scenario, `None` for an unknown name.
pub fn builtin(name: &str, seed: u64) -> Option<Scenario> {
    let description = SCENARIOS.iter().find(|(n, _)| *n == name)?.1.to_string();
    let params = SimParams { seed, ..SimParams::default() };
    let d = params.duration_s;
    let (objects, users, workers, params) = match name {
        "many-objects" => {
            let mut objects =
                vec![object("statue", Vec3::ZERO, 0.5, 1.0), object("plant", Vec3::new(0.8, 0.4, 0.0), 0.3, 5.0)];
            for i in 0..10 {
                let a = (36.0 * i as f32).to_radians();
                objects.push(object(&format!("prop{i}"), Vec3::new(3.5 * a.cos(), 3.5 * a.sin(), -0.3), 0.08, 1.0));
            }
            let users = vec![user(
                "viewer".into(),
                0.0,
                d,
                60.0,
                (1920, 1080),
                50.0,
                ViewMode::Mono,
                (0..12).collect(),
                orbit(1.8, 0.4, 12.0, 0.0),
            )];
            (objects, users, farm(8, 1e8), params)
        }
        "many-users" => {
            let objects = vec![object("lego", Vec3::ZERO, 0.6, 1.0)];
            let users = (0..24)
                .map(|i| {
                    // Six spots 5 degrees apart; the four users of a spot move together (a
                    // guided tour): the path is offset by their arrival so that at any moment
                    // they stand at the same spot.
                    let (spot, arrive) = (i / 4, 0.1 * i as f64);
                    let path = orbit(3.0, 0.8, 6.0, 5.0 * spot as f32 + 6.0 * arrive as f32);
                    user(
                        format!("u{i:02}-spot{spot}"),
                        arrive,
                        d,
                        60.0,
                        (1280, 720),
                        50.0,
                        ViewMode::Mono,
                        vec![0],
                        path,
                    )
                })
                .collect();
            (objects, users, farm(4, 5e7), params)
        }
        "quilt" => {
            let objects = vec![object("lego", Vec3::ZERO, 0.5, 1.0)];
            let quilt = ViewMode::Quilt(45);
            let users = vec![
                user("display-a".into(), 0.0, d, 20.0, (420, 560), 40.0, quilt, vec![0], orbit(2.5, 0.5, 10.0, 0.0)),
                user(
                    "display-a-mirror".into(),
                    0.0,
                    d,
                    20.0,
                    (420, 560),
                    40.0,
                    quilt,
                    vec![0],
                    orbit(2.5, 0.5, 10.0, 0.0),
                ),
                user("display-b".into(), 0.2, d, 20.0, (420, 560), 40.0, quilt, vec![0], orbit(2.5, 0.5, -10.0, 120.0)),
                user(
                    "display-b-mirror".into(),
                    0.2,
                    d,
                    20.0,
                    (420, 560),
                    40.0,
                    quilt,
                    vec![0],
                    orbit(2.5, 0.5, -10.0, 120.0),
                ),
            ];
            (objects, users, farm(8, 1e8), params)
        }
        "overload" => {
            let params = SimParams { duration_s: 15.0, ..params };
            let objects = vec![object("lego", Vec3::ZERO, 0.6, 1.0)];
            let users = (0..20)
                .map(|i| {
                    let path = orbit(3.0, 0.8, 10.0, 18.0 * i as f32);
                    user(
                        format!("u{i:02}"),
                        0.5 * i as f64,
                        params.duration_s,
                        60.0,
                        (1280, 720),
                        50.0,
                        ViewMode::Mono,
                        vec![0],
                        path,
                    )
                })
                .collect();
            (objects, users, farm(4, 2.5e7), params)
        }
        "worker-death" => {
            let objects =
                vec![object("lego", Vec3::ZERO, 0.6, 1.0), object("chair", Vec3::new(1.2, 0.0, 0.0), 0.4, 1.0)];
            let users = (0..6)
                .map(|i| {
                    let path =
                        CameraPath { target: Some(Vec3::new(0.6, 0.0, 0.0)), ..orbit(3.0, 0.3, 8.0, 60.0 * i as f32) };
                    user(format!("vr{i}"), 0.0, d, 60.0, (1000, 1000), 90.0, ViewMode::Stereo, vec![0, 1], path)
                })
                .collect();
            let mut workers = farm(5, 6e7);
            // 2.5 ms after the frame released at 3.0167 s, while its batches are in flight.
            workers[1].fail_s = Some(3.019);
            workers[3].fail_s = Some(6.019);
            workers[3].detect = Detect::Silent;
            (objects, users, workers, params)
        }
        "straggler" => {
            let objects = vec![object("lego", Vec3::ZERO, 0.6, 1.0)];
            let users = (0..6)
                .map(|i| {
                    user(
                        format!("u{i}"),
                        0.0,
                        d,
                        30.0,
                        (1280, 720),
                        50.0,
                        ViewMode::Mono,
                        vec![0],
                        orbit(3.0, 0.8, 10.0, 60.0 * i as f32),
                    )
                })
                .collect();
            let mut workers = farm(4, 3e7);
            workers[0].slow = Some((2.0, 7.0, 10.0));
            (objects, users, workers, params)
        }
        "adjacent" => {
            let objects = vec![object("lego", Vec3::ZERO, 0.6, 1.0)];
            let users = (0..8)
                .map(|i| {
                    let path = orbit(3.0, 0.8, 6.0, 3.0 * i as f32);
                    user(format!("u{i}"), 0.0, d, 30.0, (1280, 720), 50.0, ViewMode::Mono, vec![0], path)
                })
                .collect();
            (objects, users, farm(4, 5e7), params)
        }
        "stereo-crowd" => {
            let objects = vec![object("lego", Vec3::ZERO, 0.6, 1.0)];
            let users = (0..12)
                .map(|i| {
                    let path = orbit(3.0, 0.5, 8.0, 30.0 * i as f32);
                    user(
                        format!("vr{i:02}"),
                        0.1 * i as f64,
                        d,
                        30.0,
                        (1000, 1000),
                        90.0,
                        ViewMode::Stereo,
                        vec![0],
                        path,
                    )
                })
                .collect();
            (objects, users, farm(8, 6e7), params)
        }
        _ => return None,
    };
    Some(Scenario { name: name.to_string(), description, objects, users, workers, params })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_named_scenario_builds() {
        for name in names() {
            let s = builtin(name, 1).expect("built-in");
            assert!(!s.users.is_empty() && !s.workers.is_empty() && !s.objects.is_empty(), "{name}");
            for u in &s.users {
                let views = u.views_at(0.0, &s.objects).expect("cameras");
                assert_eq!(views.len(), u.views.count());
            }
        }
        assert!(builtin("nope", 1).is_none());
        assert_eq!(builtin("quilt", 1).expect("quilt").users[0].views.count(), 45);
    }
}
