//! A user's consecutive frames (issue 16; NEPHELE section 5 counts "consecutive frames of one
//! user" among the views that share rays): a batch may be taken from this worker's last full
//! render of the same user's view of the same asset by depth-based reprojection
//! ([`crate::derive`]), with only the pixels reprojection cannot vouch for rendered.
//!
//! The rules that keep the error bounded (the "8 frames of one user" rows of `nephele bench
//! share`, BENCHMARKS.md, measure exactly this: 1 frame in 4 in full, the others from it):
//!
//! * A previous render serves at most `previous_frames` later batches, then the view is
//!   rendered in full again: no pixel is older than that many frames, and none is resampled
//!   twice (a reused frame is never a source).
//! * It serves only views seen from within the reuse angle of it (the angle at the asset's
//!   centre between the two cameras' positions) and of the same image size, and only while
//!   it is younger than [`PreviousRenders::MAX_AGE`].
//! * A pixel of the source's box that its batch lacks is empty space only where the master
//!   says the batch held whole rows of its task's coverage (`ReuseLimits::rows_complete`);
//!   otherwise (a large task split inside rows) it is unknown
//!   ([`crate::derive::Absent::Unknown`]), and what a later view reads there is rendered.
//! * It is used only while it pays: per asset, the worker keeps the time per pixel of full
//!   renders and of frames taken from a previous render (reprojection plus leftovers), and
//!   renders in full while that is cheaper, trying reuse again every
//!   [`PreviousRenders::PROBE_EVERY`] chances. A diffuse object's rays can be cheaper than
//!   the reprojection (`nephele bench share`'s "live path: frames of one user" rows,
//!   BENCHMARKS.md); a glass shell's are not.
//!
//! Slots: one per (session, asset) and direction, so a quilt's key views or several users
//! keep their own. A new slot starts part-way through its count (by the asset's name), so
//! the objects of one frame are not all rendered in full on the same frame.
//!
//! Why on the worker: it holds the render the moment it is made and the kernel for the
//! leftovers, so no source travels. The previous render is not always where the next batch
//! lands: with two frames in flight the next frame's batch often goes to the other worker
//! while the previous one still renders (live, 43-58 % of the object batches were reused,
//! BENCHMARKS.md); such a batch is rendered in full, which is what it cost before. Placing
//! the batch on the worker that holds the render was tried in the scheduler and did not pay
//! (the shell's batches without a source stayed the same; holding it back cost latency), and
//! at the loadgen's orbit (about 2 degrees a frame) the reuse angle, not placement, ends a
//! slot after two or three frames. What reuse leaves to render are the costly pixels (depth
//! and semi-transparent edges), so time falls less than rays (BENCHMARKS.md, 2026-12-04).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use glam::Vec3;
use nephele_geometry::camera::Camera;
use nephele_geometry::pixels::PixelResults;

use crate::derive::Absent;

/// A full render kept as a source.
#[derive(Debug)]
pub struct Previous {
    pub camera: Camera,
    pub pixels: Vec<u32>,
    pub results: PixelResults,
    /// What the pixels of its box it lacks stand for: empty where the batch held whole rows
    /// of its task (`ReuseLimits::rows_complete`), else unknown.
    pub absent: Absent,
}

#[derive(Debug)]
struct Slot {
    source: Arc<Previous>,
    /// Later batches it has served.
    served: u32,
    rendered_at: Instant,
    /// A render ahead (the scheduler's, while the farm was idle): other sessions' views near
    /// it may take from it too.
    ahead: bool,
}

/// The worker's previous full renders, bounded in count, pixels and age.
#[derive(Debug)]
pub struct PreviousRenders {
    slots: Mutex<HashMap<(u64, String), Vec<Slot>>>,
    costs: Mutex<HashMap<String, Costs>>,
    max_pixels: usize,
}

/// Seconds per pixel of an asset's batches, moving averages.
#[derive(Debug, Default, Clone, Copy)]
struct Costs {
    full: Option<f64>,
    reused: Option<f64>,
    /// Chances to reuse turned down because rendering in full was cheaper.
    declined: u32,
}

/// How a batch was made, for [`PreviousRenders::record`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Made {
    Full,
    Reused,
}

/// What to do with a batch.
#[derive(Debug)]
pub enum Plan {
    /// Take it from this render.
    Reuse(Arc<Previous>),
    /// Render it in full (and [`PreviousRenders::remember`] it).
    Render(Why),
}

/// Why a batch is rendered in full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Why {
    /// Reuse is off for it.
    Off,
    /// No previous render of this view here (first frame, another worker had it, too far
    /// in angle or too old).
    NoSource,
    /// The previous render has served its count.
    ServedOut,
    /// Rendering in full measured cheaper for this asset.
    NotPaying,
}

/// Where a new slot of `asset` starts its count of served frames, in `0..=previous_frames`:
/// staggered by the asset's name, so that the objects of one frame do not all come due for a
/// full render on the same frame.
pub fn staggered_start(asset: &str, previous_frames: u32) -> u32 {
    let hash = asset.bytes().fold(0u32, |h, b| h.wrapping_mul(31).wrapping_add(u32::from(b)));
    hash % (previous_frames + 1)
}

/// The angle, degrees, at `centre` between the directions to `a` and to `b`.
fn angle_at(centre: Vec3, a: Vec3, b: Vec3) -> f32 {
    let (u, v) = ((a - centre).normalize_or_zero(), (b - centre).normalize_or_zero());
    if u == Vec3::ZERO || v == Vec3::ZERO {
        return if a.distance(b) < 1e-6 { 0.0 } else { 180.0 };
    }
    u.dot(v).clamp(-1.0, 1.0).acos().to_degrees()
}

impl PreviousRenders {
    /// A render older than this serves nothing (at a few frames a second it is a frame or
    /// two; a user who paused comes back to a full render).
    pub const MAX_AGE: Duration = Duration::from_secs(1);
    /// Slots per session and asset (a quilt keeps a handful of key views).
    pub const SLOTS_PER_VIEW_SET: usize = 8;
    /// Where reuse did not pay, it is tried again once in this many chances (the cost
    /// changes with the view: an object seen close up has more pixels per leftover).
    pub const PROBE_EVERY: u32 = 16;
    /// Weight of the newest batch in the moving averages of cost per pixel.
    const SMOOTHING: f64 = 0.2;

    /// Keeps at most `max_pixels` pixels in all (24 bytes each).
    pub fn new(max_pixels: usize) -> PreviousRenders {
        PreviousRenders { slots: Mutex::new(HashMap::new()), costs: Mutex::new(HashMap::new()), max_pixels }
    }

    /// What a batch of `pixels` pixels of `asset` cost, made as `made`.
    pub fn record(&self, asset: &str, made: Made, pixels: usize, elapsed: Duration) {
        if pixels == 0 {
            return;
        }
        let per_pixel = elapsed.as_secs_f64() / pixels as f64;
        let mut costs = self.costs.lock().unwrap_or_else(PoisonError::into_inner);
        let costs = costs.entry(asset.to_owned()).or_default();
        let average = match made {
            Made::Full => &mut costs.full,
            Made::Reused => &mut costs.reused,
        };
        *average = Some(average.map_or(per_pixel, |a| a + Self::SMOOTHING * (per_pixel - a)));
    }

    /// Whether taking `asset`'s batches from previous renders pays (or is due a try).
    fn pays(&self, asset: &str) -> bool {
        let mut costs = self.costs.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(costs) = costs.get_mut(asset) else { return true };
        match (costs.full, costs.reused) {
            (Some(full), Some(reused)) if reused >= full => {
                costs.declined += 1;
                costs.declined.is_multiple_of(Self::PROBE_EVERY)
            }
            _ => true,
        }
    }

    /// The slot of `(session, asset)` nearest to `camera` in angle at `centre`, if within
    /// `max_angle_deg`.
    fn nearest(slots: &[Slot], camera: &Camera, centre: Vec3, max_angle_deg: f32) -> Option<usize> {
        slots
            .iter()
            .enumerate()
            .filter(|(_, s)| s.source.camera.width() == camera.width() && s.source.camera.height() == camera.height())
            .map(|(k, s)| (k, angle_at(centre, s.source.camera.position(), camera.position())))
            .filter(|&(_, angle)| angle <= max_angle_deg)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(k, _)| k)
    }

    /// Whether the batch for `session`'s view `camera` of `asset` (centred at `centre`) is
    /// taken from a previous render, at most `previous_frames` after it, seen within
    /// `max_angle_deg`.
    pub fn plan(
        &self,
        (session, asset): (u64, &str),
        camera: &Camera,
        centre: Vec3,
        max_angle_deg: f32,
        previous_frames: u32,
    ) -> Plan {
        if previous_frames == 0 {
            return Plan::Render(Why::Off);
        }
        let mut all = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        let now = Instant::now();
        let own = (session, asset.to_owned());
        let found = match all.get_mut(&own) {
            Some(slots) => {
                slots.retain(|s| now.duration_since(s.rendered_at) < Self::MAX_AGE);
                Self::nearest(slots, camera, centre, max_angle_deg).map(|k| (own.clone(), k))
            }
            None => None,
        };
        // No render of its own near it: another session's render ahead of this asset near
        // it (users looking at the object from nearby; the scheduler renders one for them).
        let found = found.or_else(|| {
            all.iter()
                .filter(|((s, a), _)| *s != session && a == asset)
                .flat_map(|(key, slots)| {
                    slots
                        .iter()
                        .enumerate()
                        .filter(|(_, s)| s.ahead && now.duration_since(s.rendered_at) < Self::MAX_AGE)
                        .filter(|(_, s)| {
                            s.source.camera.width() == camera.width() && s.source.camera.height() == camera.height()
                        })
                        .map(move |(k, s)| (key, k, angle_at(centre, s.source.camera.position(), camera.position())))
                })
                .filter(|&(_, _, angle)| angle <= max_angle_deg)
                .min_by(|a, b| a.2.total_cmp(&b.2))
                .map(|(key, k, _)| (key.clone(), k))
        });
        let Some((key, k)) = found else { return Plan::Render(Why::NoSource) };
        let Some(slot) = all.get_mut(&key).and_then(|slots| slots.get_mut(k)) else {
            return Plan::Render(Why::NoSource);
        };
        if slot.served >= previous_frames {
            return Plan::Render(Why::ServedOut);
        }
        if !self.pays(asset) {
            return Plan::Render(Why::NotPaying);
        }
        slot.served += 1;
        Plan::Reuse(slot.source.clone())
    }

    /// Whether the costs measured so far say that taking `asset`'s batches from previous
    /// renders is no cheaper than rendering them (a render ahead of such an asset is not made).
    pub fn reuse_measured_dearer(&self, asset: &str) -> bool {
        let costs = self.costs.lock().unwrap_or_else(PoisonError::into_inner);
        costs.get(asset).is_some_and(|c| matches!((c.full, c.reused), (Some(full), Some(reused)) if reused >= full))
    }

    /// Keeps a full render as the source of its slot (replacing the slot it renews, or a new
    /// one), and drops the oldest renders beyond the bounds.
    pub fn remember(
        &self,
        slot: (u64, &str),
        source: Previous,
        centre: Vec3,
        max_angle_deg: f32,
        previous_frames: u32,
    ) {
        self.keep(slot, source, (centre, max_angle_deg), previous_frames, false);
    }

    /// [`Self::remember`] for a render ahead of the session's next frames (the scheduler's
    /// render-ahead): it serves its full `previous_frames`, new slot or not.
    pub fn remember_ahead(
        &self,
        slot: (u64, &str),
        source: Previous,
        centre: Vec3,
        max_angle_deg: f32,
        previous_frames: u32,
    ) {
        self.keep(slot, source, (centre, max_angle_deg), previous_frames, true);
    }

    fn keep(
        &self,
        (session, asset): (u64, &str),
        source: Previous,
        (centre, max_angle_deg): (Vec3, f32),
        previous_frames: u32,
        ahead: bool,
    ) {
        if previous_frames == 0 || source.pixels.len() > self.max_pixels {
            return;
        }
        let mut all = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        let now = Instant::now();
        let slots = all.entry((session, asset.to_owned())).or_default();
        let renewed = Self::nearest(slots, &source.camera, centre, max_angle_deg);
        let slot = match renewed {
            Some(k) => {
                slots.swap_remove(k);
                Slot { source: Arc::new(source), served: 0, rendered_at: now, ahead }
            }
            None => {
                let served = if ahead { 0 } else { staggered_start(asset, previous_frames) };
                Slot { source: Arc::new(source), served, rendered_at: now, ahead }
            }
        };
        slots.push(slot);
        if slots.len() > Self::SLOTS_PER_VIEW_SET {
            let oldest = (0..slots.len()).min_by_key(|&k| slots[k].rendered_at).unwrap_or(0);
            slots.swap_remove(oldest);
        }
        // Bounds over every session: the stale first, then the oldest.
        all.retain(|_, slots| {
            slots.retain(|s| now.duration_since(s.rendered_at) < Self::MAX_AGE);
            !slots.is_empty()
        });
        let mut held: usize = all.values().flatten().map(|s| s.source.pixels.len()).sum();
        while held > self.max_pixels {
            let Some((key, k)) = all
                .iter()
                .flat_map(|(key, slots)| slots.iter().enumerate().map(move |(k, s)| (key, k, s.rendered_at)))
                .min_by_key(|&(_, _, at)| at)
                .map(|(key, k, _)| (key.clone(), k))
            else {
                break;
            };
            if let Some(slots) = all.get_mut(&key) {
                held -= slots[k].source.pixels.len();
                slots.swap_remove(k);
                if slots.is_empty() {
                    all.remove(&key);
                }
            }
        }
    }

    /// Pixels held, for tests.
    #[cfg(test)]
    fn held(&self) -> usize {
        let all = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        all.values().flatten().map(|s| s.source.pixels.len()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(degrees: f32, width: u32) -> Camera {
        let a = degrees.to_radians();
        let eye = Vec3::new(3.0 * a.sin(), -3.0 * a.cos(), 0.5);
        Camera::look_at(width, 48, 0.7, eye, Vec3::ZERO, Vec3::Z).expect("camera")
    }

    fn render(camera: Camera, pixels: usize) -> Previous {
        Previous {
            camera,
            pixels: (0..pixels as u32).collect(),
            results: PixelResults::with_len(pixels),
            absent: Absent::Unknown,
        }
    }

    fn reuses(plan: Plan) -> bool {
        matches!(plan, Plan::Reuse(_))
    }

    #[test]
    fn a_render_serves_a_bounded_count_of_nearby_views_then_is_renewed() {
        let renders = PreviousRenders::new(1 << 20);
        let key = (7, "knot.nolf");
        assert!(!reuses(renders.plan(key, &camera(0.0, 64), Vec3::ZERO, 6.0, 3)), "nothing yet: render");
        renders.remember(key, render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 3);
        // The first slot of an asset starts part-way (staggered): count what it serves.
        let mut served = 0;
        while reuses(renders.plan(key, &camera(1.0, 64), Vec3::ZERO, 6.0, 3)) {
            served += 1;
            assert!(served <= 3);
        }
        // Renewed: the full render replaces the slot and serves three more.
        renders.remember(key, render(camera(1.0, 64), 100), Vec3::ZERO, 6.0, 3);
        for _ in 0..3 {
            assert!(reuses(renders.plan(key, &camera(2.0, 64), Vec3::ZERO, 6.0, 3)));
        }
        assert!(!reuses(renders.plan(key, &camera(2.0, 64), Vec3::ZERO, 6.0, 3)));
        assert_eq!(renders.held(), 100, "one slot, renewed in place");
        // Too far in angle, another size, another session or asset, or reuse off: render.
        renders.remember(key, render(camera(2.0, 64), 100), Vec3::ZERO, 6.0, 3);
        assert!(!reuses(renders.plan(key, &camera(9.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan(key, &camera(2.0, 80), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan((8, "knot.nolf"), &camera(2.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan((7, "shell.nolf"), &camera(2.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan(key, &camera(2.0, 64), Vec3::ZERO, 6.0, 0)));
    }

    #[test]
    fn views_far_apart_keep_their_own_slots_within_the_bounds() {
        let renders = PreviousRenders::new(450);
        let key = (1, "a");
        for view in 0..5 {
            renders.remember(key, render(camera(view as f32 * 10.0, 64), 100), Vec3::ZERO, 6.0, 3);
        }
        // 500 pixels asked, 450 allowed: the oldest went.
        assert_eq!(renders.held(), 400);
        assert!(!reuses(renders.plan(key, &camera(0.5, 64), Vec3::ZERO, 6.0, 3)), "the oldest view was dropped");
        // Each of the others serves its own neighbourhood (at least once: staggered starts
        // leave every slot one use or more).
        for view in 1..5 {
            assert!(reuses(renders.plan(key, &camera(view as f32 * 10.0 + 0.5, 64), Vec3::ZERO, 6.0, 15)), "{view}");
        }
        // A render larger than the whole budget is not kept.
        renders.remember((2, "b"), render(camera(0.0, 64), 451), Vec3::ZERO, 6.0, 3);
        assert_eq!(renders.held(), 400);
    }

    #[test]
    fn reuse_stops_where_rendering_in_full_is_cheaper_and_is_tried_again_now_and_then() {
        let renders = PreviousRenders::new(1 << 20);
        let key = (3, "cheap");
        let ms = Duration::from_millis;
        // A renewed slot starts its count at 0 (a new one is staggered).
        renders.remember(key, render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 15);
        let reused_of = |renders: &PreviousRenders, chances: u32| {
            (0..chances)
                .filter(|_| {
                    renders.remember(key, render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 15);
                    reuses(renders.plan(key, &camera(0.5, 64), Vec3::ZERO, 6.0, 15))
                })
                .count() as u32
        };
        // No costs known yet: reuse.
        assert_eq!(reused_of(&renders, 4), 4);
        // Reuse costs twice a full render per pixel: declined but for one probe in 16.
        renders.record("cheap", Made::Full, 1000, ms(10));
        renders.record("cheap", Made::Reused, 1000, ms(20));
        assert_eq!(reused_of(&renders, 2 * PreviousRenders::PROBE_EVERY), 2);
        // Another asset is not affected; and once reuse measures cheaper it is used again.
        assert!(reuses({
            renders.remember((3, "dear"), render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 15);
            renders.remember((3, "dear"), render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 15);
            renders.plan((3, "dear"), &camera(0.5, 64), Vec3::ZERO, 6.0, 15)
        }));
        for _ in 0..10 {
            renders.record("cheap", Made::Reused, 1000, ms(2));
        }
        assert_eq!(reused_of(&renders, 4), 4);
    }

    #[test]
    fn a_render_ahead_serves_its_full_count_and_renews_the_slot() {
        let renders = PreviousRenders::new(1 << 20);
        // A new slot of "ad" starts served out (3 of 3): a render ahead starts at 0.
        let key = (5, "ad");
        assert_eq!(staggered_start("ad", 3), 3);
        renders.remember_ahead(key, render(camera(0.0, 64), 100), Vec3::ZERO, 6.0, 3);
        for _ in 0..3 {
            assert!(reuses(renders.plan(key, &camera(1.0, 64), Vec3::ZERO, 6.0, 3)));
        }
        assert!(!reuses(renders.plan(key, &camera(1.0, 64), Vec3::ZERO, 6.0, 3)), "served out");
        // The next render ahead renews the slot in place.
        renders.remember_ahead(key, render(camera(2.0, 64), 100), Vec3::ZERO, 6.0, 3);
        assert!(reuses(renders.plan(key, &camera(2.5, 64), Vec3::ZERO, 6.0, 3)));
        assert_eq!(renders.held(), 100);
        // Another user near it, with no render of its own, takes from it too (the count is
        // the render's); one of another size or asset, or too far, does not.
        assert!(reuses(renders.plan((6, "ad"), &camera(3.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan((6, "ad"), &camera(3.0, 80), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan((6, "other"), &camera(3.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(!reuses(renders.plan((6, "ad"), &camera(12.0, 64), Vec3::ZERO, 6.0, 3)));
        assert!(reuses(renders.plan((7, "ad"), &camera(1.5, 64), Vec3::ZERO, 6.0, 3)), "third use");
        assert!(!reuses(renders.plan((8, "ad"), &camera(2.0, 64), Vec3::ZERO, 6.0, 3)), "served out");
        // A full render (not ahead) stays its own session's.
        renders.remember((9, "ad"), render(camera(30.0, 64), 100), Vec3::ZERO, 6.0, 3);
        assert!(!reuses(renders.plan((10, "ad"), &camera(30.0, 64), Vec3::ZERO, 6.0, 3)));
        // Costs: unknown or reuse cheaper is not "dearer"; reuse at twice the cost is.
        assert!(!renders.reuse_measured_dearer("ad"));
        renders.record("ad", Made::Full, 1000, Duration::from_millis(10));
        renders.record("ad", Made::Reused, 1000, Duration::from_millis(5));
        assert!(!renders.reuse_measured_dearer("ad"));
        renders.record("yy", Made::Full, 1000, Duration::from_millis(10));
        renders.record("yy", Made::Reused, 1000, Duration::from_millis(20));
        assert!(renders.reuse_measured_dearer("yy"));
    }

    #[test]
    fn angles_at_the_centre() {
        let (a, b) = (Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0));
        assert!((angle_at(Vec3::ZERO, a, b) - 90.0).abs() < 1e-4);
        assert_eq!(angle_at(Vec3::ZERO, a, a * 2.0), 0.0);
        assert_eq!(angle_at(a, a, a), 0.0);
        assert_eq!(angle_at(a, a, b), 180.0, "a camera at the centre matches nothing else");
    }
}
