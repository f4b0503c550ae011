//! The properties the paper claims, checked on the simulator (short runs: a few simulated
//! seconds each).

use nephele_scheduler::Policy;
use nephele_sim::{Report, Scenario, SimParams, Variant, csv, run, scenario_from_csv, scenarios};

fn scenario(name: &str, seconds: f64) -> Scenario {
    let mut s = scenarios::builtin(name, 7).expect("built-in scenario");
    s.params.duration_s = seconds;
    for u in &mut s.users {
        u.depart_s = u.depart_s.min(seconds);
    }
    s
}

fn simulate(s: &Scenario, variant: Variant) -> Report {
    run(s, &variant).expect("simulation runs")
}

#[test]
fn nephele_beats_round_robin_in_the_many_users_scenario() {
    let s = scenario("many-users", 4.0);
    let nephele = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let round_robin = simulate(&s, Variant::of(Policy::RoundRobin)).summary;
    assert!(nephele.attainment_mean >= 0.9, "{nephele:?}");
    assert!(
        nephele.attainment_mean > round_robin.attainment_mean + 0.3,
        "nephele {nephele:?}\nround robin {round_robin:?}"
    );
    // Users at the same spot share their rays: rendered once, fanned out to the four.
    assert!(
        nephele.shared_joins > 0 && (nephele.rays_rendered as f64) < 0.5 * nephele.rays_requested as f64,
        "{nephele:?}"
    );
    assert_eq!(round_robin.shared_joins + round_robin.history_hits, 0);
    assert!(round_robin.rays_rendered as f64 > 0.95 * round_robin.rays_requested as f64);
}

#[test]
fn viewers_of_one_quilt_render_its_rays_once() {
    let s = scenario("quilt", 1.5);
    let shared = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let unshared = simulate(&s, Variant::nephele_without_sharing()).summary;
    assert!(shared.shared_joins >= 45, "{shared:?}");
    // Two pairs of identical rigs: about half the rays.
    let ratio = shared.rays_rendered as f64 / shared.rays_requested as f64;
    assert!(ratio < 0.6, "{ratio}");
    assert_eq!(unshared.shared_joins + unshared.history_hits, 0);
    assert_eq!(shared.share_error_px_max, 0.0, "identical rigs merge exactly");
}

#[test]
fn rays_per_displayed_pixel_counts_what_sharing_saves() {
    // Stereo eyes never share; without sharing, each shown pixel of an object costs its ray.
    let s = scenario("stereo-crowd", 1.5);
    let crowd = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let pixels: u64 = 1000 * 1000 * 2 * crowd.frames_completed;
    assert_eq!(crowd.pixels_displayed, pixels, "{crowd:?}");
    let per_pixel = crowd.rays_per_displayed_pixel();
    assert!(per_pixel > 0.0 && per_pixel < 1.0, "the object fills part of each eye: {per_pixel}");
    // The same quilt shown twice: half the rays per shown pixel of rendering each alone.
    let q = scenario("quilt", 1.5);
    let shared = simulate(&q, Variant::of(Policy::Nephele)).summary;
    let unshared = simulate(&q, Variant::nephele_without_sharing()).summary;
    let ratio = shared.rays_per_displayed_pixel() / unshared.rays_per_displayed_pixel();
    assert!(ratio < 0.6, "shared {shared:?}\nunshared {unshared:?}");
}

#[test]
fn a_worker_dying_mid_frame_loses_no_frame() {
    let mut s = scenario("worker-death", 5.0);
    s.workers[3].fail_s = None; // keep only the process death at 3.019 s (connection drops)
    for policy in [Policy::Nephele, Policy::Fifo] {
        let r = simulate(&s, Variant::of(policy)).summary;
        assert!(r.batches_reissued > 0, "{policy}: the dead worker had batches in flight: {r:?}");
        assert_eq!(r.frames_dropped, 0, "{policy}: {r:?}");
        // Every released frame completed, except at most the frames in flight at the end.
        assert!(r.frames_completed + 2 * r.users as u64 >= r.frames_released, "{policy}: {r:?}");
        assert!(r.attainment_min > 0.99, "{policy}: {r:?}");
    }
}

#[test]
fn a_silent_hang_is_detected_and_its_batches_reissued() {
    let mut s = scenario("worker-death", 8.0);
    s.workers[1].fail_s = None; // only the silent hang at 6.019 s
    let r = simulate(&s, Variant::of(Policy::Nephele)).summary;
    assert!(r.batches_reissued > 0, "{r:?}");
    assert!(r.attainment_mean > 0.95, "{r:?}");
}

#[test]
fn a_straggler_is_worked_around() {
    let s = scenario("straggler", 5.0);
    let nephele = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let round_robin = simulate(&s, Variant::of(Policy::RoundRobin)).summary;
    assert!(nephele.attainment_mean > 0.95, "{nephele:?}");
    assert!(nephele.attainment_mean > round_robin.attainment_mean + 0.2, "{nephele:?}\n{round_robin:?}");
}

#[test]
fn overload_closes_admission_and_protects_the_admitted() {
    let s = scenario("overload", 8.0);
    let nephele = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let fifo = simulate(&s, Variant::of(Policy::Fifo)).summary;
    let arrived = s.users.iter().filter(|u| u.arrive_s <= s.params.duration_s).count();
    assert!(nephele.refusals > 0 && nephele.admitted < arrived, "{nephele:?}");
    assert_eq!(fifo.admitted, arrived);
    assert_eq!(fifo.refusals, 0);
    assert!(nephele.attainment_mean > fifo.attainment_mean + 0.3, "{nephele:?}\n{fifo:?}");
}

#[test]
fn heavy_and_light_objects_all_render() {
    let s = scenario("many-objects", 2.0);
    let nephele = simulate(&s, Variant::of(Policy::Nephele)).summary;
    let one_per_worker = simulate(&s, Variant::of(Policy::ObjectPerWorker)).summary;
    assert!(nephele.attainment_mean > 0.95, "{nephele:?}");
    assert!(nephele.attainment_mean > one_per_worker.attainment_mean, "{one_per_worker:?}");
}

#[test]
fn same_seed_same_numbers_other_seed_other_numbers() {
    let s = scenario("straggler", 2.0);
    let a = simulate(&s, Variant::of(Policy::Nephele));
    let b = simulate(&s, Variant::of(Policy::Nephele));
    assert_eq!(a, b);
    let mut other = s.clone();
    other.params.seed = 8;
    let c = simulate(&other, Variant::of(Policy::Nephele));
    assert_ne!(a.users, c.users, "worker jitter follows the seed");
}

#[test]
fn a_csv_trace_and_farm_replay() {
    let trace = "user,arrive_s,depart_s,fps,width,height,fov_deg,views,objects,radius_m,height_m,speed_deg_s,start_deg\n\
                 a,0,2,30,320,240,50,mono,cube:0:0:0:0.5,3,0.5,10,0\n\
                 b,0.5,2,30,320,240,50,stereo,cube:0:0:0:0.5;ball:1:0:0:0.3:5,3,0.5,0,90\n";
    let farm = "w1,5e7\nw2,5e7,0.2,0.2\n";
    let params = SimParams { duration_s: 2.0, ..SimParams::default() };
    let s = scenario_from_csv("mine", (trace, "trace.csv"), Some((farm, "farm.csv")), params).expect("valid");
    assert_eq!((s.users.len(), s.objects.len(), s.workers.len()), (2, 2, 2));
    let r = simulate(&s, Variant::of(Policy::Nephele)).summary;
    assert_eq!(r.admitted, 2);
    assert!(r.frames_completed > 50, "{r:?}");
    let bad = scenario_from_csv(
        "mine",
        ("a,0,2,30,320,240,50,mono,cube:0:0:0:0.5,3,0.5,10,0\nb,0,2,oops,320,240,50,mono,c:0:0:0:1,3,0,0,0", "t.csv"),
        None,
        SimParams::default(),
    );
    let err = bad.expect_err("malformed");
    assert_eq!(err.line, 2);
    assert!(err.to_string().contains("t.csv line 2: fps 'oops' is not a number"), "{err}");
    assert!(csv::TRACE_FORMAT.contains("quilt"));
}

#[test]
fn every_scenario_runs_under_every_policy() {
    for name in scenarios::names() {
        let s = scenario(name, 0.5);
        for variant in Variant::defaults() {
            let r = simulate(&s, variant.clone()).summary;
            assert!(r.frames_released > 0, "{name} {}: {r:?}", variant.label);
        }
    }
}
