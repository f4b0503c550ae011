//! One module per subcommand; each parses its own arguments and calls into the libraries.

pub mod bake;
pub mod composer;
pub mod dataset;
pub mod eval;
pub mod first_start;
pub mod loadgen;
pub mod master;
pub mod pathtrace;
pub mod probe;
pub mod render;
pub mod scenes;
pub mod simulate;
pub mod train;
pub mod train_gi;
pub mod up;
pub mod worker;

use anyhow::Result;
use glam::Vec3;

pub use nephele_geometry::camera::parse_size;

/// Parses `x,y,z` into a finite vector.
pub fn parse_vec3(text: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = text.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("expected x,y,z, got '{text}'"));
    }
    let mut v = [0.0f32; 3];
    for (slot, part) in v.iter_mut().zip(parts) {
        *slot = part.trim().parse().map_err(|_| format!("'{part}' is not a number"))?;
        if !slot.is_finite() {
            return Err(format!("'{part}' is not finite"));
        }
    }
    Ok(Vec3::from(v))
}

/// Parses a background colour name or `r,g,b` in [0, 1].
pub fn parse_background(text: &str) -> Result<[f32; 3], String> {
    match text {
        "white" => Ok([1.0; 3]),
        "black" => Ok([0.0; 3]),
        _ => {
            let v = parse_vec3(text).map_err(|e| format!("{e} (or use 'white' / 'black')"))?;
            if v.min_element() < 0.0 || v.max_element() > 1.0 {
                return Err(format!("background '{text}' must lie in [0, 1]"));
            }
            Ok(v.to_array())
        }
    }
}

/// Opens the device `--device` asks for: the kernels' accelerator (`None` for the CPU) and
/// the label a worker reports (`cpu (AVX2+FMA)`, or the GPU adapter's name).
pub fn open_device(
    choice: nephele_gpu::DeviceChoice,
    simd: nephele_nn::SimdMode,
) -> Result<(Option<std::sync::Arc<dyn nephele_kernels::assets::Accelerator>>, String)> {
    use anyhow::Context;
    let accelerator = nephele_gpu::accelerator(choice).with_context(|| format!("--device {choice}"))?;
    let label = match &accelerator {
        Some(gpu) => gpu.label(),
        None => format!("cpu ({})", simd.describe()),
    };
    tracing::info!(device = %label, asked = %choice, "kernels' device");
    Ok((accelerator, label))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_vectors_and_backgrounds_parse_or_fail_clearly() {
        assert_eq!(parse_size("800x600"), Ok((800, 600)));
        assert!(parse_size("0x10").is_err());
        assert!(parse_size("800").is_err());
        assert!(parse_size("99999x10").is_err());
        assert_eq!(parse_vec3("1, 2,3"), Ok(Vec3::new(1.0, 2.0, 3.0)));
        assert!(parse_vec3("1,2").is_err());
        assert!(parse_vec3("1,nan,2").is_err());
        assert_eq!(parse_background("white"), Ok([1.0; 3]));
        assert!(parse_background("2,0,0").is_err());
    }
}
