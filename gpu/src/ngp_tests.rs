//! The GPU baseline against its CPU twin: a radiance field of the default network sizes whose occupancy holds a
//! sphere and a box in a corner (empty blocks and cells to skip), densities from random
//! hash-grid features (soft, fractional opacities; early stops inside the sphere), the
//! colour network on every sample that matters. Tolerances as for i-NOLF (`tests.rs`).

use std::sync::OnceLock;

use glam::Vec3;
use proptest::prelude::*;

use crate::tests::{MAX_COLOR_MEAN_ABS, camera_strategy, check_agreement, check_sane, context};
use crate::{Agreement, GpuNgpKernel};
use nephele_geometry::camera::Camera;
use nephele_kernels::kernel::{RayKernel, all_pixels};
use nephele_kernels::ngp::{FieldConfig, NgpKernel, OccupancyGrid, RadianceField};
use nephele_nn::HashGridConfig;

struct Fixture {
    cpu: NgpKernel,
    gpu: GpuNgpKernel,
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        // The default (i-NGP) network sizes, so that loop trip counts are those of a real
        // field (llvmpipe caps them per invocation; see `ngp.wgsl`), with a smaller table.
        let config = FieldConfig {
            grid: HashGridConfig::with_finest_resolution(16, 14, 16, 2048),
            steps_per_diagonal: 512,
            occupancy_resolution: 32,
            ..FieldConfig::default()
        };
        let mut field = RadianceField::new(config, Vec3::splat(-1.0), 2.0, 5).expect("field");
        // Features of order one, so that density and colour vary in space.
        for (i, f) in field.grid.params_mut().iter_mut().enumerate() {
            *f = ((i as u32).wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32 * 4.0 - 2.0;
        }
        // Raise the raw density so that rays stop inside the sphere: a ray through fog with
        // more than about 170 coloured samples would be cut short by llvmpipe's cap on loop
        // iterations per invocation (see `ngp.wgsl`), which CI runs on; real GPUs have none.
        let d = field.density.config();
        let bias = d.input * d.hidden + d.hidden + d.hidden * d.output;
        field.density.params_mut()[bias] += 4.0;
        let r = config.occupancy_resolution;
        let flags: Vec<bool> = (0..(r as usize).pow(3))
            .map(|i| {
                let c = field.occupancy.cell_center(i) * 2.0 - Vec3::ONE;
                c.length() < 0.55 || (c - Vec3::new(0.75, -0.75, 0.75)).abs().max_element() < 0.12
            })
            .collect();
        field.occupancy = OccupancyGrid::from_flags(r, &flags).expect("occupancy");
        let cpu = NgpKernel::new(field);
        let gpu = GpuNgpKernel::new(context(), &cpu).expect("gpu baseline");
        Fixture { cpu, gpu }
    })
}

#[test]
fn baseline_frames_agree_with_the_cpu_kernel() {
    let f = fixture();
    let views = [
        (Vec3::new(2.5, -1.5, 1.0), Vec3::ZERO),
        (Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO),
        (Vec3::new(0.1, 0.05, 0.0), Vec3::new(1.0, 0.2, 0.3)),
        (Vec3::new(0.0, -3.0, 0.0), Vec3::new(0.0, -6.0, 0.0)),
    ];
    let mut hits = 0;
    for (eye, target) in views {
        let up = if (target - eye).normalize().z.abs() > 0.9 { Vec3::Y } else { Vec3::Z };
        let camera = Camera::look_at(33, 25, 0.9, eye, target, up).expect("camera");
        let pixels = all_pixels(&camera);
        let (cpu, cpu_stats) = f.cpu.render_pixels(&camera, &pixels).expect("cpu");
        let (gpu, gpu_stats) = f.gpu.render_pixels(&camera, &pixels).expect("gpu");
        check_sane(&gpu).unwrap_or_else(|e| panic!("view from {eye}: {e}"));
        check_agreement(&Agreement::of(&cpu, &gpu)).unwrap_or_else(|e| panic!("view from {eye}: {e}"));
        // The same rays reach matter; the GPU may count fewer samples (it stops counting
        // at the early-stop sample, the CPU at the end of its 16-sample chunk).
        assert_eq!(gpu_stats.rays_hit, cpu_stats.rays_hit, "view from {eye}");
        assert!(gpu_stats.queries <= cpu_stats.queries);
        hits += gpu.opacity.iter().filter(|&&o| o > 0.0).count();
    }
    assert!(hits > 400, "{hits} pixels see the field");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn baseline_random_cameras_agree_with_the_cpu_kernel(camera in camera_strategy()) {
        let f = fixture();
        let pixels = all_pixels(&camera);
        let (cpu, _) = f.cpu.render_pixels(&camera, &pixels).expect("cpu");
        let (gpu, _) = f.gpu.render_pixels(&camera, &pixels).expect("gpu");
        check_sane(&gpu)?;
        let a = Agreement::of(&cpu, &gpu);
        prop_assert_eq!(a.non_finite, 0);
        prop_assert!(a.mask_mismatches <= 2, "{}", a);
        prop_assert!(a.depth_mismatches <= 2, "{}", a);
        prop_assert!(a.color_mean_abs < MAX_COLOR_MEAN_ABS, "{}", a);
    }
}
