use super::*;

/// An analytic scene: a ball of radius 0.6 at the origin, coloured by its normal, seen from
/// random points at distance 3; targets exact (opacity 1 on the ball, 0 beside it; the
/// depth fraction of the hit along the segment inside the box `[-1, 1]^3`).
fn ball_rays(count: usize, seed: u64, sampling: &RaySampling) -> RaySet {
    let mut rng = SplitMix64::new(seed);
    let mut set = RaySet { depth_known: true, ..RaySet::default() };
    let mut unit = || Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE;
    while set.len() < count {
        let origin = unit().normalize_or(Vec3::Z) * 3.0;
        let aim = unit() * 0.8;
        let dir = (aim - origin).normalize();
        let Some((t0, t1)) = sampling.segment(origin, dir) else { continue };
        // |o + t d|^2 = r^2.
        let b = origin.dot(dir);
        let disc = b * b - (origin.length_squared() - 0.36);
        let target = if disc > 0.0 {
            let t = -b - disc.sqrt();
            let n = (origin + t * dir) / 0.6;
            let c = (n * 0.5 + Vec3::splat(0.5)).to_array();
            [c[0], c[1], c[2], 1.0, (t - t0) / (t1 - t0)]
        } else {
            [0.0, 0.0, 0.0, 0.0, 0.5]
        };
        set.rays.push((origin, dir));
        set.targets.push(target);
    }
    set
}

fn ball_sampling() -> RaySampling {
    RaySampling { points: 8, frequencies: 2, min: [-1.0; 3], max: [1.0; 3] }
}

fn options(steps: u32, hard_fraction: f32) -> DistillOptions {
    DistillOptions {
        points: 8,
        frequencies: 2,
        width: 32,
        blocks: 2,
        steps,
        fine_tune_steps: 0,
        batch: 256,
        learning_rate: 3e-3,
        hard_fraction,
        hard_pool: 4096,
        ..DistillOptions::default()
    }
}

#[test]
fn a_short_distillation_lowers_the_loss_on_an_analytic_scene() {
    let sampling = ball_sampling();
    let train = ball_rays(8000, 1, &sampling);
    let held_out = ball_rays(2000, 2, &sampling);
    let opts = options(300, 0.2);
    let start = ResidualMlp::new(network_config(&sampling, opts.width, opts.blocks), opts.seed).expect("network");
    let before = mean_loss(&start, &sampling, &held_out, opts.depth_weight);
    let mut losses = Vec::new();
    let (network, state) =
        distill([&train, &RaySet::default()], &sampling, &opts, None, 0, &mut |s| losses.push(s.loss), &mut |_| Ok(()))
            .expect("distill");
    let after = mean_loss(&network, &sampling, &held_out, opts.depth_weight);
    assert_eq!(losses.len(), 300);
    assert_eq!(state.curve.len(), 6);
    assert!(after < 0.25 * before, "held-out loss {before} -> {after}");
    assert!(!state.pool.is_empty() && state.pool.len() <= opts.hard_pool);
}

#[test]
fn a_resumed_run_ends_where_an_uninterrupted_one_does() {
    let sampling = ball_sampling();
    let pseudo = ball_rays(3000, 3, &sampling);
    // "Real" rays without depth, for the fine-tuning half of the batches.
    let mut real = ball_rays(1000, 4, &sampling);
    real.depth_known = false;
    let opts = DistillOptions { fine_tune_steps: 20, ..options(40, 0.25) };
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("run.ckpt");
    let mut saved = 0;
    let (whole, whole_state) =
        distill([&pseudo, &real], &sampling, &opts, None, 0, &mut |_| {}, &mut |_| Ok(())).expect("uninterrupted");
    // Interrupted after 30 steps (a checkpoint every 30; the error stops the run).
    let stop = distill([&pseudo, &real], &sampling, &opts, None, 30, &mut |_| {}, &mut |c| {
        c.save(&path)?;
        saved += 1;
        Err(DistillError::Data("interrupted".into()))
    });
    assert!(stop.is_err() && saved == 1);
    let resume = DistillCheckpoint::load(&path).expect("load");
    assert_eq!(resume.state.step, 30);
    let mut fine_tuned = 0;
    let (resumed, resumed_state) = distill(
        [&pseudo, &real],
        &sampling,
        &opts,
        Some(resume),
        0,
        &mut |s| fine_tuned += u32::from(s.fine_tuning),
        &mut |_| Ok(()),
    )
    .expect("resumed");
    assert_eq!(fine_tuned, 20);
    assert_eq!(resumed.params(), whole.params());
    assert_eq!(resumed_state.pool, whole_state.pool);
    // Other options are refused.
    let other = DistillOptions { learning_rate: 1e-2, ..opts.clone() };
    let resume = DistillCheckpoint::load(&path).expect("load");
    assert!(distill([&pseudo, &real], &sampling, &other, Some(resume), 0, &mut |_| {}, &mut |_| Ok(())).is_err());
    // A damaged checkpoint is refused.
    let mut bytes = std::fs::read(&path).expect("read");
    let n = bytes.len();
    bytes[n / 2] ^= 1;
    std::fs::write(&path, &bytes).expect("write");
    assert!(DistillCheckpoint::load(&path).expect_err("damaged").to_string().contains("checksum"));
}

#[test]
fn ray_caches_round_trip_and_refuse_damage_or_another_key() {
    let sampling = ball_sampling();
    let set = ball_rays(100, 5, &sampling);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("rays.cache");
    assert_eq!(RaySet::load(&path, 7).expect("missing is fine"), None);
    set.save(&path, 7).expect("save");
    assert_eq!(std::fs::metadata(&path).expect("meta").len() as usize, set.file_bytes());
    assert_eq!(RaySet::load(&path, 7).expect("load"), Some(set));
    assert_eq!(RaySet::load(&path, 8).expect("other key"), None);
    let bytes = std::fs::read(&path).expect("read");
    std::fs::write(&path, &bytes[..bytes.len() - 10]).expect("truncate");
    assert!(RaySet::load(&path, 7).is_err());
}

#[test]
fn bad_options_are_refused() {
    let ok = options(10, 0.2);
    assert!(ok.validate().is_ok());
    for bad in [
        DistillOptions { steps: 0, fine_tune_steps: 0, ..ok.clone() },
        DistillOptions { batch: 4, ..ok.clone() },
        DistillOptions { learning_rate: f32::NAN, ..ok.clone() },
        DistillOptions { hard_fraction: 0.95, ..ok.clone() },
        DistillOptions { hard_pool: 10, ..ok.clone() },
        DistillOptions { depth_weight: -1.0, ..ok.clone() },
        DistillOptions { pseudo_views: 0, ..ok.clone() },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
}

#[test]
fn pseudo_data_meets_the_matter_and_follows_the_teacher() {
    use nephele_kernels::ngp::{FieldConfig, RadianceField};
    let field = RadianceField::new(FieldConfig::small_test(), Vec3::splat(-1.0), 2.0, 3).expect("field");
    let teacher = NgpKernel::new(field);
    let (sampling, matter) = geometry_of(&teacher, 4, 1).expect("geometry");
    let cameras: Vec<Camera> = [Vec3::new(0.0, -3.0, 1.0), Vec3::new(3.0, 0.0, 1.0)]
        .iter()
        .map(|&eye| Camera::look_at(32, 32, 0.8, eye, Vec3::ZERO, Vec3::Z).expect("camera"))
        .collect();
    let opts = DistillOptions { pseudo_views: 3, rays_per_view: 50, ..options(1, 0.0) };
    let mut progress = Vec::new();
    let set = pseudo_data(&teacher, &sampling, &matter, &cameras, &opts, &mut |d, t| progress.push((d, t)))
        .expect("pseudo-data");
    assert_eq!(progress, [(1, 3), (2, 3), (3, 3)]);
    assert_eq!(set.len(), 150);
    assert!(set.depth_known);
    let (answers, _) = teacher.render_rays(&set.rays);
    for (((o, d), t), r) in set.rays.iter().zip(&set.targets).zip(&answers) {
        assert!(matter.hits(*o, *d));
        let (t0, t1) = sampling.segment(*o, *d).expect("segment");
        assert_eq!(*t, target_of(r, t0, t1));
        assert!(t.iter().all(|v| (0.0..=1.0).contains(v)), "{t:?}");
    }
}
