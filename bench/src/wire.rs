//! `nephele bench wire`: what the protocol costs. Encode and decode time per pixel (packed
//! arrays against serde's element-by-element encoding of the same data), bytes on the wire
//! per pixel, and the loopback throughput of batch results between two processes (blocking
//! I/O) and between two tasks of one process (the tokio codec the worker uses).

use std::io::{BufRead, BufReader};
use std::net::{TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail, ensure};
use nephele_proto::stream::{framed, handshake};
use nephele_proto::{
    BatchIds, BatchResult, FrameConfig, FrameReader, FrameWriter, Goodbye, KernelStats, Message, RayBatch,
    ResultEncoding, Role, ViewProjection, decode_frame, encode_frame,
};
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::Progress;

#[derive(Debug, clap::Args)]
pub struct WireArgs {
    /// Pixels per batch.
    #[arg(long, default_value_t = 16384)]
    pixels: usize,
    /// Batches sent over each loopback link.
    #[arg(long, default_value_t = 2000)]
    batches: usize,
    /// Repetitions of the in-memory encode/decode timings.
    #[arg(long, default_value_t = 200)]
    repeats: usize,
    /// Built-in scene of the compact-results frame: its default view is path traced at
    /// `--frame-size`, cut into batches, sent f32 and compact, and the composites compared.
    #[arg(long, default_value = "glossy")]
    frame_scene: String,
    /// Size of that frame.
    #[arg(long, default_value = "640x480", value_parser = nephele_geometry::camera::parse_size)]
    frame_size: (u32, u32),
    /// Also write the results as JSON.
    #[arg(long)]
    json: Option<std::path::PathBuf>,
}

/// The receiving process of the loopback run (spawned by `bench wire`).
#[derive(Debug, clap::Args)]
pub struct SinkArgs {
    /// Address to listen on; the bound address is printed on stdout.
    #[arg(long, default_value = "127.0.0.1:0")]
    listen: String,
}

/// Pixel result bytes (colour 12 + opacity 4 + depth 4) per pixel: the payload the figures
/// count as "pixel results".
const RESULT_BYTES_PER_PIXEL: f64 = 20.0;

fn sample_result(pixels: usize, batch_id: u64) -> BatchResult {
    let (width, height) = (4096u32, 4096u32);
    let start = (batch_id as usize * pixels) % (width as usize * height as usize - pixels);
    let pixels: Vec<u32> = (start as u32..(start + pixels) as u32).collect();
    let hash = |p: u32| (p.wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32;
    BatchResult {
        ids: BatchIds { batch_id, task_id: batch_id / 4, session_id: 1, frame_id: batch_id / 16, view_index: 0 },
        worker_id: 1,
        width,
        height,
        // One pixel in five is a miss: no colour, no opacity, no depth.
        color: pixels
            .iter()
            .map(|&p| if p % 5 == 0 { [0.0; 3] } else { [hash(p) * 0.8, hash(p ^ 1) * 0.8, hash(p ^ 2) * 0.8] })
            .collect(),
        opacity: pixels.iter().map(|&p| if p % 5 == 0 { 0.0 } else { 1.0 }).collect(),
        depth: pixels.iter().map(|&p| if p % 5 == 0 { 0.0 } else { 2.0 + hash(p) }).collect(),
        pixels,
        render_time_us: 1000,
        stats: KernelStats { rays: 1, rays_hit: 1, queries: 1, hidden: 0 },
        encoding: nephele_proto::ResultEncoding::F32,
    }
}

/// One real frame through both encodings: the default view of a built-in scene, path traced
/// (transparent background), cut into batches of `batch` pixels, encoded f32 and compact and
/// decoded; bytes per frame and the composite over white (8-bit sRGB, as a viewer sees it)
/// of the compact path against the f32 path.
fn compact_frame_figures(scene: &str, (width, height): (u32, u32), batch: usize) -> Result<serde_json::Value> {
    use nephele_geometry::camera::Camera;
    use nephele_kernels::kernel::{PixelResults, all_pixels, frame_to_image};
    let builtin = nephele_pathtracer::scenes::load(scene)?;
    let (eye, target, fov_y) = builtin.default_view();
    let camera = Camera::look_at(width, height, fov_y, eye, target, glam::Vec3::Z)?;
    let options = nephele_kernels::assets::LoadOptions { pathtrace_spp: 2, pathtrace_bounces: 2, ..Default::default() };
    let kernel = nephele_kernels::assets::path_traced(builtin.scene.clone(), &options)?;
    let pixels = all_pixels(&camera);
    let (rendered, _) = kernel.render_pixels(&camera, &pixels)?;
    let cfg = FrameConfig::default();
    let mut received = PixelResults::with_len(pixels.len());
    let (mut f32_bytes, mut compact_bytes, mut touched) = (0usize, 0usize, 0usize);
    for (k, chunk) in pixels.chunks(batch).enumerate() {
        let range = k * batch..k * batch + chunk.len();
        let mut result = sample_result(1, k as u64);
        result.width = width;
        result.height = height;
        result.pixels = chunk.to_vec();
        result.color = rendered.color[range.clone()].to_vec();
        result.opacity = rendered.opacity[range.clone()].to_vec();
        result.depth = rendered.depth[range].to_vec();
        let mut frame = Vec::new();
        encode_frame(&Message::BatchResult(result.clone()), &mut frame, &cfg)?;
        f32_bytes += frame.len();
        frame.clear();
        result.encoding = ResultEncoding::Compact;
        encode_frame(&Message::BatchResult(result), &mut frame, &cfg)?;
        compact_bytes += frame.len();
        let Ok(Message::BatchResult(got)) = decode_frame(&frame, &cfg)?.0 else { bail!("compact frame rejected") };
        touched += got.pixels.len();
        for (j, &p) in got.pixels.iter().enumerate() {
            let i = p as usize;
            received.color[i] = got.color[j];
            received.opacity[i] = got.opacity[j];
            received.depth[i] = got.depth[j];
        }
    }
    let exact = frame_to_image(width, height, &rendered).context("frame")?;
    let compact = frame_to_image(width, height, &received).context("frame")?;
    let (psnr, _) = nephele_imaging::metrics::psnr_and_ssim(&compact, &exact, [1.0; 3])?;
    let depth_error = (0..pixels.len())
        .filter(|&i| rendered.opacity[i] > 0.0 && rendered.depth[i] > 0.0)
        .map(|i| ((received.depth[i] - rendered.depth[i]) / rendered.depth[i]).abs())
        .fold(0.0f32, f32::max);
    let n = pixels.len();
    println!(
        "one {width}x{height} frame of '{scene}' in batches of {batch}: {:.1} % of pixels touched; f32 {:.0} kB ({:.2} B/px), compact {:.0} kB ({:.2} B/px, {:.2} B per touched pixel): {:.1}x fewer bytes; composite over white PSNR {} against the f32 path, largest relative depth error {depth_error:.2e}",
        100.0 * touched as f64 / n as f64,
        f32_bytes as f64 / 1e3,
        f32_bytes as f64 / n as f64,
        compact_bytes as f64 / 1e3,
        compact_bytes as f64 / n as f64,
        compact_bytes as f64 / touched.max(1) as f64,
        f32_bytes as f64 / compact_bytes.max(1) as f64,
        if psnr.is_finite() { format!("{psnr:.1} dB") } else { "infinite (identical 8-bit images)".into() }
    );
    Ok(json!({"scene": scene, "width": width, "height": height, "touched_fraction": touched as f64 / n as f64,
        "f32_bytes": f32_bytes, "compact_bytes": compact_bytes, "composite_psnr_db": if psnr.is_finite() { psnr } else { 999.0 },
        "max_relative_depth_error": depth_error}))
}

/// The same result as serde sees it without packing: every element visited on its own.
#[derive(Serialize, Deserialize)]
struct ElementWise {
    ids: BatchIds,
    worker_id: u64,
    width: u32,
    height: u32,
    pixels: Vec<u32>,
    color: Vec<[f32; 3]>,
    opacity: Vec<f32>,
    depth: Vec<f32>,
    render_time_us: u64,
    stats: KernelStats,
}

impl From<&BatchResult> for ElementWise {
    fn from(r: &BatchResult) -> ElementWise {
        ElementWise {
            ids: r.ids,
            worker_id: r.worker_id,
            width: r.width,
            height: r.height,
            pixels: r.pixels.clone(),
            color: r.color.clone(),
            opacity: r.opacity.clone(),
            depth: r.depth.clone(),
            render_time_us: r.render_time_us,
            stats: r.stats,
        }
    }
}

/// One message's in-memory codec figures: median encode and decode (validation included)
/// per pixel of its `pixels`, and its frame's bytes per pixel.
struct Codec {
    encode_ns: f64,
    decode_ns: f64,
    bytes_per_pixel: f64,
}

fn frame_codec(message: &Message, pixels: usize, repeats: usize) -> Result<Codec> {
    let cfg = FrameConfig::default();
    let mut frame = Vec::new();
    encode_frame(message, &mut frame, &cfg)?;
    let mut buf = Vec::with_capacity(frame.len());
    let encode_ns = median_ns(repeats, || {
        buf.clear();
        encode_frame(message, &mut buf, &cfg).expect("encodes");
    }) / pixels as f64;
    let decode_ns = median_ns(repeats, || {
        let (decoded, _) = decode_frame(&frame, &cfg).expect("decodes");
        assert!(decoded.is_ok());
    }) / pixels as f64;
    Ok(Codec { encode_ns, decode_ns, bytes_per_pixel: frame.len() as f64 / pixels as f64 })
}

/// Median of `repeats` timings of `f`, nanoseconds.
fn median_ns(repeats: usize, mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..repeats.max(3))
        .map(|_| {
            let start = Instant::now();
            f();
            start.elapsed().as_nanos() as f64
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[times.len() / 2]
}

pub fn run(args: WireArgs, progress: &dyn Progress) -> Result<()> {
    ensure!(args.pixels > 0 && args.batches > 0, "--pixels and --batches must be positive");
    let cfg = FrameConfig::default();
    let n = args.pixels;
    let result = sample_result(n, 0);
    let message = Message::BatchResult(result.clone());

    // In memory: packed (the protocol) against element by element.
    let packed = frame_codec(&message, n, args.repeats)?;
    let (encode_ns, decode_ns, result_bytes_per_pixel) = (packed.encode_ns, packed.decode_ns, packed.bytes_per_pixel);
    let validate_ns = median_ns(args.repeats, || {
        nephele_proto::validate::message(&message).expect("valid");
    }) / n as f64;
    let elementwise = ElementWise::from(&result);
    let plain = postcard::to_allocvec(&elementwise)?;
    let mut plain_buf = Vec::with_capacity(plain.len());
    let plain_encode_ns = median_ns(args.repeats, || {
        plain_buf = postcard::to_extend(&elementwise, std::mem::take(&mut plain_buf)).expect("encodes");
        plain_buf.clear();
    }) / n as f64;
    let plain_decode_ns = median_ns(args.repeats, || {
        let decoded: ElementWise = postcard::from_bytes(&plain).expect("decodes");
        assert_eq!(decoded.pixels.len(), n);
    }) / n as f64;
    // The compact form of the same result (80 % of its pixels touched).
    let compact_message = Message::BatchResult(BatchResult { encoding: ResultEncoding::Compact, ..result.clone() });
    let compact = frame_codec(&compact_message, n, args.repeats)?;
    let (compact_encode_ns, compact_decode_ns, compact_bytes_per_pixel) =
        (compact.encode_ns, compact.decode_ns, compact.bytes_per_pixel);
    let batch = Message::RayBatch(RayBatch {
        ids: result.ids,
        asset_id: "lego".into(),
        camera: ViewProjection {
            width: 4096,
            height: 4096,
            view: glam::Mat4::IDENTITY,
            projection: glam::Mat4::IDENTITY,
        },
        pixels: result.pixels.clone(),
        deadline_in_us: Some(50_000),
        composer: "127.0.0.1:9000".into(),
        derived: Vec::new(),
        reuse: Default::default(),
        occluders: Vec::new(),
    });
    let mut batch_frame = Vec::new();
    encode_frame(&batch, &mut batch_frame, &cfg)?;
    let batch_bytes_per_pixel = batch_frame.len() as f64 / n as f64;

    println!("protocol cost, {n} pixels per batch, {} repeats, medians", args.repeats);
    println!("{:<34} {:>12} {:>12} {:>12}", "encoding", "encode ns/px", "decode ns/px", "bytes/px");
    println!(
        "{:<34} {:>12.2} {:>12.2} {:>12.2}",
        "packed arrays (nephele-proto)", encode_ns, decode_ns, result_bytes_per_pixel
    );
    println!(
        "{:<34} {:>12.2} {:>12.2} {:>12.2}",
        "compact (80 % touched, half floats)", compact_encode_ns, compact_decode_ns, compact_bytes_per_pixel
    );
    println!(
        "{:<34} {:>12.2} {:>12.2} {:>12.2}",
        "element by element (serde+postcard)",
        plain_encode_ns,
        plain_decode_ns,
        plain.len() as f64 / n as f64
    );
    println!(
        "packed encode and decode include validation (finite colour, opacity in [0,1], indices in the image): {validate_ns:.2} ns/px of it"
    );
    println!("ray batch (master -> worker): {batch_bytes_per_pixel:.2} bytes/px on the wire");
    let frame_figures = compact_frame_figures(&args.frame_scene, args.frame_size, n).context("compact frame")?;

    let bar = progress.bar(3 * args.batches as u64, "loopback", "batches");
    let process = loopback_processes(&args, &bar).context("two-process loopback")?;
    let tasks = loopback_tokio(&args, &bar, None).context("tokio loopback")?;
    // The same inside TLS (`--farm-tls`), with a farm certificate made for the run.
    let tls_dir = tempfile::tempdir().context("a folder for the farm certificate")?;
    nephele_transport::FarmTls::generate(tls_dir.path())?;
    let farm_tls = nephele_transport::FarmTls::load(tls_dir.path())?;
    let tasks_tls = loopback_tokio(&args, &bar, Some(&farm_tls)).context("tokio loopback over TLS")?;
    bar.finish_and_clear();
    println!(
        "{:<34} {:>10} {:>10} {:>12} {:>12}",
        "loopback TCP, batch results", "batches/s", "GB/s px", "GB/s wire", "Mpixels/s"
    );
    for (name, r) in [
        ("two processes (blocking I/O)", &process),
        ("two tokio tasks (worker codec)", &tasks),
        ("the same inside farm TLS", &tasks_tls),
    ] {
        println!(
            "{:<34} {:>10.0} {:>10.2} {:>12.2} {:>12.1}",
            name,
            r.batches_per_second,
            r.batches_per_second * n as f64 * RESULT_BYTES_PER_PIXEL / 1e9,
            r.wire_bytes_per_second / 1e9,
            r.batches_per_second * n as f64 / 1e6
        );
    }
    // What TLS adds per pixel result: the difference of the two tokio rows' times per pixel
    // (both ends on this machine's cores: encryption and decryption together).
    let ns_per_pixel = |r: &Loopback| 1e9 / (r.batches_per_second * n as f64);
    let tls_ns_per_pixel = ns_per_pixel(&tasks_tls) - ns_per_pixel(&tasks);
    println!(
        "farm TLS: {tls_ns_per_pixel:.2} ns more per pixel result (f32 results, {:.1} bytes/px on the wire; compact results carry {compact_bytes_per_pixel:.1})",
        tasks.wire_bytes_per_second / (tasks.batches_per_second * n as f64)
    );
    // The connection's opening, without and with the farm credential (alternated).
    let (open_us, secret_us) = openings(200).context("connection openings")?;
    println!(
        "connection opening over loopback (Hellos; + challenge and proof), median of 200 each: open farm {open_us:.0} us, with the farm secret {secret_us:.0} us ({:+.0} us per connection, nothing per frame)",
        secret_us - open_us
    );
    if let Some(path) = &args.json {
        let loopback = |r: &Loopback| {
            json!({
                "batches_per_second": r.batches_per_second,
                "pixel_result_gb_per_second": r.batches_per_second * n as f64 * RESULT_BYTES_PER_PIXEL / 1e9,
                "wire_gb_per_second": r.wire_bytes_per_second / 1e9,
            })
        };
        let out = json!({
            "pixels_per_batch": n,
            "batches": args.batches,
            "packed": { "encode_ns_per_pixel": encode_ns, "decode_ns_per_pixel": decode_ns, "validate_ns_per_pixel": validate_ns, "bytes_per_pixel": result_bytes_per_pixel },
            "elementwise": { "encode_ns_per_pixel": plain_encode_ns, "decode_ns_per_pixel": plain_decode_ns, "bytes_per_pixel": plain.len() as f64 / n as f64 },
            "ray_batch_bytes_per_pixel": batch_bytes_per_pixel,
            "compact": { "encode_ns_per_pixel": compact_encode_ns, "decode_ns_per_pixel": compact_decode_ns, "bytes_per_pixel": compact_bytes_per_pixel, "frame": frame_figures },
            "loopback_two_processes": loopback(&process),
            "loopback_tokio_tasks": loopback(&tasks),
            "loopback_tokio_tasks_farm_tls": loopback(&tasks_tls),
            "farm_tls_ns_per_pixel": tls_ns_per_pixel,
            "opening_us": { "open_farm": open_us, "with_farm_secret": secret_us },
        });
        std::fs::write(path, serde_json::to_string_pretty(&out)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Median time of a connection's opening (connect, the Hellos, and with a secret the
/// challenge and the proofs) between two tokio tasks, `count` times without and `count`
/// times with a farm secret, alternated; microseconds.
fn openings(count: usize) -> Result<(f64, f64)> {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    runtime.block_on(async move {
        let secret = nephele_proto::auth::FarmSecret::generate()?;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let timeout = Duration::from_secs(10);
        let server_secret = secret.clone();
        let server = tokio::spawn(async move {
            for i in 0..2 * count {
                let (stream, _) = listener.accept().await?;
                stream.set_nodelay(true)?;
                let mut conn = framed(stream, FrameConfig::default());
                let with = (i % 2 == 1).then_some(&server_secret);
                handshake(&mut conn, Role::Composer, &[Role::Tool], with, timeout).await?;
            }
            anyhow::Ok(())
        });
        let (mut open, mut with_secret) = (Vec::new(), Vec::new());
        for i in 0..2 * count {
            let start = Instant::now();
            let stream = tokio::net::TcpStream::connect(addr).await?;
            stream.set_nodelay(true)?;
            let mut conn = framed(stream, FrameConfig::default());
            let with = (i % 2 == 1).then_some(&secret);
            handshake(&mut conn, Role::Tool, &[Role::Composer], with, timeout).await?;
            let us = start.elapsed().as_secs_f64() * 1e6;
            if with.is_some() { with_secret.push(us) } else { open.push(us) }
        }
        server.await??;
        let median = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        Ok((median(&mut open), median(&mut with_secret)))
    })
}

#[derive(Debug)]
struct Loopback {
    batches_per_second: f64,
    wire_bytes_per_second: f64,
}

/// Sender here, receiver in a child process (`bench wire-sink`), blocking sockets. Timed
/// from the first byte to the receiver's goodbye, which it sends after decoding and
/// validating the last batch.
fn loopback_processes(args: &WireArgs, bar: &indicatif::ProgressBar) -> Result<Loopback> {
    let exe = std::env::current_exe().context("locating the nephele binary")?;
    let mut child = Command::new(exe)
        .args(["--quiet", "bench", "wire-sink", "--listen", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .spawn()
        .context("starting the receiving process")?;
    let stdout = child.stdout.take().context("child stdout")?;
    let mut lines = BufReader::new(stdout).lines();
    let addr = lines.next().context("the receiver printed no address")??;
    let stream = TcpStream::connect(addr.trim()).with_context(|| format!("connecting to {addr}"))?;
    stream.set_nodelay(true)?;
    let cfg = FrameConfig::default();
    let mut reader = FrameReader::new(stream.try_clone()?, cfg);
    let mut writer = FrameWriter::new(stream, cfg);
    nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Tool, &[Role::Composer], None)?;
    // Distinct batches, encoded while timing: the sender's encode cost is part of the link.
    let messages: Vec<Message> = (0..8).map(|i| Message::BatchResult(sample_result(args.pixels, i))).collect();
    let mut wire_bytes = 0u64;
    let mut frame = Vec::new();
    let start = Instant::now();
    for i in 0..args.batches {
        frame.clear();
        encode_frame(&messages[i % messages.len()], &mut frame, &cfg)?;
        writer.write_raw(&frame)?;
        wire_bytes += frame.len() as u64;
        bar.inc(1);
    }
    writer.write_message(&Message::Goodbye(Goodbye { reason: "done".into(), returned_batches: vec![] }))?;
    writer.flush()?;
    match reader.read_message()? {
        Ok(Message::Goodbye(g)) => ensure!(g.reason == format!("received {}", args.batches), "receiver: {}", g.reason),
        other => bail!("expected the receiver's goodbye, got {other:?}"),
    }
    let seconds = start.elapsed().as_secs_f64();
    let status = child.wait()?;
    ensure!(status.success(), "the receiving process failed");
    Ok(Loopback {
        batches_per_second: args.batches as f64 / seconds,
        wire_bytes_per_second: wire_bytes as f64 / seconds,
    })
}

/// `nephele bench wire-sink`: accepts one connection as a composer, decodes and validates
/// every frame, answers the sender's goodbye with its own.
pub fn sink(args: SinkArgs) -> Result<()> {
    let listener = TcpListener::bind(&args.listen).with_context(|| format!("binding {}", args.listen))?;
    println!("{}", listener.local_addr()?);
    let (stream, _) = listener.accept()?;
    stream.set_nodelay(true)?;
    let cfg = FrameConfig::default();
    let mut reader = FrameReader::new(BufReader::with_capacity(1 << 18, stream.try_clone()?), cfg);
    let mut writer = FrameWriter::new(stream, cfg);
    nephele_proto::frame::handshake(&mut reader, &mut writer, Role::Composer, &[Role::Tool, Role::Worker], None)?;
    let mut received = 0u64;
    loop {
        match reader.read_message()? {
            Ok(Message::BatchResult(r)) => {
                ensure!(r.pixels.len() == r.depth.len(), "inconsistent result");
                received += 1;
            }
            Ok(Message::Goodbye(_)) => break,
            Ok(other) => bail!("unexpected {} message", other.kind()),
            Err(rejected) => bail!("{rejected}"),
        }
    }
    writer.write_message(&Message::Goodbye(Goodbye {
        reason: format!("received {received}"),
        returned_batches: vec![],
    }))?;
    writer.flush()?;
    Ok(())
}

/// Both ends as tokio tasks over a loopback socket, with the codec the worker uses.
/// With `tls`, inside TLS with a farm certificate ([`nephele_transport`]).
fn loopback_tokio(
    args: &WireArgs,
    bar: &indicatif::ProgressBar,
    tls: Option<&nephele_transport::FarmTls>,
) -> Result<Loopback> {
    use futures_util::{SinkExt, StreamExt};

    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let batches = args.batches;
    let pixels = args.pixels;
    let (server_tls, client_tls) = (tls.cloned(), tls.cloned());
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let timeout = Duration::from_secs(10);
        let receiver = tokio::spawn(async move {
            let (stream, _) = listener.accept().await?;
            let stream = nephele_transport::accept(stream, server_tls.as_ref(), timeout).await?;
            let mut conn = framed(stream, FrameConfig::default());
            handshake(&mut conn, Role::Composer, &[Role::Tool], None, timeout).await?;
            let mut received = 0u64;
            while let Some(item) = conn.next().await {
                match item?.map_err(nephele_proto::ProtoError::from)? {
                    Message::BatchResult(_) => received += 1,
                    Message::Goodbye(_) => break,
                    other => bail!("unexpected {} message", other.kind()),
                }
            }
            conn.send(&Message::Goodbye(Goodbye { reason: format!("received {received}"), returned_batches: vec![] }))
                .await?;
            anyhow::Ok(received)
        });
        let stream = nephele_transport::connect(&addr.to_string(), client_tls.as_ref(), timeout).await?;
        let mut conn = framed(stream, FrameConfig::default());
        handshake(&mut conn, Role::Tool, &[Role::Composer], None, timeout).await?;
        let messages: Vec<Message> = (0..8).map(|i| Message::BatchResult(sample_result(pixels, i))).collect();
        let mut frame_lens = Vec::new();
        for m in &messages {
            let mut frame = Vec::new();
            encode_frame(m, &mut frame, &FrameConfig::default())?;
            frame_lens.push(frame.len() as u64);
        }
        let mut wire_bytes = 0u64;
        let start = Instant::now();
        for i in 0..batches {
            conn.send(&messages[i % messages.len()]).await?;
            wire_bytes += frame_lens[i % messages.len()];
            bar.inc(1);
        }
        conn.send(&Message::Goodbye(Goodbye { reason: "done".into(), returned_batches: vec![] })).await?;
        match conn.next().await {
            Some(Ok(Ok(Message::Goodbye(_)))) => {}
            other => bail!("expected the receiver's goodbye, got {other:?}"),
        }
        let seconds = start.elapsed().as_secs_f64();
        let received = receiver.await??;
        ensure!(received == batches as u64, "received {received} of {batches}");
        Ok(Loopback {
            batches_per_second: batches as f64 / seconds,
            wire_bytes_per_second: wire_bytes as f64 / seconds,
        })
    })
}
