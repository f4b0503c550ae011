//! `nephele eval`: PSNR and SSIM of predictions against ground truth, NeRF-style.

use std::path::PathBuf;

use anyhow::{Context, Result};
use nephele_imaging::metrics;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Folder of predicted PNG images.
    #[arg(long)]
    pred: PathBuf,
    /// Folder of ground-truth PNG images with the same file names.
    #[arg(long)]
    gt: PathBuf,
    /// Background both sides are composited over before scoring ('white', 'black' or r,g,b).
    #[arg(long, default_value = "white", value_parser = super::parse_background)]
    background: [f32; 3],
    /// Also write the report as JSON to this file.
    #[arg(long)]
    json: Option<PathBuf>,
}

pub fn run(args: Args) -> Result<()> {
    let report = metrics::evaluate_dirs(&args.pred, &args.gt, args.background)
        .with_context(|| format!("evaluating {} against {}", args.pred.display(), args.gt.display()))?;
    println!("{:<32} {:>9} {:>8}", "image", "PSNR dB", "SSIM");
    for score in &report.per_image {
        println!("{:<32} {:>9.3} {:>8.5}", score.name, score.psnr, score.ssim);
    }
    println!(
        "{:<32} {:>9.3} {:>8.5}",
        format!("mean of {}", report.per_image.len()),
        report.mean_psnr,
        report.mean_ssim
    );
    if report.perfect_matches > 0 {
        println!("({} identical image(s) left out of the mean PSNR)", report.perfect_matches);
    }
    if let Some(path) = args.json {
        let text = serde_json::to_string_pretty(&report)?;
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
