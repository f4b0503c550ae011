//! `nephele bench encode`: the composer's per-frame stages at streaming sizes.
//!
//! Each frame of a moving synthetic scene is planned as object batches (an environment
//! behind everything with a panning texture plus a little per-pixel noise, as a path-traced
//! or neural background has; a solid and a translucent object in front), fused, converted
//! to YUV 4:2:0 and encoded; the encoded stream is decoded again to report PSNR against the
//! encoder's input beside the speed.

use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use nephele_composer::encode::{Effort, EncoderSettings, FrameKind, H264Encoder};
use nephele_composer::fusion::{BatchKey, BatchResult, Compositor, FrameLayout, FusionLimits, PlannedBatch};
use nephele_composer::testpattern;
use nephele_composer::yuv::Yuv420;
use nephele_geometry::PixelResults;
use nephele_geometry::camera::Camera;
use openh264_decode::decode_psnr;
use serde_json::json;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Picture layouts: `WxH` (mono) or `2xWxH` (stereo, side by side).
    #[arg(long, value_delimiter = ',', default_value = "640x480,1280x720,2x960x1080")]
    sizes: Vec<String>,
    /// Frames per size (the first is the IDR).
    #[arg(long, default_value_t = 60)]
    frames: u32,
    /// Stream frame rate the rate control plans for (bitrate = bytes x 8 x fps / frames).
    #[arg(long, default_value_t = 30.0)]
    fps: f32,
    /// Encoder bitrate in kbit/s (default: about 0.1 bit per pixel per frame).
    #[arg(long)]
    bitrate: Option<u32>,
    /// OpenH264 effort: low, medium or high.
    #[arg(long, default_value = "low")]
    effort: String,
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

fn parse_layout(text: &str) -> Result<FrameLayout> {
    let parts: Vec<&str> = text.split(['x', 'X']).collect();
    let num = |s: &str| s.trim().parse::<u32>().with_context(|| format!("bad number in '{text}'"));
    let layout = match parts.as_slice() {
        [w, h] => FrameLayout::mono(num(w)?, num(h)?),
        [n, w, h] => FrameLayout::side_by_side(num(w)?, num(h)?, num(n)? as u16),
        _ => anyhow::bail!("expected WxH or NxWxH, got '{text}'"),
    };
    layout.map_err(|e| anyhow::anyhow!("{text}: {e}"))
}

/// One frame of the benchmark scene as plan + batches (one environment batch per view and
/// per 64-row band, as several workers would send it, plus the test pattern's objects).
fn scene_frame(
    layout: FrameLayout,
    frame: u64,
    deadline: Instant,
) -> (nephele_composer::fusion::FramePlan, Vec<BatchResult>) {
    let (w, h) = (layout.view_width(), layout.view_height());
    let cameras: Vec<Camera> = (0..layout.views())
        .filter_map(|v| {
            let angle = frame as f32 * 0.01;
            let eye = glam::Vec3::new(3.0 * angle.sin() + f32::from(v) * 0.064, -3.0 * angle.cos(), 1.0);
            Camera::look_at(w, h, 0.9, eye, glam::Vec3::ZERO, glam::Vec3::Z).ok()
        })
        .collect();
    let (mut plan, mut batches) = testpattern::frame(1, frame, layout, &cameras, deadline);
    let shift = frame as u32 * 3;
    for view in 0..layout.views() {
        for (band, y0) in (0..h).step_by(64).enumerate() {
            let y1 = (y0 + 64).min(h);
            let pixels: Vec<u32> = (y0..y1).flat_map(|y| (0..w).map(move |x| y * w + x)).collect();
            let mut r = PixelResults::with_len(pixels.len());
            for (i, &p) in pixels.iter().enumerate() {
                let (x, y) = ((p % w + shift) as f32, (p / w) as f32);
                let smooth = 0.25 + 0.15 * (x * 0.02).sin() * (y * 0.015).cos() + 0.1 * ((x + y) * 0.005).sin();
                // Sharp-edged texture (16-pixel tiles) so that motion search has edges to follow.
                let tile = if ((x as u32 / 16) + (y as u32 / 16)).is_multiple_of(2) { 0.12 } else { 0.0 };
                // A little high-frequency noise, like a Monte Carlo or neural background.
                let hash = (p.wrapping_add(frame as u32 * 7919)).wrapping_mul(2_654_435_761) >> 24;
                let noise = (hash as f32 / 255.0 - 0.5) * 0.04;
                let v = (smooth + tile + noise).clamp(0.0, 1.0);
                r.color[i] = [v, v * 0.9, v * 0.8];
                r.opacity[i] = 1.0;
                r.depth[i] = 50.0;
            }
            let key = BatchKey { object: 100, batch: u32::from(view) * 1000 + band as u32 };
            plan.batches.push(PlannedBatch { key, view, pixels: pixels.clone().into() });
            batches.push(BatchResult::from_results(1, frame, view, key, pixels, r));
        }
    }
    (plan, batches)
}

mod openh264_decode {
    use openh264::decoder::Decoder;
    use openh264::formats::YUVSource;

    /// Decodes one access unit and returns the luma PSNR against `reference` (dB).
    pub fn decode_psnr(decoder: &mut Decoder, data: &[u8], reference: &[u8], width: usize) -> Option<f64> {
        let yuv = decoder.decode(data).ok()??;
        let stride = yuv.strides().0;
        let (w, h) = yuv.dimensions();
        if w != width {
            return None;
        }
        let mut se = 0.0f64;
        for r in 0..h {
            for (a, b) in yuv.y()[r * stride..r * stride + w].iter().zip(&reference[r * w..(r + 1) * w]) {
                se += (f64::from(*a) - f64::from(*b)).powi(2);
            }
        }
        let mse = se / (w * h) as f64;
        Some(10.0 * (255.0f64 * 255.0 / mse.max(1e-10)).log10())
    }
}

pub fn run(args: Args, progress: &dyn Progress) -> Result<()> {
    let effort = match args.effort.as_str() {
        "low" => Effort::Low,
        "medium" => Effort::Medium,
        "high" => Effort::High,
        other => anyhow::bail!("effort must be low, medium or high, not '{other}'"),
    };
    anyhow::ensure!(args.frames >= 2, "--frames must be at least 2");
    println!(
        "composer stages per frame, {} frames per size, {} fps rate control, effort {:?}, {} threads for fusion/YUV",
        args.frames,
        args.fps,
        effort,
        rayon::current_num_threads()
    );
    println!(
        "{:<16} {:>9} {:>8} {:>8} {:>9} {:>9} {:>8} {:>10} {:>9} {:>9} {:>8}",
        "layout", "fuse ms", "yuv ms", "enc ms", "IDR ms", "P ms", "enc fps", "kbit/s", "IDR kB", "P kB", "PSNR-Y"
    );
    let mut rows = Vec::new();
    for text in &args.sizes {
        let layout = parse_layout(text)?;
        let (w, h) = (layout.width(), layout.height());
        let mut settings = EncoderSettings::low_latency(w, h);
        settings.fps = args.fps;
        settings.effort = effort;
        if let Some(k) = args.bitrate {
            settings.bitrate_bps = k.saturating_mul(1000);
        }
        let mut encoder = H264Encoder::new(settings).with_context(|| format!("encoder for {text}"))?;
        let mut decoder = openh264::decoder::Decoder::new().map_err(|e| anyhow::anyhow!("decoder: {e}"))?;
        let mut compositor = Compositor::new(FusionLimits::default());
        compositor.open_session(1)?;
        let mut yuv = Yuv420::new(w, h)?;
        let (mut fuse_s, mut yuv_s, mut idr_s, mut p_s) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        let (mut idr_bytes, mut p_bytes, mut p_frames, mut idr_frames) = (0u64, 0u64, 0u64, 0u64);
        let mut psnr_sum = 0.0;
        let mut psnr_n = 0u32;
        let mut skipped = 0u32;
        let bar = progress.bar(u64::from(args.frames), text, "frames");
        for f in 0..args.frames {
            let far = Instant::now() + Duration::from_secs(3600);
            let (plan, batches) = scene_frame(layout, u64::from(f), far);
            // Fusion: gathering the batches and compositing them (scene generation excluded).
            let t0 = Instant::now();
            compositor.plan_frame(plan)?;
            for b in batches {
                compositor.add_batch(b)?;
            }
            let fused = compositor.poll(Instant::now());
            let t1 = Instant::now();
            let frame = fused.into_iter().next().context("a complete frame is fused at once")?;
            yuv.fill_from_linear_rgb(&frame.rgb)?;
            let t2 = Instant::now();
            let encoded = encoder.encode(&yuv, u64::from(f) * 1000 / args.fps as u64)?;
            let t3 = Instant::now();
            fuse_s += (t1 - t0).as_secs_f64();
            yuv_s += (t2 - t1).as_secs_f64();
            let enc = (t3 - t2).as_secs_f64();
            match encoded.kind {
                FrameKind::Skipped => {
                    p_s += enc;
                    skipped += 1;
                }
                FrameKind::Idr => {
                    idr_s += enc;
                    idr_bytes += encoded.data.len() as u64;
                    idr_frames += 1;
                }
                _ => {
                    p_s += enc;
                    p_bytes += encoded.data.len() as u64;
                    p_frames += 1;
                }
            }
            if let Some(p) = decode_psnr(&mut decoder, &encoded.data, &yuv.y, w as usize) {
                psnr_sum += p;
                psnr_n += 1;
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let n = f64::from(args.frames);
        let enc_ms = (idr_s + p_s) / n * 1e3;
        let kbps = (idr_bytes + p_bytes) as f64 * 8.0 * f64::from(args.fps) / n / 1e3;
        let idr_ms = idr_s / idr_frames.max(1) as f64 * 1e3;
        let p_ms = p_s / (p_frames + u64::from(skipped)).max(1) as f64 * 1e3;
        let psnr = psnr_sum / f64::from(psnr_n.max(1));
        let stats = encoder.stats();
        println!(
            "{:<16} {:>9.2} {:>8.2} {:>8.2} {:>9.2} {:>9.2} {:>8.1} {:>10.0} {:>9.1} {:>9.1} {:>8.2}",
            format!("{text} ({w}x{h})"),
            fuse_s / n * 1e3,
            yuv_s / n * 1e3,
            enc_ms,
            idr_ms,
            p_ms,
            1e3 / enc_ms,
            kbps,
            idr_bytes as f64 / idr_frames.max(1) as f64 / 1e3,
            p_bytes as f64 / p_frames.max(1) as f64 / 1e3,
            psnr
        );
        rows.push(json!({
            "layout": text, "width": w, "height": h, "frames": args.frames,
            "fuse_ms": fuse_s / n * 1e3, "yuv_ms": yuv_s / n * 1e3,
            "encode_ms": enc_ms, "idr_encode_ms": idr_ms, "p_encode_ms": p_ms, "encode_fps": 1e3 / enc_ms,
            "target_kbps": settings.bitrate_bps / 1000, "kbps": kbps,
            "idr_kbytes": idr_bytes as f64 / idr_frames.max(1) as f64 / 1e3,
            "p_kbytes": p_bytes as f64 / p_frames.max(1) as f64 / 1e3,
            "psnr_y_db": psnr, "decoded_frames": psnr_n, "skipped_frames": skipped,
            "vbv_peak_ms": stats.vbv_peak_ms, "vbv_overflows": stats.vbv_overflows,
        }));
        println!(
            "{:<16} target {} kbit/s, modelled VBV ({} ms) peak {:.0} ms, {} overflows, {} skipped by rate control, {} of {} frames decoded",
            "",
            settings.bitrate_bps / 1000,
            settings.vbv_ms,
            stats.vbv_peak_ms,
            stats.vbv_overflows,
            skipped,
            psnr_n,
            args.frames
        );
    }
    if let Some(path) = args.json {
        std::fs::write(&path, serde_json::to_string_pretty(&rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}
