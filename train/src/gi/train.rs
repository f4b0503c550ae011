//! Training the single-eye global-illumination U-Net on path-traced frames (the stereo GI
//! paper's teacher): random crops of the single-eye frames, squared error in `ln(1 + x)`
//! ([`nephele_kernels::gi`]), Adam with a step-decayed learning rate, checkpoints that a later
//! run resumes from.
//!
//! Every eighth single-eye frame is held out for validation ([`split_frames`]).

use std::path::Path;

use nephele_geometry::SplitMix64;
use nephele_kernels::gi::{GBufferPixel, GI_INPUTS, GI_OUTPUTS, GiFeatures, GiModel, encode_target};
use nephele_nn::{Adam, AdamConfig, NnError, UNet, UNetConfig, UNetWorkspace};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::checkpoint::{Checkpoint, CheckpointError, CheckpointState};

use super::data::{GiBuffers, GiDataError, GiFrame, load_frame, read_manifest, with_served_inputs};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiTrainOptions {
    pub steps: u32,
    /// Crops per step.
    pub batch: usize,
    /// Side of the square training crops (a multiple of `2^(levels - 1)`).
    pub crop: usize,
    pub learning_rate: f32,
    /// Channels per U-Net level, finest first.
    pub channels: Vec<usize>,
    pub seed: u64,
}

impl Default for GiTrainOptions {
    fn default() -> Self {
        GiTrainOptions { steps: 3000, batch: 4, crop: 64, learning_rate: 2e-3, channels: vec![16, 32, 64], seed: 1 }
    }
}

impl GiTrainOptions {
    pub fn network(&self, eyes: usize) -> UNetConfig {
        UNetConfig { inputs: GI_INPUTS, eyes, outputs: GI_OUTPUTS, channels: self.channels.clone() }
    }

    pub fn validate(&self) -> Result<(), GiTrainError> {
        self.network(1).validate()?;
        let step = 1 << (self.channels.len() - 1);
        if self.steps == 0 || self.batch == 0 || self.crop < step || !self.crop.is_multiple_of(step) {
            return Err(GiTrainError::Options(format!(
                "steps {}, batch {}, crop {} (crops must be a positive multiple of {step} for {} levels)",
                self.steps,
                self.batch,
                self.crop,
                self.channels.len()
            )));
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return Err(GiTrainError::Options(format!("learning rate {}", self.learning_rate)));
        }
        Ok(())
    }

    /// The learning rate at `step`: full for half the run, a third until 3/4, a tenth after.
    pub fn learning_rate_at(&self, step: u32) -> f32 {
        let t = step as f32 / self.steps as f32;
        self.learning_rate
            * if t < 0.5 {
                1.0
            } else if t < 0.75 {
                0.3
            } else {
                0.1
            }
    }
}

#[derive(Debug, Error)]
pub enum GiTrainError {
    #[error("GI training options: {0}")]
    Options(String),
    #[error(transparent)]
    Data(#[from] GiDataError),
    #[error(transparent)]
    Network(#[from] NnError),
    #[error(transparent)]
    Model(#[from] nephele_kernels::gi::GiModelError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
}

/// A frame ready for training: network inputs and `ln(1 + GI)` targets.
#[derive(Debug, Clone)]
pub struct GiSample {
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub inputs: Vec<f32>,
    pub targets: Vec<f32>,
    /// The path-traced GI, linear (for evaluation).
    pub gi: Vec<[f32; 3]>,
}

/// The G-buffer pixels of loaded buffers.
pub fn g_buffer_pixels(b: &GiBuffers) -> Vec<GBufferPixel> {
    (0..b.depth.len())
        .map(|i| GBufferPixel {
            position: b.position[i],
            normal: b.normal[i],
            albedo: b.albedo[i],
            depth: b.depth[i],
            direct: b.direct[i],
        })
        .collect()
}

/// Feature scales from the data: the box of every position the frames see.
pub fn features_of<'a>(frames: impl IntoIterator<Item = &'a GiBuffers>) -> GiFeatures {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for b in frames {
        for (p, &d) in b.position.iter().zip(&b.depth) {
            if d > 0.0 && p.iter().all(|v| v.is_finite()) {
                for i in 0..3 {
                    lo[i] = lo[i].min(p[i]);
                    hi[i] = hi[i].max(p[i]);
                }
            }
        }
    }
    if lo[0] > hi[0] {
        return GiFeatures { centre: [0.0; 3], scale: 1.0 };
    }
    let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])];
    let scale = (0..3).map(|i| 0.5 * (hi[i] - lo[i])).fold(0.0f32, f32::max).max(1e-3);
    GiFeatures { centre, scale }
}

/// The sample of one frame's buffers.
pub fn sample_of(frame: &GiFrame, b: &GiBuffers, features: &GiFeatures) -> GiSample {
    let (inputs, _) = features.encode_image(&g_buffer_pixels(b));
    let targets = b.gi.iter().flat_map(|c| c.map(encode_target)).collect();
    GiSample {
        name: frame.name.clone(),
        width: b.width as usize,
        height: b.height as usize,
        inputs,
        targets,
        gi: b.gi.clone(),
    }
}

/// The single-eye frames of a dataset split into training and held-out (every eighth).
pub fn split_frames(frames: &[GiFrame]) -> (Vec<GiFrame>, Vec<GiFrame>) {
    let single: Vec<&GiFrame> = frames.iter().filter(|f| f.stereo.is_none()).collect();
    let (mut train, mut held_out) = (Vec::new(), Vec::new());
    for (i, f) in single.into_iter().enumerate() {
        if i % 8 == 7 { held_out.push(f.clone()) } else { train.push(f.clone()) }
    }
    (train, held_out)
}

/// The single-eye training data of a dataset folder: training samples, held-out samples,
/// the feature scales, and how many non-finite values the files held (zeroed). With
/// `input_spp`, the inputs are rendered as the farm serves them at that many samples
/// ([`with_served_inputs`]), held-out frames included.
pub fn load_single_eye(
    dir: &Path,
    input_spp: Option<u32>,
) -> Result<(Vec<GiSample>, Vec<GiSample>, GiFeatures, usize), GiTrainError> {
    let manifest = read_manifest(dir)?;
    let (train, held_out) = split_frames(&manifest.frames);
    if train.is_empty() {
        return Err(GiTrainError::Options(format!("{} holds no single-eye training frames", dir.display())));
    }
    let load = |frames: &[GiFrame]| -> Result<Vec<(GiFrame, GiBuffers)>, GiTrainError> {
        frames.iter().map(|f| Ok((f.clone(), load_inputs(dir, &manifest.spec, f, input_spp)?))).collect()
    };
    let (train, held_out) = (load(&train)?, load(&held_out)?);
    let non_finite = train.iter().chain(&held_out).map(|(_, b)| b.non_finite).sum();
    let features = features_of(train.iter().map(|(_, b)| b));
    let samples = |v: &[(GiFrame, GiBuffers)]| v.iter().map(|(f, b)| sample_of(f, b, &features)).collect::<Vec<_>>();
    Ok((samples(&train), samples(&held_out), features, non_finite))
}

/// A frame's buffers, its inputs rendered as served at `input_spp` samples where given.
pub fn load_inputs(
    dir: &Path,
    spec: &super::data::GiSpec,
    frame: &GiFrame,
    input_spp: Option<u32>,
) -> Result<GiBuffers, GiTrainError> {
    let buffers = load_frame(dir, frame)?;
    Ok(match input_spp {
        Some(spp) => with_served_inputs(spec, frame, spp, &buffers)?,
        None => buffers,
    })
}

/// Where a training run stands (what a checkpoint holds besides the weights).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GiTrainState {
    pub options: GiTrainOptions,
    pub features: GiFeatures,
    pub step: u32,
    /// `(step, mean loss of the steps since the previous entry)`, every 50 steps.
    pub curve: Vec<(u32, f32)>,
    pub adam_steps: u64,
    pub rng: u64,
}

impl CheckpointState for GiTrainState {
    const MAGIC: &'static [u8; 4] = b"NGIC";
    const VERSION: u32 = 1;
    const WHAT: &'static str = "GI training checkpoint";
}

/// A run's weights, optimiser moments and state.
pub type GiCheckpoint = Checkpoint<GiTrainState>;

/// Progress of a run, every step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GiStep {
    pub step: u32,
    pub steps: u32,
    pub loss: f32,
}

/// The network, optimiser and state a training run starts from: `resume`'s when given (it
/// must have been made with the same options and data, else an error), otherwise `fresh()`
/// with a new optimiser and a state whose random stream is `options.seed ^ salt`.
pub(super) fn resume_or_start(
    resume: Option<GiCheckpoint>,
    options: &GiTrainOptions,
    features: GiFeatures,
    config: UNetConfig,
    salt: u64,
    fresh: impl FnOnce() -> Result<UNet, GiTrainError>,
) -> Result<(UNet, Adam, GiTrainState), GiTrainError> {
    let adam_config = AdamConfig { learning_rate: options.learning_rate, epsilon: 1e-8, ..AdamConfig::default() };
    if let Some(c) = resume {
        if c.state.options != *options || c.state.features != features {
            return Err(GiTrainError::Options(
                "the checkpoint was made with other options or data; start afresh or pass the same settings".into(),
            ));
        }
        let network = UNet::from_params(config, c.params)?;
        let adam = Adam::from_moments(adam_config, c.m, c.v, c.state.adam_steps)?;
        return Ok((network, adam, c.state));
    }
    let network = fresh()?;
    let adam = Adam::new(adam_config, network.params().len());
    let state = GiTrainState {
        options: options.clone(),
        features,
        step: 0,
        curve: Vec::new(),
        adam_steps: 0,
        rng: options.seed ^ salt,
    };
    Ok((network, adam, state))
}

/// Trains a single-eye model on `train` (resuming `resume` when given: same options and
/// features, or an error). `on_step` sees every step; `checkpoint` is called every
/// `checkpoint_every` steps and at the end with the run's state. Returns the model and the
/// final state.
pub fn train_single_eye(
    train: &[GiSample],
    features: GiFeatures,
    options: &GiTrainOptions,
    resume: Option<GiCheckpoint>,
    checkpoint_every: u32,
    on_step: &mut dyn FnMut(GiStep),
    checkpoint: &mut dyn FnMut(&GiCheckpoint) -> Result<(), GiTrainError>,
) -> Result<(GiModel, GiTrainState), GiTrainError> {
    options.validate()?;
    if let Some(s) = train.iter().find(|s| s.width < options.crop || s.height < options.crop) {
        return Err(GiTrainError::Options(format!(
            "frame {} is {}x{}, smaller than the {} crop",
            s.name, s.width, s.height, options.crop
        )));
    }
    if train.is_empty() {
        return Err(GiTrainError::Options("no training frames".into()));
    }
    let config = options.network(1);
    let (mut network, mut adam, mut state) =
        resume_or_start(resume, options, features, config.clone(), 0x6769_7472, || {
            Ok(UNet::new(config, options.seed)?)
        })?;
    let mut rng = SplitMix64::new(state.rng);
    let crop = options.crop;
    let mut ws = UNetWorkspace::new();
    let mut grads = vec![0.0f32; network.params().len()];
    let mut input = vec![0.0f32; crop * crop * GI_INPUTS];
    let mut target = vec![0.0f32; crop * crop * GI_OUTPUTS];
    let mut window = (0.0f64, 0u32);
    while state.step < options.steps {
        grads.fill(0.0);
        let mut loss = 0.0f64;
        for _ in 0..options.batch {
            let sample = &train[rng.below(train.len() as u64) as usize];
            let x0 = rng.below((sample.width - crop + 1) as u64) as usize;
            let y0 = rng.below((sample.height - crop + 1) as u64) as usize;
            for y in 0..crop {
                let row = (y0 + y) * sample.width + x0;
                input[y * crop * GI_INPUTS..][..crop * GI_INPUTS]
                    .copy_from_slice(&sample.inputs[row * GI_INPUTS..][..crop * GI_INPUTS]);
                target[y * crop * GI_OUTPUTS..][..crop * GI_OUTPUTS]
                    .copy_from_slice(&sample.targets[row * GI_OUTPUTS..][..crop * GI_OUTPUTS]);
            }
            let output = network.forward(crop, crop, &input, &mut ws)?[0].to_vec();
            let scale = 2.0 / (target.len() * options.batch) as f32;
            let mut d_out: Vec<f32> = output.iter().zip(&target).map(|(o, t)| scale * (o - t)).collect();
            loss += output.iter().zip(&target).map(|(o, t)| f64::from(o - t).powi(2)).sum::<f64>()
                / (target.len() * options.batch) as f64;
            network.backward(&input, &mut ws, std::slice::from_mut(&mut d_out), &mut grads)?;
        }
        finish_step(
            &mut network,
            &mut adam,
            &grads,
            loss,
            &mut state,
            &mut window,
            &rng,
            checkpoint_every,
            on_step,
            checkpoint,
        )?;
    }
    let training = serde_json::json!({
        "steps": state.step, "batch": options.batch, "crop": options.crop, "frames": train.len(),
        "final_loss": state.curve.last().map(|c| c.1),
    });
    Ok((GiModel::new(network, features, training)?, state))
}

/// The end of one optimisation step, shared by the teacher's and the student's loops: the
/// Adam update at the scheduled rate, the loss curve, progress, and a checkpoint when due.
#[allow(clippy::too_many_arguments)]
pub(crate) fn finish_step(
    network: &mut UNet,
    adam: &mut Adam,
    grads: &[f32],
    loss: f64,
    state: &mut GiTrainState,
    window: &mut (f64, u32),
    rng: &SplitMix64,
    checkpoint_every: u32,
    on_step: &mut dyn FnMut(GiStep),
    checkpoint: &mut dyn FnMut(&GiCheckpoint) -> Result<(), GiTrainError>,
) -> Result<(), GiTrainError> {
    let steps = state.options.steps;
    adam.set_learning_rate(state.options.learning_rate_at(state.step));
    adam.step(network.params_mut(), grads)?;
    state.step += 1;
    window.0 += loss;
    window.1 += 1;
    if state.step.is_multiple_of(50) || state.step == steps {
        state.curve.push((state.step, (window.0 / f64::from(window.1)) as f32));
        *window = (0.0, 0);
    }
    on_step(GiStep { step: state.step, steps, loss: loss as f32 });
    if (checkpoint_every > 0 && state.step.is_multiple_of(checkpoint_every)) || state.step == steps {
        state.adam_steps = adam.steps();
        state.rng = rng.state();
        let (m, v) = adam.moments();
        checkpoint(&GiCheckpoint {
            state: state.clone(),
            params: network.params().to_vec(),
            m: m.to_vec(),
            v: v.to_vec(),
        })?;
    }
    Ok(())
}

/// Mean PSNR (dB) of the model's single-eye output against the path-traced GI of `samples`,
/// on the displayed image (linear radiance clamped to [0, 1], sRGB-encoded).
pub fn evaluate_single_eye(model: &GiModel, samples: &[GiSample]) -> Result<f64, GiTrainError> {
    let mut ws = UNetWorkspace::new();
    let mut total = 0.0;
    for s in samples {
        let output = model.network.forward(s.width, s.height, &s.inputs, &mut ws)?[0].to_vec();
        let predicted: Vec<[f32; 3]> =
            output.chunks_exact(3).map(|c| [0, 1, 2].map(|i| nephele_kernels::gi::decode_output(c[i]))).collect();
        let (w, h) = (s.width as u32, s.height as u32);
        total += nephele_imaging::metrics::psnr_rgb(w, h, &displayed(&predicted), &displayed(&s.gi))
            .map_err(|e| GiTrainError::Options(format!("frame {}: {e}", s.name)))?;
    }
    Ok(total / samples.len().max(1) as f64)
}

/// A linear RGB image as displayed: clamped to [0, 1], sRGB-encoded, interleaved (what
/// the PSNR and SSIM of the GI models compare).
pub fn displayed(image: &[[f32; 3]]) -> Vec<f32> {
    image.iter().flat_map(|c| c.map(|v| nephele_imaging::image::linear_to_srgb(v.clamp(0.0, 1.0)))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gi::data::{GiSpec, render_gi_dataset};

    fn tiny_data(dir: &Path) {
        let spec = GiSpec {
            scene: "room-day".into(),
            single: 9,
            stereo_pairs: 0,
            train_pairs: 0,
            width: 16,
            height: 16,
            fov_y: 1.2,
            spp: 4,
            bounces: 3,
            seed: 2,
        };
        render_gi_dataset(&spec, dir, &|_| {}).expect("dataset");
    }

    fn options(steps: u32) -> GiTrainOptions {
        GiTrainOptions { steps, batch: 2, crop: 8, learning_rate: 3e-3, channels: vec![8, 16], seed: 4 }
    }

    #[test]
    fn a_short_run_lowers_the_loss_and_resumes_from_its_checkpoint() {
        let dir = tempfile::tempdir().expect("tempdir");
        tiny_data(dir.path());
        let (train, held_out, features, bad) = load_single_eye(dir.path(), None).expect("load");
        assert_eq!((train.len(), held_out.len(), bad), (8, 1, 0));
        assert!(features.scale > 1.0 && features.scale < 4.0, "{features:?}");

        let mut losses = Vec::new();
        let mut saved = Vec::new();
        let (model, state) =
            train_single_eye(&train, features, &options(300), None, 100, &mut |s| losses.push(s.loss), &mut |c| {
                saved.push(c.clone());
                Ok(())
            })
            .expect("train");
        let early: f32 = losses[..20].iter().sum::<f32>() / 20.0;
        let late: f32 = losses[losses.len() - 20..].iter().sum::<f32>() / 20.0;
        assert!(late < 0.7 * early, "loss {early} -> {late}");
        assert_eq!((state.step, saved.len(), state.curve.len()), (300, 3, 6));
        assert!(evaluate_single_eye(&model, &held_out).expect("eval").is_finite());

        // Resuming from step 200 reproduces the last 100 steps exactly.
        let path = dir.path().join("run.ckpt");
        saved[1].save(&path).expect("save");
        let resumed = GiCheckpoint::load(&path).expect("load");
        assert_eq!(resumed.state, saved[1].state);
        let (again, state_again) =
            train_single_eye(&train, features, &options(300), Some(resumed), 100, &mut |_| {}, &mut |_| Ok(()))
                .expect("resume");
        assert_eq!(again.network.params(), model.network.params());
        assert_eq!(state_again.curve.len(), 6);
        // Other options do not resume.
        let other = GiCheckpoint::load(&path).expect("load");
        assert!(
            train_single_eye(&train, features, &options(400), Some(other), 0, &mut |_| {}, &mut |_| Ok(())).is_err()
        );
        // A damaged checkpoint is refused.
        let mut bytes = std::fs::read(&path).expect("read");
        bytes[30] ^= 4;
        std::fs::write(&path, &bytes).expect("write");
        assert!(GiCheckpoint::load(&path).is_err());
    }

    #[test]
    fn options_are_checked() {
        assert!(options(10).validate().is_ok());
        assert!(GiTrainOptions { crop: 7, ..options(10) }.validate().is_err());
        assert!(GiTrainOptions { steps: 0, ..options(10) }.validate().is_err());
        assert!(GiTrainOptions { learning_rate: f32::NAN, ..options(10) }.validate().is_err());
        assert!(GiTrainOptions { channels: vec![], ..options(10) }.validate().is_err());
        assert_eq!(options(100).learning_rate_at(80), 3e-4);
    }
}
