use glam::Vec3;

use super::*;
use crate::kernel::{RayKernel, all_pixels};
use nephele_geometry::camera::Camera;

fn sampling(points: usize) -> RaySampling {
    RaySampling { points, frequencies: 2, min: [-1.0, -2.0, -1.0], max: [1.0, 2.0, 3.0] }
}

/// A matter grid over `[-2, 2]^3` with one occupied cell at the centre (resolution 16).
fn matter() -> MatterGrid {
    let resolution = 16;
    let mut flags = vec![false; (resolution * resolution * resolution) as usize];
    let c = resolution / 2;
    flags[(c * resolution * resolution + c * resolution + c) as usize] = true;
    let grid = OccupancyGrid::from_flags(resolution, &flags).expect("grid");
    MatterGrid::new(MatterPlacement { min: [-2.0; 3], size: 4.0, step: 0.01, resolution }, grid).expect("matter")
}

fn model(points: usize, width: usize, blocks: usize) -> NelfModel {
    let s = sampling(points);
    let network = ResidualMlp::new(network_config(&s, width, blocks), 7).expect("network");
    NelfModel::new(network, s, matter(), serde_json::json!({"test": true})).expect("model")
}

#[test]
fn the_sampler_is_exact_on_a_known_ray_and_box() {
    let s = sampling(4);
    // Along +y through the box's middle in x and z: enters at y = -2 (t = 3), leaves at y = 2
    // (t = 7); the 4 points are the midpoints of 4 parts of 1 each.
    let (origin, dir) = (Vec3::new(0.0, -5.0, 1.0), Vec3::Y);
    let (t0, t1) = s.segment(origin, dir).expect("hits");
    assert_eq!((t0, t1), (3.0, 7.0));
    let distances: Vec<f32> = (0..4).map(|i| s.point_distance(i, t0, t1)).collect();
    assert_eq!(distances, [3.5, 4.5, 5.5, 6.5]);
    let mut points = Vec::new();
    let mut out = vec![0.0; s.input_len()];
    assert_eq!(s.input_len(), 12 * 5);
    s.encode(origin, dir, t0, t1, &mut points, &mut out);
    // Normalised: x = 0 -> 0, z = 1 -> 0, y = -1.5 .. 1.5 in [-2, 2] -> -0.75 .. 0.75.
    assert_eq!(points, [0.0, -0.75, 0.0, 0.0, -0.25, 0.0, 0.0, 0.25, 0.0, 0.0, 0.75, 0.0]);
    // Layout per value: x, sin(pi x), cos(pi x), sin(2 pi x), cos(2 pi x).
    let y = -0.75f32;
    let expect = [y, (std::f32::consts::PI * y).sin(), (std::f32::consts::PI * y).cos()];
    for (a, b) in out[5..8].iter().zip(expect) {
        assert!((a - b).abs() < 1e-6, "{a} vs {b}");
    }
    // From inside the box the segment starts at the origin; behind, parallel outside and
    // degenerate rays miss.
    assert_eq!(s.segment(Vec3::new(0.0, 0.0, 1.0), Vec3::Y), Some((0.0, 2.0)));
    assert_eq!(s.segment(Vec3::new(0.0, 5.0, 1.0), Vec3::Y), None);
    assert_eq!(s.segment(Vec3::new(5.0, 0.0, 1.0), Vec3::Y), None);
    assert_eq!(s.segment(Vec3::new(0.0, -5.0, 1.0), Vec3::ZERO), None);
    assert_eq!(s.segment(Vec3::new(f32::NAN, -5.0, 1.0), Vec3::Y), None);
}

#[test]
fn the_fast_encoding_matches_the_exact_one() {
    for frequencies in [0, 1, 4, 8] {
        let s = RaySampling { frequencies, ..sampling(16) };
        let mut rng = nephele_geometry::SplitMix64::new(frequencies as u64);
        for _ in 0..200 {
            let origin = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 10.0 - Vec3::splat(5.0);
            let dir = (Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) - Vec3::splat(0.5)).normalize();
            let Some((t0, t1)) = s.segment(origin, dir) else { continue };
            let (mut points, mut fast, mut exact) = (Vec::new(), vec![0.0; s.input_len()], vec![0.0; s.input_len()]);
            s.encode(origin, dir, t0, t1, &mut points, &mut fast);
            nephele_nn::frequency_encode(&points, frequencies, true, &mut exact);
            let worst = fast.iter().zip(&exact).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            assert!(worst < 2e-7 * (1 << frequencies) as f32 + 1e-6, "{frequencies} octaves: {worst}");
        }
    }
}

#[test]
fn bad_samplings_are_refused() {
    for bad in [
        RaySampling { points: 0, ..sampling(4) },
        RaySampling { points: MAX_POINTS + 1, ..sampling(4) },
        RaySampling { frequencies: MAX_FREQUENCIES + 1, ..sampling(4) },
        RaySampling { max: [1.0, -2.0, 3.0], ..sampling(4) },
        RaySampling { min: [f32::NAN, -2.0, -1.0], ..sampling(4) },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
    // A network that does not fit the sampling.
    let s = sampling(4);
    let other = ResidualMlp::new(network_config(&sampling(5), 8, 1), 1).expect("network");
    assert!(NelfModel::new(other, s, matter(), serde_json::Value::Null).is_err());
}

#[test]
fn an_asset_round_trips_and_damage_is_refused() {
    let m = model(4, 16, 2);
    let bytes = m.to_bytes();
    assert_eq!(NelfModel::from_bytes(&bytes).expect("round trip"), m);
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("a.nelf");
    m.save(&path).expect("save");
    assert_eq!(NelfModel::load(&path).expect("load"), m);
    // Through the registry, by extension's magic.
    let kernel = crate::assets::load_by_magic(&path, &crate::assets::LoadOptions::default()).expect("registry");
    assert_eq!(kernel.kind(), "nelf");

    let expect_error = |bytes: &[u8], needle: &str| {
        let err = NelfModel::from_bytes(bytes).expect_err("refused").to_string();
        assert!(err.contains(needle), "{needle:?} not in {err:?}");
    };
    expect_error(&bytes[..bytes.len() - 9], "checksum");
    expect_error(&bytes[..10], "truncated");
    expect_error(b"NEPHNGP\0 something else entirely", "not a NeLF");
    let mut flipped = bytes.clone();
    flipped[bytes.len() / 2] ^= 0x40;
    expect_error(&flipped, "checksum");
    // Well-formed files that lie: a NaN parameter, another version, a header that does not
    // match the payload (each with a fresh checksum).
    let reseal = |mut b: Vec<u8>| {
        crate::assets::reseal_trailing_crc(&mut b);
        b
    };
    let header_len = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
    let mut nan = bytes.clone();
    nan[16 + header_len..16 + header_len + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    expect_error(&reseal(nan), "not finite");
    let mut version = bytes.clone();
    version[8] = 9;
    expect_error(&reseal(version), "format version 9");
    let mut short = bytes[..bytes.len() - 12].to_vec();
    short.extend_from_slice(&[0; 4]);
    expect_error(&reseal(short), "payload bytes");
    let mut long_header = bytes.clone();
    long_header[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    expect_error(&reseal(long_header), "header length");
}

#[test]
fn rays_that_miss_the_matter_cost_no_query_and_the_rest_are_the_network() {
    let m = model(6, 16, 1);
    let kernel = NelfKernel::new(m.clone());
    // Through the occupied centre cell, beside it, and away from everything.
    let rays = [
        (Vec3::new(0.1, -5.0, 0.1), Vec3::Y),
        (Vec3::new(0.9, -5.0, 0.9), Vec3::Y),
        (Vec3::new(0.1, -5.0, 0.1), -Vec3::Y),
    ];
    let mut scratch = NelfScratch::new();
    let mut out = Vec::new();
    kernel.render_rays_into(&rays, &mut scratch, &mut out);
    assert_eq!(out.iter().map(|r| r.queried).collect::<Vec<_>>(), [true, false, false]);
    assert_eq!(out[1], NelfRay::default());
    // The first equals the network on the encoded ray.
    let s = &m.header.sampling;
    let (t0, t1) = s.segment(rays[0].0, rays[0].1).expect("segment");
    let mut input = vec![0.0; s.input_len()];
    s.encode(rays[0].0, rays[0].1, t0, t1, &mut Vec::new(), &mut input);
    let mut y = vec![0.0; NELF_OUTPUTS];
    m.network.infer(&input, &mut y, &mut nephele_nn::ResidualWorkspace::new()).expect("infer");
    assert_eq!(out[0].opacity, y[3]);
    assert_eq!(out[0].distance, t0 + y[4] * (t1 - t0));
    assert!(out[0].color.iter().all(|&c| (0.0..=out[0].opacity).contains(&c)));

    // A frame: only pixels whose rays cross the centre cell are queried; everything finite.
    let camera = Camera::look_at(24, 16, 0.7, Vec3::new(0.0, -6.0, 0.5), Vec3::ZERO, Vec3::Z).expect("camera");
    let (frame, stats) = kernel.render_pixels(&camera, &all_pixels(&camera)).expect("frame");
    assert_eq!(stats.rays, 24 * 16);
    assert!(stats.queries > 0 && stats.queries < stats.rays / 4, "{stats:?}");
    assert_eq!(stats.rays_hit, stats.queries);
    assert!(frame.color.iter().flatten().chain(&frame.opacity).chain(&frame.depth).all(|v| v.is_finite()));
    let covered = frame.opacity.iter().filter(|&&a| a > 0.0).count() as u64;
    assert!(covered <= stats.queries);
    assert!(kernel.render_pixels(&camera, &[24 * 16]).is_err());
}

mod mutated_files {
    use proptest::prelude::*;

    use super::*;

    proptest! {
        #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]
        /// Mutated bytes with a fresh checksum (what a fuzzer reaches; `kernels/fuzz`'s
        /// `model_load` target runs the same without end) decode to a model or a typed error,
        /// never a panic; a model that decodes renders finite values. Half of the mutations
        /// land in the JSON header, which a uniform choice would seldom hit.
        #[test]
        fn decode_to_a_model_or_an_error(
            edits in prop::collection::vec((any::<bool>(), any::<u32>(), any::<u8>()), 1..6),
            cut in prop::option::of(any::<u32>()),
        ) {
            let mut bytes = model(2, 8, 1).to_bytes();
            let header_end = 16 + u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]) as usize;
            for (in_header, at, value) in edits {
                let span = if in_header { header_end } else { bytes.len() };
                let at = at as usize % span;
                bytes[at] = value;
            }
            if let Some(cut) = cut {
                bytes.truncate(cut as usize % bytes.len());
            }
            crate::assets::reseal_trailing_crc(&mut bytes);
            if let Ok(m) = NelfModel::from_bytes(&bytes) {
                let kernel = NelfKernel::new(m);
                let camera = Camera::look_at(8, 8, 0.7, Vec3::new(0.0, -6.0, 0.5), Vec3::ZERO, Vec3::Z).expect("camera");
                let (frame, _) = kernel.render_pixels(&camera, &all_pixels(&camera)).expect("render");
                prop_assert!(frame.color.iter().flatten().chain(&frame.opacity).chain(&frame.depth).all(|v| v.is_finite()));
            }
        }
    }
}

mod nasty_rays {
    use proptest::prelude::*;

    use super::*;

    fn component() -> impl Strategy<Value = f32> {
        prop_oneof![
            -3.0f32..3.0,
            Just(0.0f32),
            Just(-0.0f32),
            Just(1e-40f32),
            Just(1e30f32),
            Just(-1e30f32),
            Just(f32::NAN),
            Just(f32::INFINITY),
            Just(f32::NEG_INFINITY),
            Just(f32::MAX),
        ]
    }

    proptest! {
        /// Any ray, however broken, is answered with finite values in range, and queried
        /// only where the matter is.
        #[test]
        fn any_ray_gets_a_finite_answer(
            rays in prop::collection::vec(((component(), component(), component()), (component(), component(), component())), 1..40)
        ) {
            let kernel = NelfKernel::new(model(4, 8, 1));
            let rays: Vec<(Vec3, Vec3)> = rays
                .into_iter()
                .map(|((a, b, c), (d, e, f))| (Vec3::new(a, b, c), Vec3::new(d, e, f).normalize_or_zero()))
                .collect();
            let mut out = Vec::new();
            kernel.render_rays_into(&rays, &mut NelfScratch::new(), &mut out);
            prop_assert_eq!(out.len(), rays.len());
            for (r, &(o, d)) in out.iter().zip(&rays) {
                prop_assert!(r.color.iter().chain([&r.opacity, &r.distance]).all(|v| v.is_finite()), "{:?} for {:?}", r, (o, d));
                prop_assert!((0.0..=1.0).contains(&r.opacity));
                if r.queried {
                    prop_assert!(o.is_finite() && d.is_finite() && r.distance >= 0.0);
                }
            }
        }
    }
}

#[test]
fn the_march_within_the_segment_answers_as_the_whole_march() {
    // A grid with a few clusters of occupied cells, and the box around them (the sampling
    // box a distillation takes from its teacher).
    let resolution: u32 = 32;
    let mut rng = nephele_geometry::SplitMix64::new(5);
    let flags: Vec<bool> = (0..resolution * resolution * resolution)
        .map(|i| {
            let (x, y, z) = (i % resolution, (i / resolution) % resolution, i / (resolution * resolution));
            let near = |c: [u32; 3], r: u32| x.abs_diff(c[0]) <= r && y.abs_diff(c[1]) <= r && z.abs_diff(c[2]) <= r;
            (near([9, 12, 14], 3) || near([20, 18, 11], 2)) && rng.next_f32() < 0.3
        })
        .collect();
    let grid = OccupancyGrid::from_flags(resolution, &flags).expect("grid");
    let (lo, hi) = grid.occupied_bounds().expect("occupied");
    let placement = MatterPlacement { min: [-1.0; 3], size: 2.0, step: 2.0 * 3f32.sqrt() / 256.0, resolution };
    let matter = MatterGrid::new(placement, grid).expect("matter");
    let to_world = |u: Vec3| Vec3::splat(-1.0) + u * 2.0;
    let s = RaySampling { points: 4, frequencies: 1, min: to_world(lo).to_array(), max: to_world(hi).to_array() };
    let (mut hits, mut rays) = (0, 0);
    for i in 0..20_000 {
        let unit = |rng: &mut nephele_geometry::SplitMix64| {
            Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE
        };
        // Rays from outside at the clusters, and rays from inside the box.
        let origin = if i % 4 == 0 { unit(&mut rng) * 0.5 } else { unit(&mut rng).normalize_or(Vec3::Z) * 3.0 };
        let dir = (to_world((lo + hi) * 0.5) + unit(&mut rng) * 0.4 - origin).normalize_or(Vec3::X);
        let full = matter.hits(origin, dir);
        let within = s.segment(origin, dir).is_some_and(|seg| matter.hits_within(origin, dir, seg));
        assert_eq!(full, within, "ray {origin} {dir}");
        hits += usize::from(full);
        rays += 1;
    }
    assert!(hits > rays / 10 && hits < rays, "{hits} of {rays}");
}
