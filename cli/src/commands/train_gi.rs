//! `nephele train gi`: the single-eye global-illumination U-Net (the stereo GI model's
//! teacher) on a dataset of `nephele dataset gi`, with a progress bar, checkpoints and resume.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use nephele_train::gi::train::{GiCheckpoint, GiTrainOptions, evaluate_single_eye, load_single_eye, train_single_eye};

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
    let start = Instant::now();
    let (train, held_out, features, non_finite) =
        load_single_eye(&args.data).with_context(|| format!("loading the GI dataset {}", args.data.display()))?;
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
    let checkpoint_path = args.checkpoint.clone().unwrap_or_else(|| args.out.with_extension("ckpt"));
    let resume = if checkpoint_path.exists() && !args.restart {
        let c = GiCheckpoint::load(&checkpoint_path)?;
        if c.state.options != options || c.state.features != features {
            bail!(
                "{} was made with other settings or data; pass the same settings to resume, or --restart",
                checkpoint_path.display()
            );
        }
        println!("resuming from {} at step {}", checkpoint_path.display(), c.state.step);
        Some(c)
    } else {
        None
    };
    let bar = progress.bar(u64::from(options.steps), "GI teacher", "steps");
    if let Some(c) = &resume {
        bar.set_position(u64::from(c.state.step));
    }
    let mut smoothed = None::<f32>;
    let (model, state) = train_single_eye(
        &train,
        features,
        &options,
        resume,
        args.checkpoint_every,
        &mut |s| {
            let loss = smoothed.map_or(s.loss, |l| 0.95 * l + 0.05 * s.loss);
            smoothed = Some(loss);
            bar.set_position(u64::from(s.step));
            bar.set_message(format!("GI teacher, loss {loss:.5}"));
        },
        &mut |c| c.save(&checkpoint_path),
    )?;
    bar.finish_and_clear();
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
