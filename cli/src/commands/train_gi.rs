//! `nephele train gi`: the single-eye global-illumination U-Net (the stereo GI model's
//! teacher) on a dataset of `nephele dataset gi`, or with `--teacher` the stereo student of
//! such a teacher; with a progress bar, checkpoints and resume.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_kernels::gi::GiModel;
use nephele_nn::StudentStart;
use nephele_train::gi::stereo::{StudentOptions, evaluate_pairs, load_pairs, shade_pairs, train_stereo};
use nephele_train::gi::train::{
    GiCheckpoint, GiStep, GiTrainOptions, evaluate_single_eye, load_single_eye, train_single_eye,
};

use crate::progress::Progress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// A dataset of one lighting from `nephele dataset gi` (the folder with gi.json, e.g.
    /// OUT/day). Every eighth single-eye frame is held out for the validation PSNR.
    #[arg(long)]
    data: PathBuf,
    /// Where to write the model (`.ngi`).
    #[arg(long)]
    out: PathBuf,
    /// Optimisation steps.
    #[arg(long, default_value_t = 3000)]
    steps: u32,
    /// Random crops per step.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    /// Side of the square crops (a multiple of 2^(levels - 1)).
    #[arg(long, default_value_t = 64)]
    crop: usize,
    /// Channels per U-Net level, finest first (comma-separated). The default is sized for a
    /// 2-core CPU; a GPU run can afford e.g. 32,64,128,256.
    #[arg(long, default_value = "16,32,64", value_delimiter = ',')]
    channels: Vec<usize>,
    /// Adam learning rate (a third after half the steps, a tenth after three quarters).
    #[arg(long, default_value_t = 2e-3)]
    learning_rate: f32,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Checkpoint file (default: OUT with `.ckpt`), written every --checkpoint-every steps; a
    /// run with the same settings resumes from it.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    #[arg(long, default_value_t = 250)]
    checkpoint_every: u32,
    /// Start afresh even if a checkpoint exists (it is overwritten).
    #[arg(long)]
    restart: bool,
    /// Train the stereo student of this single-eye model (`.ngi`) instead: one pass for both
    /// eyes, on the dataset's training pairs, from the teacher's output (no stereo ground
    /// truth). --channels must be the teacher's.
    #[arg(long)]
    teacher: Option<PathBuf>,
    /// Weight of the spatial coherence loss for the stereo student (0 turns it off). With few
    /// training pairs (24) it costs each eye a few tenths of a dB for little coherence on
    /// unseen pairs; with 64 it pays (BENCHMARKS.md, "2026-12-06g").
    #[arg(long, default_value_t = StudentOptions::default().coherence_weight)]
    coherence_weight: f32,
    /// How the stereo student's first layer and right-eye head start: `teacher` (the
    /// teacher's first layer over the mean of both eyes, its head for both eyes) or `fresh`
    /// (random, as the paper has it). Every other layer is the teacher's either way.
    #[arg(long, value_enum, default_value_t = Start::Teacher)]
    student_start: Start,
    /// Train (and score) on inputs rendered as the farm serves them, at this many samples per
    /// pixel (the served kernel's: 2), instead of the dataset's direct light, which shares the
    /// target's samples; the target stays the dataset's converged image. A model so trained
    /// takes the farm's noisy inputs to the converged light (`nephele up` trains its room so).
    #[arg(long)]
    input_spp: Option<u32>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Start {
    Teacher,
    Fresh,
}

pub fn run(args: Args, progress: &Progress) -> Result<()> {
    let options = GiTrainOptions {
        steps: args.steps,
        batch: args.batch,
        crop: args.crop,
        learning_rate: args.learning_rate,
        channels: args.channels.clone(),
        seed: args.seed,
    };
    options.validate()?;
    if let Some(teacher) = &args.teacher {
        return student(&args, &options, teacher, progress);
    }
    let start = Instant::now();
    let (train, held_out, features, non_finite) = load_single_eye(&args.data, args.input_spp)
        .with_context(|| format!("loading the GI dataset {}", args.data.display()))?;
    if non_finite > 0 {
        println!("{non_finite} NaN or infinite G-buffer values in the files were set to 0");
    }
    let config = options.network(1);
    println!(
        "train gi: {} training and {} held-out frames of {}x{}; U-Net {:?}, {} parameters, {:.0} multiply-adds per pixel",
        train.len(),
        held_out.len(),
        train[0].width,
        train[0].height,
        config.channels,
        config.param_count(),
        config.macs_per_pixel()
    );
    let (checkpoint_path, resume) = resume_from(&args, &options)?;
    if let Some(c) = &resume
        && c.state.features != features
    {
        bail!("{} was made on other data; pass the same data to resume, or --restart", checkpoint_path.display());
    }
    let bar = progress.bar(u64::from(options.steps), "GI teacher", "steps");
    if let Some(c) = &resume {
        bar.set_position(u64::from(c.state.step));
    }
    let (mut model, state) = train_single_eye(
        &train,
        features,
        &options,
        resume,
        args.checkpoint_every,
        &mut show_progress(&bar, "GI teacher"),
        &mut |c| c.save(&checkpoint_path).map_err(Into::into),
    )?;
    bar.finish_and_clear();
    // The scene the farm renders the G-buffer of when it serves the model.
    model.header.scene = Some(nephele_train::gi::data::read_manifest(&args.data)?.spec.scene);
    model.save(&args.out).with_context(|| format!("writing {}", args.out.display()))?;
    let train_psnr = evaluate_single_eye(&model, &train)?;
    let held_psnr = if held_out.is_empty() { f64::NAN } else { evaluate_single_eye(&model, &held_out)? };
    println!(
        "wrote {} after {} steps in {:.0} s: PSNR {train_psnr:.2} dB on the training frames, {held_psnr:.2} dB on {} held-out frames (displayed images)",
        args.out.display(),
        state.step,
        start.elapsed().as_secs_f64(),
        held_out.len()
    );
    println!(
        "loss curve (step, mean loss): {:?}",
        state.curve.iter().map(|(s, l)| (*s, (l * 1e5).round() / 1e5)).collect::<Vec<_>>()
    );
    Ok(())
}

/// The resumable checkpoint of this run, or `None` (absent, or `--restart`).
fn resume_from(args: &Args, options: &GiTrainOptions) -> Result<(PathBuf, Option<GiCheckpoint>)> {
    let path = args.checkpoint.clone().unwrap_or_else(|| args.out.with_extension("ckpt"));
    if !path.exists() || args.restart {
        return Ok((path, None));
    }
    let c = GiCheckpoint::load(&path)?;
    if c.state.options != *options {
        bail!("{} was made with other settings; pass the same settings to resume, or --restart", path.display());
    }
    println!("resuming from {} at step {}", path.display(), c.state.step);
    Ok((path, Some(c)))
}

fn student(args: &Args, options: &GiTrainOptions, teacher_path: &std::path::Path, progress: &Progress) -> Result<()> {
    let start = Instant::now();
    let teacher =
        GiModel::load(teacher_path).with_context(|| format!("loading the teacher {}", teacher_path.display()))?;
    if teacher.eyes() != 1 {
        bail!("{} is a stereo model; the teacher is a single-eye model", teacher_path.display());
    }
    let features = teacher.header.features;
    let pairs = load_pairs(&args.data, &features, true, args.input_spp)
        .with_context(|| format!("loading {}", args.data.display()))?;
    let eval = load_pairs(&args.data, &features, false, args.input_spp)?;
    println!(
        "train gi (stereo student of {}): {} training pairs, coherence weight {}, first layer and right head {:?}",
        teacher_path.display(),
        pairs.len(),
        args.coherence_weight,
        args.student_start
    );
    let student_start = match args.student_start {
        Start::Teacher => StudentStart::FromTeacher,
        Start::Fresh => StudentStart::Fresh,
    };
    let (checkpoint_path, resume) = resume_from(args, options)?;
    let bar = progress.bar(u64::from(options.steps), "GI stereo student", "steps");
    let (model, state) = train_stereo(
        &teacher,
        &pairs,
        options,
        StudentOptions { coherence_weight: args.coherence_weight, start: student_start },
        resume,
        args.checkpoint_every,
        &mut show_progress(&bar, "GI stereo student"),
        &mut |c| c.save(&checkpoint_path).map_err(Into::into),
    )?;
    bar.finish_and_clear();
    model.save(&args.out).with_context(|| format!("writing {}", args.out.display()))?;
    println!("wrote {} after {} steps in {:.0} s", args.out.display(), state.step, start.elapsed().as_secs_f64());
    if !eval.is_empty() {
        let stereo = evaluate_pairs(&eval, &shade_pairs(&model, &eval)?);
        let twice = evaluate_pairs(&eval, &shade_pairs(&teacher, &eval)?);
        println!(
            "on {} evaluation pairs: stereo {:.2} / {:.2} dB (left / right), teacher run twice {:.2} / {:.2} dB; inter-eye coherence error {:.5} (teacher twice {:.5})",
            eval.len(),
            stereo.psnr[0],
            stereo.psnr[1],
            twice.psnr[0],
            twice.psnr[1],
            stereo.coherence,
            twice.coherence
        );
    }
    Ok(())
}

/// A step callback that moves `bar` and shows the smoothed loss.
fn show_progress<'b>(bar: &'b indicatif::ProgressBar, name: &'static str) -> impl FnMut(GiStep) + 'b {
    let mut smoothed = None::<f32>;
    move |s| {
        let loss = smoothed.map_or(s.loss, |l| 0.95 * l + 0.05 * s.loss);
        smoothed = Some(loss);
        bar.set_position(u64::from(s.step));
        bar.set_message(format!("{name}, loss {loss:.5}"));
    }
}
