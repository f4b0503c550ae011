//! The WGSL U-Net against the CPU forward (`nephele_nn::UNet::forward`): random networks of
//! one and two eyes, one to three levels, inputs with zeros and negatives, image sides that
//! are not powers of two. Tolerance: every output within 1e-4 of the CPU's, relative to the
//! larger of 1 and its magnitude (float summation in the same order, FMA contraction aside).

use nephele_nn::{UNet, UNetConfig, UNetWorkspace};

use crate::GpuUNet;
use crate::tests::context;

const TOLERANCE: f32 = 1e-4;

fn inputs(n: usize, seed: u32) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let h = (i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed.wrapping_mul(40_503)) >> 8;
            // A quarter zeros (the CPU skips them), the rest in [-2, 2).
            if h.is_multiple_of(4) { 0.0 } else { (h % 4096) as f32 / 1024.0 - 2.0 }
        })
        .collect()
}

#[test]
fn the_wgsl_unet_agrees_with_the_cpu_forward() {
    let ctx = context();
    for (eyes, channels, (w, h), seed) in [
        (1, vec![4], (7, 5), 1),
        (1, vec![4, 8], (12, 6), 2),
        (2, vec![4, 8], (10, 8), 3),
        (1, vec![8, 16, 32], (24, 16), 4),
        (2, vec![16, 32, 64], (20, 12), 5),
    ] {
        let config = UNetConfig { inputs: 13, eyes, outputs: 3, channels };
        let net = UNet::new(config.clone(), seed).expect("network");
        let input = inputs(w * h * eyes * 13, seed as u32);
        let mut ws = UNetWorkspace::new();
        let cpu: Vec<Vec<f32>> = net.forward(w, h, &input, &mut ws).expect("cpu").iter().map(|s| s.to_vec()).collect();
        let gpu = GpuUNet::new(ctx.clone(), &net).expect("gpu network").forward(w, h, &input).expect("gpu");
        assert_eq!(gpu.len(), eyes);
        for (c, g) in cpu.iter().zip(&gpu) {
            assert_eq!(c.len(), g.len());
            for (i, (a, b)) in c.iter().zip(g).enumerate() {
                assert!(
                    b.is_finite() && (a - b).abs() <= TOLERANCE * a.abs().max(1.0),
                    "{config:?} {w}x{h} [{i}]: cpu {a} gpu {b}"
                );
            }
        }
    }
}

/// The masked pass (the room's pixels that objects cover are not shaded) against the CPU's:
/// masks with a covered blob, isolated pixels, whole borders and nothing at all; the needed
/// pixels within the tolerance of the CPU's, every other output pixel exactly 0 on both.
#[test]
fn the_masked_wgsl_unet_agrees_with_the_cpu_masked_forward() {
    use nephele_nn::PixelMask;
    let ctx = context();
    for (eyes, channels, (w, h), seed) in [(1, vec![4, 8], (16, 12), 6), (2, vec![8, 16, 32], (24, 16), 7)] {
        let config = UNetConfig { inputs: 13, eyes, outputs: 3, channels };
        let net = UNet::new(config.clone(), seed).expect("network");
        let gpu_net = GpuUNet::new(ctx.clone(), &net).expect("gpu network");
        let input = inputs(w * h * eyes * 13, seed as u32);
        let blob = move |x: usize, y: usize| !(x > w / 4 && x < 3 * w / 4 && y > h / 5 && y < 4 * h / 5);
        type Selects = Box<dyn Fn(usize, usize) -> bool>;
        let masks: [(&str, Selects); 4] = [
            ("outside a covered blob", Box::new(blob)),
            ("isolated pixels", Box::new(|x, y| (x * 7 + y * 3) % 11 == 0)),
            ("the borders", Box::new(move |x, y| x == 0 || y == 0 || x == w - 1 || y == h - 1)),
            ("nothing", Box::new(|_, _| false)),
        ];
        for (what, selected) in masks {
            let flags: Vec<bool> = (0..w * h).map(|p| selected(p % w, p / w)).collect();
            let needed = PixelMask::from_flags(w, h, flags.clone()).expect("mask");
            let mut ws = UNetWorkspace::new();
            let cpu: Vec<Vec<f32>> = net
                .forward_masked(w, h, &input, Some(&needed), &mut ws)
                .expect("cpu")
                .iter()
                .map(|s| s.to_vec())
                .collect();
            let gpu = gpu_net.forward_masked(w, h, &input, Some(&needed)).expect("gpu");
            assert_eq!(gpu.len(), eyes);
            for (c, g) in cpu.iter().zip(&gpu) {
                for (i, (a, b)) in c.iter().zip(g).enumerate() {
                    if !flags[i / 3] {
                        assert!(*a == 0.0 && *b == 0.0, "{what} {w}x{h} [{i}]: not needed, cpu {a} gpu {b}");
                    }
                    assert!(
                        b.is_finite() && (a - b).abs() <= TOLERANCE * a.abs().max(1.0),
                        "{what} {config:?} {w}x{h} [{i}]: cpu {a} gpu {b}"
                    );
                }
            }
        }
    }
}

#[test]
fn bad_sizes_and_inputs_are_refused() {
    let net = UNet::new(UNetConfig { inputs: 13, eyes: 1, outputs: 3, channels: vec![4, 8] }, 1).expect("net");
    let gpu = GpuUNet::new(context(), &net).expect("gpu network");
    assert!(gpu.forward(7, 6, &vec![0.0; 7 * 6 * 13]).is_err(), "odd width for two levels");
    assert!(gpu.forward(8, 6, &[0.0; 10]).is_err(), "input length");
}

/// The farm's GI kernel loaded through the asset registry with the GPU as accelerator (its
/// networks on the device, the G-buffer on the CPU) against the same files on the CPU: a view,
/// a band of it and a stereo pair agree within the tolerance (on the decoded colour,
/// `exp(x) - 1`, relative to the larger of 1 and its magnitude), depth exactly.
#[test]
fn the_served_gi_kernel_on_the_device_agrees_with_the_cpu() {
    use nephele_geometry::camera::{Camera, stereo_pair};
    use nephele_kernels::assets::{LoadOptions, load_by_magic};
    use nephele_kernels::gi::{GI_INPUTS, GI_OUTPUTS, GiFeatures, GiModel};

    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("room.ngi");
    let features = GiFeatures { centre: [0.0, 0.0, 1.4], scale: 2.5 };
    for (eyes, file, seed) in [(1, path.clone(), 11), (2, nephele_kernels::environment::stereo_path(&path), 12)] {
        let config = UNetConfig { inputs: GI_INPUTS, eyes, outputs: GI_OUTPUTS, channels: vec![8, 16, 32] };
        let mut model =
            GiModel::new(UNet::new(config, seed).expect("net"), features, serde_json::Value::Null).expect("model");
        model.header.scene = Some("room-day".into());
        model.save(&file).expect("saved");
    }
    let cpu = load_by_magic(&path, &LoadOptions::default()).expect("CPU kernel");
    let accelerator = crate::GpuAccelerator(context());
    let options = LoadOptions { accelerator: Some(std::sync::Arc::new(accelerator)), ..LoadOptions::default() };
    let gpu = load_by_magic(&path, &options).expect("GPU kernel");

    let view =
        Camera::look_at(40, 24, 1.2, glam::Vec3::new(0.0, -1.2, 1.5), glam::Vec3::new(0.5, 1.0, 1.0), glam::Vec3::Z)
            .expect("camera");
    let all: Vec<u32> = (0..40 * 24).collect();
    let band: Vec<u32> = (8 * 40..16 * 40).collect();
    let agree = |what: &str, a: &nephele_kernels::kernel::PixelResults, b: &nephele_kernels::kernel::PixelResults| {
        assert_eq!(a.depth, b.depth, "{what}: depth");
        assert_eq!(a.opacity, b.opacity, "{what}: opacity");
        for (i, (x, y)) in a.color.iter().flatten().zip(b.color.iter().flatten()).enumerate() {
            assert!(y.is_finite() && (x - y).abs() <= TOLERANCE * x.abs().max(1.0), "{what} [{i}]: cpu {x} gpu {y}");
        }
    };
    for pixels in [&all, &band] {
        let (a, _) = cpu.render_pixels(&view, pixels).expect("CPU render");
        let (b, _) = gpu.render_pixels(&view, pixels).expect("GPU render");
        agree("one view", &a, &b);
    }
    let eyes = stereo_pair(&view, 0.064).expect("eyes");
    let pair = |k: &dyn nephele_kernels::kernel::RayKernel| {
        k.render_pair((&eyes[0], &all), (&eyes[1], &band)).expect("a stereo pass").expect("rendered").0
    };
    let ([l_cpu, r_cpu], [l_gpu, r_gpu]) = (pair(cpu.as_ref()), pair(gpu.as_ref()));
    agree("left eye", &l_cpu, &l_gpu);
    agree("right eye", &r_cpu, &r_gpu);
}
