//! The stereo student (the stereo GI paper, section 3): one U-Net pass for both eyes,
//! initialised from the single-eye teacher ([`nephele_nn::UNet::stereo_from_single`]; by
//! default its first layer and right head too, [`StudentStart::FromTeacher`]) and
//! trained without stereo ground truth: each eye's head learns the teacher's output for that
//! eye, and the spatial coherence loss (eq. 1, [`super::warp`]) pulls the right eye's image,
//! warped onto the left, towards the left eye's.
//!
//! Training pairs are the dataset's `t_N` pairs (their path-traced GI is never read);
//! evaluation uses the `p_N` pairs and their ground truth.

use std::path::Path;

use nephele_geometry::SplitMix64;
use nephele_kernels::gi::{GI_INPUTS, GI_OUTPUTS, GiFeatures, GiModel, decode_output};
use nephele_nn::{StudentStart, UNet, UNetWorkspace};

use super::data::{Eye, GiFrame, load_frame, read_manifest};
use super::train::{
    GiCheckpoint, GiStep, GiTrainError, GiTrainOptions, GiTrainState, displayed, finish_step, resume_or_start,
    sample_of,
};
use super::warp::Warp;

/// What the student's training adds to [`GiTrainOptions`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentOptions {
    /// Weight of the spatial coherence loss (eq. 1; 0 turns it off).
    pub coherence_weight: f32,
    /// How the first layer and the right head start (the rest is the teacher's).
    pub start: StudentStart,
}

impl Default for StudentOptions {
    fn default() -> Self {
        // The paper's weight: with 64 training pairs it lowers the inter-eye error 38-54 %
        // for at most 0.3 dB of either eye as served (BENCHMARKS.md, "2026-12-06g").
        StudentOptions { coherence_weight: 1.0, start: StudentStart::FromTeacher }
    }
}

/// One stereo pair ready for training or evaluation.
#[derive(Debug, Clone)]
pub struct StereoSample {
    pub name: String,
    pub width: usize,
    pub height: usize,
    /// Both eyes' inputs stacked per pixel (left's `GI_INPUTS`, then right's).
    pub stacked: Vec<f32>,
    /// Each eye's own inputs (for the single-eye teacher).
    pub eyes: [Vec<f32>; 2],
    /// The right eye's image onto the left, from the depths and the cameras.
    pub warp: Warp,
    /// Path-traced GI of each eye, linear (evaluation pairs only).
    pub gi: Option<[Vec<[f32; 3]>; 2]>,
}

/// The stereo pairs of a dataset folder: the training pairs (`train`) or the evaluation
/// pairs, with inputs scaled by `features`; with `input_spp`, the inputs rendered as the farm
/// serves them ([`super::data::with_served_inputs`]; the warp keeps the dataset's depth).
pub fn load_pairs(
    dir: &Path,
    features: &GiFeatures,
    train: bool,
    input_spp: Option<u32>,
) -> Result<Vec<StereoSample>, GiTrainError> {
    let manifest = read_manifest(dir)?;
    let eye_of = |f: &GiFrame, eye: Eye| f.stereo.is_some_and(|s| s.eye == eye && s.train == train);
    let lefts: Vec<&GiFrame> = manifest.frames.iter().filter(|f| eye_of(f, Eye::Left)).collect();
    let mut pairs = Vec::with_capacity(lefts.len());
    for left in lefts {
        let pair = left.stereo.map(|s| s.pair);
        let right = manifest
            .frames
            .iter()
            .find(|f| eye_of(f, Eye::Right) && f.stereo.map(|s| s.pair) == pair)
            .ok_or_else(|| GiTrainError::Options(format!("{} has no right eye", left.name)))?;
        let (lb, rb) = (load_frame(dir, left)?, load_frame(dir, right)?);
        let inputs = |f: &GiFrame, b: &super::data::GiBuffers| match input_spp {
            Some(spp) => super::data::with_served_inputs(&manifest.spec, f, spp, b),
            None => Ok(b.clone()),
        };
        let (li, ri) = (inputs(left, &lb)?, inputs(right, &rb)?);
        let (ls, rs) = (sample_of(left, &li, features), sample_of(right, &ri, features));
        let camera = |f: &GiFrame| manifest.spec.camera(f).map_err(|e| GiTrainError::Data(e.into()));
        let (lc, rc) = (camera(left)?, camera(right)?);
        let warp = Warp::right_onto_left(&lc, &lb.depth, &rc, &rb.depth);
        let stacked = ls
            .inputs
            .chunks_exact(GI_INPUTS)
            .zip(rs.inputs.chunks_exact(GI_INPUTS))
            .flat_map(|(l, r)| l.iter().chain(r).copied())
            .collect();
        pairs.push(StereoSample {
            name: left.name.trim_end_matches("_left").to_string(),
            width: ls.width,
            height: ls.height,
            stacked,
            eyes: [ls.inputs, rs.inputs],
            warp,
            gi: (!train).then_some([ls.gi, rs.gi]),
        });
    }
    Ok(pairs)
}

/// The teacher's output (in `ln(1 + x)`) for both eyes of every pair.
pub fn teacher_targets(teacher: &GiModel, pairs: &[StereoSample]) -> Result<Vec<[Vec<f32>; 2]>, GiTrainError> {
    let mut ws = UNetWorkspace::new();
    pairs
        .iter()
        .map(|p| {
            let mut run = |input: &[f32]| -> Result<Vec<f32>, GiTrainError> {
                Ok(teacher.network.forward(p.width, p.height, input, &mut ws)?[0].to_vec())
            };
            Ok([run(&p.eyes[0])?, run(&p.eyes[1])?])
        })
        .collect()
}

/// The warp restricted to a crop: left pixels inside it whose taps all fall inside it.
fn crop_warp(warp: &Warp, x0: usize, y0: usize, crop: usize) -> Warp {
    let w = warp.width as usize;
    let inside = |index: u32| {
        let (x, y) = (index as usize % w, index as usize / w);
        (x >= x0 && x < x0 + crop && y >= y0 && y < y0 + crop).then(|| ((y - y0) * crop + (x - x0)) as u32)
    };
    let taps = (0..crop * crop)
        .map(|i| {
            let (x, y) = (x0 + i % crop, y0 + i / crop);
            let taps = warp.taps[y * w + x].as_ref()?;
            taps.iter().map(|&(index, weight)| Some((inside(index)?, weight))).collect::<Option<Vec<_>>>()
        })
        .collect();
    Warp { width: crop as u32, height: crop as u32, taps }
}

/// Trains the stereo student of `teacher` on `pairs` with coherence weight
/// `options.coherence_weight`; resumes `resume` when given. As [`super::train::train_single_eye`]
/// for progress and checkpoints.
#[allow(clippy::too_many_arguments)]
pub fn train_stereo(
    teacher: &GiModel,
    pairs: &[StereoSample],
    options: &GiTrainOptions,
    student: StudentOptions,
    resume: Option<GiCheckpoint>,
    checkpoint_every: u32,
    on_step: &mut dyn FnMut(GiStep),
    checkpoint: &mut dyn FnMut(&GiCheckpoint) -> Result<(), GiTrainError>,
) -> Result<(GiModel, GiTrainState), GiTrainError> {
    options.validate()?;
    if pairs.is_empty() {
        return Err(GiTrainError::Options("no stereo training pairs (nephele dataset gi --train-pairs)".into()));
    }
    let coherence_weight = student.coherence_weight;
    if !(coherence_weight.is_finite() && coherence_weight >= 0.0) {
        return Err(GiTrainError::Options(format!("coherence weight {coherence_weight}")));
    }
    if options.channels != teacher.network.config().channels {
        return Err(GiTrainError::Options("the student has the teacher's levels and channels".into()));
    }
    let crop = options.crop;
    if let Some(p) = pairs.iter().find(|p| p.width < crop || p.height < crop) {
        return Err(GiTrainError::Options(format!("pair {} is smaller than the {crop} crop", p.name)));
    }
    let targets = teacher_targets(teacher, pairs)?;
    let features = teacher.header.features;
    let (mut network, mut adam, mut state) =
        resume_or_start(resume, options, features, options.network(2), 0x7374_6572, || {
            Ok(UNet::stereo_from_single(&teacher.network, student.start, options.seed)?)
        })?;
    let mut rng = SplitMix64::new(state.rng);
    let mut ws = UNetWorkspace::new();
    let mut grads = vec![0.0f32; network.params().len()];
    let per_pixel = 2 * GI_INPUTS;
    let mut input = vec![0.0f32; crop * crop * per_pixel];
    let mut target = [vec![0.0f32; crop * crop * GI_OUTPUTS], vec![0.0f32; crop * crop * GI_OUTPUTS]];
    let mut window = (0.0f64, 0u32);
    while state.step < options.steps {
        grads.fill(0.0);
        let mut loss = 0.0f64;
        for _ in 0..options.batch {
            let i = rng.below(pairs.len() as u64) as usize;
            let (pair, teacher_out) = (&pairs[i], &targets[i]);
            let x0 = rng.below((pair.width - crop + 1) as u64) as usize;
            let y0 = rng.below((pair.height - crop + 1) as u64) as usize;
            for y in 0..crop {
                let row = (y0 + y) * pair.width + x0;
                input[y * crop * per_pixel..][..crop * per_pixel]
                    .copy_from_slice(&pair.stacked[row * per_pixel..][..crop * per_pixel]);
                for eye in 0..2 {
                    target[eye][y * crop * GI_OUTPUTS..][..crop * GI_OUTPUTS]
                        .copy_from_slice(&teacher_out[eye][row * GI_OUTPUTS..][..crop * GI_OUTPUTS]);
                }
            }
            let warp = crop_warp(&pair.warp, x0, y0, crop);
            let heads: Vec<Vec<f32>> =
                network.forward(crop, crop, &input, &mut ws)?.iter().map(|h| h.to_vec()).collect();
            let n = (crop * crop * GI_OUTPUTS * options.batch) as f32;
            let mut d_heads: Vec<Vec<f32>> = heads
                .iter()
                .zip(&target)
                .map(|(out, t)| out.iter().zip(t).map(|(o, t)| 2.0 * (o - t) / n).collect())
                .collect();
            for (out, t) in heads.iter().zip(&target) {
                loss += out.iter().zip(t).map(|(o, t)| f64::from(o - t).powi(2)).sum::<f64>() / f64::from(n);
            }
            if coherence_weight > 0.0 {
                let (error, _) = warp.coherence(&heads[0], &heads[1], GI_OUTPUTS);
                loss += f64::from(coherence_weight) * error / options.batch as f64;
                let (d_left, d_right) = d_heads.split_at_mut(1);
                warp.coherence_backward(
                    &heads[0],
                    &heads[1],
                    GI_OUTPUTS,
                    coherence_weight / options.batch as f32,
                    &mut d_left[0],
                    &mut d_right[0],
                );
            }
            network.backward(&input, &mut ws, &mut d_heads, &mut grads)?;
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
        "student_of": teacher.header.training, "steps": state.step, "batch": options.batch, "crop": crop,
        "pairs": pairs.len(), "coherence_weight": coherence_weight, "final_loss": state.curve.last().map(|c| c.1),
    });
    let mut model = GiModel::new(network, features, training)?;
    model.header.scene = teacher.header.scene.clone();
    Ok((model, state))
}

/// What a model gives on the evaluation pairs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StereoEvaluation {
    /// Mean PSNR (dB, displayed images) of the left and right eyes against path tracing.
    pub psnr: [f64; 2],
    /// Mean SSIM of the left and right eyes (displayed images; NaN for images under 11x11).
    pub ssim: [f64; 2],
    /// Mean inter-eye coherence error: MSE between the left image and the right image warped
    /// onto it, displayed images, unmasked pixels.
    pub coherence: f64,
}

/// Linear RGB images of both eyes of every pair: the stereo model in one pass per pair, or
/// a single-eye model run once per eye.
pub fn shade_pairs(model: &GiModel, pairs: &[StereoSample]) -> Result<Vec<[Vec<[f32; 3]>; 2]>, GiTrainError> {
    let mut ws = UNetWorkspace::new();
    let decode =
        |v: &[f32]| v.chunks_exact(GI_OUTPUTS).map(|c| [0, 1, 2].map(|i| decode_output(c[i]))).collect::<Vec<_>>();
    pairs
        .iter()
        .map(|p| {
            if model.eyes() == 2 {
                let heads = model.network.forward(p.width, p.height, &p.stacked, &mut ws)?;
                Ok([decode(heads[0]), decode(heads[1])])
            } else {
                let left = decode(model.network.forward(p.width, p.height, &p.eyes[0], &mut ws)?[0]);
                let right = decode(model.network.forward(p.width, p.height, &p.eyes[1], &mut ws)?[0]);
                Ok([left, right])
            }
        })
        .collect()
}

/// PSNR and SSIM of both eyes and the coherence error of `images` (from [`shade_pairs`]) on
/// evaluation `pairs`. Images are compared as displayed: linear radiance clamped to [0, 1]
/// and sRGB-encoded.
pub fn evaluate_pairs(pairs: &[StereoSample], images: &[[Vec<[f32; 3]>; 2]]) -> StereoEvaluation {
    let (mut psnr, mut ssim, mut coherence) = ([0.0; 2], [0.0; 2], 0.0);
    for (p, eyes) in pairs.iter().zip(images) {
        if let Some(gi) = &p.gi {
            for eye in 0..2 {
                let (a, b) = (displayed(&eyes[eye]), displayed(&gi[eye]));
                psnr[eye] +=
                    nephele_imaging::metrics::psnr_rgb(p.width as u32, p.height as u32, &a, &b).unwrap_or(f64::NAN);
                ssim[eye] +=
                    nephele_imaging::metrics::ssim_rgb(p.width as u32, p.height as u32, &a, &b).unwrap_or(f64::NAN);
            }
        }
        coherence += p.warp.coherence(&displayed(&eyes[0]), &displayed(&eyes[1]), 3).0;
    }
    let n = pairs.len().max(1) as f64;
    StereoEvaluation { psnr: psnr.map(|v| v / n), ssim: ssim.map(|v| v / n), coherence: coherence / n }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gi::data::{GiSpec, render_gi_dataset};
    use crate::gi::train::{load_single_eye, train_single_eye};

    #[test]
    fn the_student_learns_both_eyes_from_the_teacher_and_the_coherence_loss_aligns_them() {
        let dir = tempfile::tempdir().expect("tempdir");
        let spec = GiSpec {
            scene: "room-night".into(),
            single: 8,
            stereo_pairs: 1,
            train_pairs: 3,
            width: 16,
            height: 16,
            fov_y: 1.2,
            spp: 4,
            bounces: 3,
            seed: 3,
        };
        render_gi_dataset(&spec, dir.path(), &|_| {}).expect("dataset");
        let (train, _, features, _) = load_single_eye(dir.path(), None).expect("load");
        let options =
            GiTrainOptions { steps: 60, batch: 2, crop: 8, learning_rate: 3e-3, channels: vec![4, 8], seed: 1 };
        let (teacher, _) =
            train_single_eye(&train, features, &options, None, 0, &mut |_| {}, &mut |_| Ok(())).expect("teacher");
        let pairs = load_pairs(dir.path(), &features, true, None).expect("pairs");
        assert_eq!(pairs.len(), 3);
        assert!(pairs.iter().all(|p| p.gi.is_none() && p.warp.valid() > 0));
        let eval = load_pairs(dir.path(), &features, false, None).expect("eval pairs");
        assert!(eval.len() == 1 && eval[0].gi.is_some());

        let student_options = GiTrainOptions { steps: 80, crop: 16, ..options.clone() };
        let mut losses = Vec::new();
        let (student, state) = train_stereo(
            &teacher,
            &pairs,
            &student_options,
            StudentOptions::default(),
            None,
            0,
            &mut |s| losses.push(s.loss),
            &mut |_| Ok(()),
        )
        .expect("student");
        assert_eq!((student.eyes(), state.step), (2, 80));
        let early: f32 = losses[..10].iter().sum::<f32>() / 10.0;
        let late: f32 = losses[losses.len() - 10..].iter().sum::<f32>() / 10.0;
        assert!(late < early, "student loss {early} -> {late}");
        let images = shade_pairs(&student, &eval).expect("shade");
        let result = evaluate_pairs(&eval, &images);
        assert!(result.psnr.iter().all(|p| p.is_finite()) && result.coherence.is_finite(), "{result:?}");
        // The teacher run twice gives the same kind of evaluation.
        let twice = evaluate_pairs(&eval, &shade_pairs(&teacher, &eval).expect("shade"));
        assert!(twice.psnr.iter().all(|p| p.is_finite()));
        // The coherence loss aligns the eyes: on the training pairs, the left image and the
        // warped right one differ less with a strong weight than with none.
        let coherence_of = |weight: f32| {
            let student = StudentOptions { coherence_weight: weight, ..StudentOptions::default() };
            let (model, _) =
                train_stereo(&teacher, &pairs, &student_options, student, None, 0, &mut |_| {}, &mut |_| Ok(()))
                    .expect("student");
            let mut ws = UNetWorkspace::new();
            let total: f64 = pairs
                .iter()
                .map(|p| {
                    let heads = model.network.forward(p.width, p.height, &p.stacked, &mut ws).expect("forward");
                    p.warp.coherence(heads[0], heads[1], GI_OUTPUTS).0
                })
                .sum();
            total / pairs.len() as f64
        };
        let (none, strong) = (coherence_of(0.0), coherence_of(10.0));
        assert!(strong < 0.8 * none, "coherence error {none} without the loss, {strong} with it");
        // A student of other channels than its teacher is refused.
        let other = GiTrainOptions { channels: vec![4, 4], ..student_options };
        let refused =
            train_stereo(&teacher, &pairs, &other, StudentOptions::default(), None, 0, &mut |_| {}, &mut |_| Ok(()));
        assert!(refused.is_err());
    }

    #[test]
    fn a_crop_keeps_the_taps_inside_it() {
        let warp = Warp {
            width: 4,
            height: 4,
            taps: (0..16u32).map(|i| if i % 4 == 0 { None } else { Some(vec![(i - 1, 1.0)]) }).collect(),
        };
        let c = crop_warp(&warp, 1, 1, 2);
        // Crop pixels (1,1),(2,1),(1,2),(2,2): the x = 1 ones read x = 0, outside the crop.
        assert_eq!(c.taps, vec![None, Some(vec![(0, 1.0)]), None, Some(vec![(2, 1.0)])]);
    }
}
