//! The stereo neural global-illumination kernel's model (Zhang and Simo-Serra; the design's
//! "Stereo GI"): a U-Net ([`nephele_nn::UNet`]) from a rasterised view's G-buffer and direct
//! light to its global illumination, one eye or both eyes in one pass, and its file format.
//!
//! Per pixel the network sees [`GI_INPUTS`] values ([`GiFeatures::encode`]): the world
//! position relative to the environment's centre and scale, the shading normal, the albedo,
//! the view depth over the scale, and `ln(1 + direct light)`; it predicts `ln(1 + GI)` per
//! channel ([`decode_output`]), a range where the sunlit floor and the dark corners weigh
//! alike in a squared loss.
//!
//! A `.ngi` file: `NGI1`, a little-endian `u32` format version, the length of a JSON header
//! and the header (network shape, feature scales, a free-form description of the training),
//! the parameters as little-endian `f32`, and a CRC-32 of everything before it. Loading
//! checks every part and refuses NaN or infinite parameters.

use std::path::Path;

use nephele_nn::{NnError, PixelMask, UNet, UNetConfig, UNetWorkspace};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Inputs per pixel and eye: position 3, normal 3, albedo 3, depth 1, direct light 3.
pub const GI_INPUTS: usize = 13;
/// Outputs per pixel and eye: RGB in `ln(1 + x)`.
pub const GI_OUTPUTS: usize = 3;
/// First bytes of a `.ngi` file.
pub const GI_MAGIC: &[u8; 4] = b"NGI1";
/// Version of the layout after the magic.
pub const GI_FORMAT_VERSION: u32 = 1;

/// How G-buffer values are scaled into the network's range, fixed per environment.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GiFeatures {
    /// Centre of the environment (world units).
    pub centre: [f32; 3],
    /// Half the environment's largest side: positions and depths are divided by it.
    pub scale: f32,
}

/// One pixel of a G-buffer.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GBufferPixel {
    pub position: [f32; 3],
    pub normal: [f32; 3],
    pub albedo: [f32; 3],
    pub depth: f32,
    pub direct: [f32; 3],
}

impl GiFeatures {
    /// Writes the network inputs of `pixel` into `out` (`GI_INPUTS` values). Values that are
    /// NaN or infinite are written as 0; returns how many there were.
    pub fn encode(&self, pixel: &GBufferPixel, out: &mut [f32]) -> usize {
        let mut bad = 0;
        let mut clean = |v: f32| {
            if v.is_finite() {
                v
            } else {
                bad += 1;
                0.0
            }
        };
        let s = 1.0 / self.scale;
        for i in 0..3 {
            out[i] = clean((pixel.position[i] - self.centre[i]) * s);
            out[3 + i] = clean(pixel.normal[i]);
            out[6 + i] = clean(pixel.albedo[i]);
            out[10 + i] = clean(pixel.direct[i]).max(0.0).ln_1p();
        }
        out[9] = clean(pixel.depth * s);
        // A clean but absurd value (a depth of 1e30) stays finite and is clamped.
        out[..GI_INPUTS].iter_mut().for_each(|v| *v = v.clamp(-64.0, 64.0));
        bad
    }

    /// Inputs of a whole image (`GI_INPUTS` per pixel) and the count of non-finite values.
    pub fn encode_image(&self, pixels: &[GBufferPixel]) -> (Vec<f32>, usize) {
        let mut out = vec![0.0; pixels.len() * GI_INPUTS];
        let bad = pixels.iter().zip(out.chunks_exact_mut(GI_INPUTS)).map(|(p, o)| self.encode(p, o)).sum();
        (out, bad)
    }
}

/// Largest network output decoded: `exp(30) - 1`, about 1e13, is far above any radiance a
/// scene holds, and `exp` of anything over 88.7 would be infinite in f32.
pub const MAX_OUTPUT: f32 = 30.0;

/// Linear radiance from one network output value (`ln(1 + x)`, clamped into
/// `[0, MAX_OUTPUT]`).
pub fn decode_output(value: f32) -> f32 {
    if value.is_finite() { value.clamp(0.0, MAX_OUTPUT).exp_m1() } else { 0.0 }
}

/// The network target of a linear radiance value.
pub fn encode_target(radiance: f32) -> f32 {
    if radiance.is_finite() { radiance.max(0.0).ln_1p() } else { 0.0 }
}

/// The JSON header of a `.ngi` file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiHeader {
    pub network: UNetConfig,
    pub features: GiFeatures,
    /// The built-in scene the model was trained on (the environment a worker renders the
    /// G-buffer of when it serves the model); absent in models from before serving existed.
    #[serde(default)]
    pub scene: Option<String>,
    /// How it was trained (free-form).
    #[serde(default)]
    pub training: serde_json::Value,
}

#[derive(Debug, Error)]
pub enum GiModelError {
    #[error("{0}")]
    Format(String),
    #[error("network: {0}")]
    Network(#[from] NnError),
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("U-Net on {device}: {message}")]
    Device { device: String, message: String },
}

/// A U-Net's forward pass on another device than the CPU: the GPU crate's WGSL twin
/// (`nephele_gpu::GpuUNet`), resident there with its parameters. The same inputs and outputs
/// as [`UNet::forward_masked`] (pixel-major, eyes interleaved; one output image per head, left
/// first; with `needed`, only those output pixels computed, the others 0).
pub trait UNetDevice: Send + Sync + std::fmt::Debug {
    fn forward(
        &self,
        width: usize,
        height: usize,
        input: &[f32],
        needed: Option<&PixelMask>,
    ) -> Result<Vec<Vec<f32>>, String>;
    /// The device, for logs and errors.
    fn label(&self) -> String;
}

/// A trained GI network and how its inputs are scaled.
#[derive(Debug, Clone, PartialEq)]
pub struct GiModel {
    pub header: GiHeader,
    pub network: UNet,
}

impl GiModel {
    pub fn new(network: UNet, features: GiFeatures, training: serde_json::Value) -> Result<GiModel, GiModelError> {
        let config = network.config();
        if config.inputs != GI_INPUTS || config.outputs != GI_OUTPUTS {
            return Err(GiModelError::Format(format!(
                "a GI network takes {GI_INPUTS} inputs and gives {GI_OUTPUTS} outputs per eye, not {} and {}",
                config.inputs, config.outputs
            )));
        }
        if !(features.scale.is_finite() && features.scale > 0.0 && features.centre.iter().all(|c| c.is_finite())) {
            return Err(GiModelError::Format(format!("feature scales {features:?}")));
        }
        Ok(GiModel { header: GiHeader { network: config.clone(), features, scene: None, training }, network })
    }

    /// Eyes per pass: 1 (single-eye model) or 2 (stereo).
    pub fn eyes(&self) -> usize {
        self.network.config().eyes
    }

    pub fn to_bytes(&self) -> Vec<u8> {
        let header = serde_json::to_vec(&self.header).unwrap_or_default();
        let mut out = Vec::with_capacity(16 + header.len() + 4 * self.network.params().len());
        out.extend_from_slice(GI_MAGIC);
        out.extend_from_slice(&GI_FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
        out.extend_from_slice(&header);
        for p in self.network.params() {
            out.extend_from_slice(&p.to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    pub fn from_bytes(bytes: &[u8]) -> Result<GiModel, GiModelError> {
        let bad = |why: String| GiModelError::Format(why);
        if bytes.len() < 16 || &bytes[..4] != GI_MAGIC {
            return Err(bad("not a GI model (no NGI1 header)".into()));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        let crc = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
        if crc32fast::hash(body) != crc {
            return Err(bad("checksum mismatch: the file is damaged or truncated".into()));
        }
        let word = |at: usize| u32::from_le_bytes([body[at], body[at + 1], body[at + 2], body[at + 3]]);
        let version = word(4);
        if version != GI_FORMAT_VERSION {
            return Err(bad(format!("format version {version}; this build reads {GI_FORMAT_VERSION}")));
        }
        let header_len = word(8) as usize;
        let header_end =
            12usize.checked_add(header_len).filter(|&e| e <= body.len()).ok_or_else(|| bad("header length".into()))?;
        let header: GiHeader =
            serde_json::from_slice(&body[12..header_end]).map_err(|e| bad(format!("header: {e}")))?;
        header.network.validate()?;
        let rest = &body[header_end..];
        if rest.len() != 4 * header.network.param_count() {
            return Err(bad(format!(
                "{} parameter bytes for a network of {} parameters",
                rest.len(),
                header.network.param_count()
            )));
        }
        let params = rest.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
        let network = UNet::from_params(header.network.clone(), params)?;
        let mut model = GiModel::new(network, header.features, header.training)?;
        model.header.scene = header.scene;
        Ok(model)
    }

    pub fn save(&self, path: &Path) -> Result<(), GiModelError> {
        let io = |source| GiModelError::Io { path: path.display().to_string(), source };
        let tmp = path.with_extension("ngi.part");
        std::fs::write(&tmp, self.to_bytes()).map_err(io)?;
        std::fs::rename(&tmp, path).map_err(io)
    }

    pub fn load(path: &Path) -> Result<GiModel, GiModelError> {
        let bytes =
            std::fs::read(path).map_err(|source| GiModelError::Io { path: path.display().to_string(), source })?;
        GiModel::from_bytes(&bytes)
    }

    /// Global illumination of `eyes()` views of `width x height` from their G-buffers (one
    /// slice per eye, left first).
    pub fn shade(
        &self,
        width: usize,
        height: usize,
        eyes: &[&[GBufferPixel]],
        ws: &mut UNetWorkspace,
    ) -> Result<Shaded, GiModelError> {
        self.shade_where(width, height, eyes, None, ws)
    }

    /// [`Self::shade`] for the pixels `needed` selects (every pixel when `None`): the network
    /// computes only what those pixels read ([`nephele_nn::UNet::forward_masked`]), the
    /// others come out black.
    pub fn shade_where(
        &self,
        width: usize,
        height: usize,
        eyes: &[&[GBufferPixel]],
        needed: Option<&PixelMask>,
        ws: &mut UNetWorkspace,
    ) -> Result<Shaded, GiModelError> {
        let (input, bad) = self.inputs(width, height, eyes)?;
        let heads = self.network.forward_masked(width, height, &input, needed, ws)?;
        Ok(Shaded { eyes: heads.iter().map(|head| decode_image(head)).collect(), non_finite_inputs: bad })
    }

    /// [`Self::shade_where`] with the network run on `device` (which must hold this model's
    /// network: [`UNetDevice`]).
    pub fn shade_on(
        &self,
        device: &dyn UNetDevice,
        width: usize,
        height: usize,
        eyes: &[&[GBufferPixel]],
        needed: Option<&PixelMask>,
    ) -> Result<Shaded, GiModelError> {
        let (input, bad) = self.inputs(width, height, eyes)?;
        let failed = |message: String| GiModelError::Device { device: device.label(), message };
        let heads = device.forward(width, height, &input, needed).map_err(failed)?;
        let expected = width * height * GI_OUTPUTS;
        if heads.len() != self.eyes() || heads.iter().any(|h| h.len() != expected) {
            return Err(failed(format!("{} heads for a {}-eye model", heads.len(), self.eyes())));
        }
        Ok(Shaded { eyes: heads.iter().map(|head| decode_image(head)).collect(), non_finite_inputs: bad })
    }

    /// The network's input for the eyes' G-buffers, and how many values were not finite.
    fn inputs(&self, width: usize, height: usize, eyes: &[&[GBufferPixel]]) -> Result<(Vec<f32>, usize), GiModelError> {
        if eyes.len() != self.eyes() || eyes.iter().any(|e| e.len() != width * height) {
            return Err(GiModelError::Format(format!(
                "{} eye images for a {}-eye model of {width}x{height}",
                eyes.len(),
                self.eyes()
            )));
        }
        let per_pixel = self.eyes() * GI_INPUTS;
        let mut input = vec![0.0; width * height * per_pixel];
        let mut bad = 0;
        for (eye, pixels) in eyes.iter().enumerate() {
            for (p, pixel) in pixels.iter().enumerate() {
                bad += self.header.features.encode(pixel, &mut input[p * per_pixel + eye * GI_INPUTS..][..GI_INPUTS]);
            }
        }
        Ok((input, bad))
    }
}

/// One head's output as linear RGB per pixel.
fn decode_image(head: &[f32]) -> Vec<[f32; 3]> {
    head.chunks_exact(GI_OUTPUTS).map(|c| [decode_output(c[0]), decode_output(c[1]), decode_output(c[2])]).collect()
}

/// What [`GiModel::shade`] gives.
#[derive(Debug, Clone, PartialEq)]
pub struct Shaded {
    /// Linear RGB per pixel, one image per eye (left first).
    pub eyes: Vec<Vec<[f32; 3]>>,
    /// G-buffer values that were NaN or infinite and were read as 0.
    pub non_finite_inputs: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(eyes: usize) -> GiModel {
        let config = UNetConfig { inputs: GI_INPUTS, eyes, outputs: GI_OUTPUTS, channels: vec![4, 8] };
        let features = GiFeatures { centre: [0.0, 0.0, 1.4], scale: 2.5 };
        GiModel::new(UNet::new(config, 1).expect("net"), features, serde_json::json!({"steps": 0})).expect("model")
    }

    #[test]
    fn files_round_trip_and_damage_is_refused() {
        let m = model(2);
        let bytes = m.to_bytes();
        assert_eq!(GiModel::from_bytes(&bytes).expect("decode"), m);
        let mut flipped = bytes.clone();
        flipped[40] ^= 1;
        assert!(GiModel::from_bytes(&flipped).expect_err("crc").to_string().contains("checksum"));
        assert!(GiModel::from_bytes(&bytes[..bytes.len() - 9]).is_err());
        assert!(GiModel::from_bytes(b"NOLF and more bytes").is_err());
        let mut later = bytes.clone();
        later[4] = 9;
        crate::assets::reseal_trailing_crc(&mut later);
        assert!(GiModel::from_bytes(&later).expect_err("version").to_string().contains("version 9"));
        let wrong = UNet::new(UNetConfig { inputs: 5, eyes: 1, outputs: 3, channels: vec![4] }, 0).expect("net");
        assert!(GiModel::new(wrong, m.header.features, serde_json::Value::Null).is_err());
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 300, ..Default::default() })]
        /// Mutated bytes with a fresh checksum (as `kernels/fuzz`'s `model_load` target makes
        /// them) decode to a model or a typed error, never a panic. Half of the mutations land
        /// in the JSON header.
        #[test]
        fn mutated_files_decode_to_a_model_or_an_error(
            edits in proptest::collection::vec((proptest::bool::ANY, proptest::num::u32::ANY, proptest::num::u8::ANY), 1..6),
            cut in proptest::option::of(proptest::num::u32::ANY),
        ) {
            let mut bytes = model(1).to_bytes();
            let header_end = 12 + u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
            for (in_header, at, value) in edits {
                let span = if in_header { header_end } else { bytes.len() };
                bytes[at as usize % span] = value;
            }
            if let Some(cut) = cut {
                bytes.truncate(cut as usize % bytes.len());
            }
            crate::assets::reseal_trailing_crc(&mut bytes);
            let _ = GiModel::from_bytes(&bytes);
        }
    }

    #[test]
    fn bad_g_buffer_values_are_zeroed_and_counted_and_outputs_are_finite() {
        let m = model(1);
        let features = m.header.features;
        let mut pixels = vec![
            GBufferPixel {
                position: [0.5, 0.2, 1.0],
                normal: [0.0, 0.0, 1.0],
                albedo: [0.5; 3],
                depth: 2.0,
                direct: [1.0; 3]
            };
            16
        ];
        pixels[3].position[0] = f32::NAN;
        pixels[5].direct = [f32::INFINITY, -1.0, 2.0];
        pixels[7].depth = 1e30;
        let (inputs, bad) = features.encode_image(&pixels);
        assert_eq!(bad, 2);
        assert!(inputs.iter().all(|v| v.is_finite() && v.abs() <= 64.0));
        let shaded = m.shade(4, 4, &[&pixels], &mut UNetWorkspace::new()).expect("shade");
        assert_eq!((shaded.eyes.len(), shaded.eyes[0].len(), shaded.non_finite_inputs), (1, 16, 2));
        assert!(shaded.eyes[0].iter().flatten().all(|v| v.is_finite() && *v >= 0.0));
        assert!(m.shade(4, 4, &[&pixels, &pixels], &mut UNetWorkspace::new()).is_err());
        assert_eq!((decode_output(f32::NAN), decode_output(-3.0)), (0.0, 0.0));
        assert!(decode_output(1e9).is_finite() && decode_output(1e9) == decode_output(MAX_OUTPUT));
        assert!((decode_output(encode_target(2.5)) - 2.5).abs() < 1e-6);
    }

    /// A device that runs the CPU forward (or, broken, drops a head).
    #[derive(Debug)]
    struct CpuDevice {
        network: UNet,
        drop_a_head: bool,
    }

    impl UNetDevice for CpuDevice {
        fn forward(
            &self,
            width: usize,
            height: usize,
            input: &[f32],
            needed: Option<&PixelMask>,
        ) -> Result<Vec<Vec<f32>>, String> {
            let mut ws = UNetWorkspace::new();
            let mut heads: Vec<Vec<f32>> = self
                .network
                .forward_masked(width, height, input, needed, &mut ws)
                .map_err(|e| e.to_string())?
                .iter()
                .map(|h| h.to_vec())
                .collect();
            if self.drop_a_head {
                heads.pop();
            }
            Ok(heads)
        }

        fn label(&self) -> String {
            "test device".into()
        }
    }

    #[test]
    fn shading_on_a_device_decodes_its_heads_as_the_cpu_does_and_refuses_missing_ones() {
        let m = model(2);
        let pixels: Vec<GBufferPixel> = (0..16)
            .map(|i| GBufferPixel {
                position: [i as f32 * 0.1, 0.5, 1.0],
                normal: [0.0, 0.0, 1.0],
                albedo: [0.5, 0.4, 0.3],
                depth: 1.0 + i as f32 * 0.05,
                direct: [0.2 * (i % 3) as f32; 3],
            })
            .collect();
        let eyes = [pixels.as_slice(), pixels.as_slice()];
        let cpu = m.shade(4, 4, &eyes, &mut UNetWorkspace::new()).expect("cpu");
        let device = CpuDevice { network: m.network.clone(), drop_a_head: false };
        assert_eq!(m.shade_on(&device, 4, 4, &eyes, None).expect("device"), cpu);
        let broken = CpuDevice { network: m.network.clone(), drop_a_head: true };
        let err = m.shade_on(&broken, 4, 4, &eyes, None).expect_err("one head for two eyes");
        assert!(err.to_string().contains("test device"), "{err}");
        assert!(m.shade_on(&device, 4, 4, &eyes[..1], None).is_err(), "one eye for a stereo model");
    }
}
