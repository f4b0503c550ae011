//! Field checks run on every decoded message (and on every message before it is sent), so
//! that nothing past the decoder sees a NaN camera, a pixel outside its image, arrays of
//! different lengths, or a name that could escape a directory.

use crate::error::ValidationError;
use crate::messages::{
    BatchDone, BatchFailed, BatchResult, ClientPose, CloseStream, ComposerRegister, ErrorMessage, FramePlan, Goodbye,
    LoadReport, Message, OpenStream, RayBatch, Register, Registered, ReuseLimits, StreamOpened, ViewProjection,
};

/// Largest image side on the wire (a camera itself accepts up to
/// `nephele_geometry::camera::MAX_IMAGE_SIDE`).
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Most pixels in one batch: 2 Mi pixels, a 48 MiB result, under the default frame limit.
pub const MAX_BATCH_PIXELS: usize = 1 << 21;
/// Longest worker name.
pub const MAX_NAME_LEN: usize = 64;
/// Longest asset id.
pub const MAX_ASSET_ID_LEN: usize = 128;
/// Longest kernel kind name, and most kinds per worker.
pub const MAX_KERNEL_NAME_LEN: usize = 32;
pub const MAX_KERNELS: usize = 32;
/// Longest `host:port`.
pub const MAX_ADDRESS_LEN: usize = 255;
/// Longest free-text message or reason.
pub const MAX_TEXT_LEN: usize = 4096;
/// Most batch ids a worker hands back in one [`Goodbye`].
pub const MAX_RETURNED_BATCHES: usize = 1 << 16;
/// Most render threads a worker may claim.
pub const MAX_THREADS: u32 = 1 << 16;
/// Load report interval bounds, milliseconds.
pub const LOAD_REPORT_INTERVAL_MS: (u32, u32) = (10, 60_000);
/// Longest SDP offer or answer: 64 KiB (a browser's offer is a few kilobytes).
pub const MAX_SDP_LEN: usize = 64 * 1024;
/// Most views of one session (a 45-view quilt fits).
pub const MAX_VIEWS: u32 = nephele_geometry::camera::MAX_VIEWS as u32;
/// Longest session name (the HTTP API's public session id).
pub const MAX_SESSION_NAME_LEN: usize = 64;
/// Highest target frame rate of a stream.
pub const MAX_TARGET_FPS: f32 = 240.0;
/// Most parts (object x view) in one frame plan.
pub const MAX_PLAN_PARTS: usize = 1 << 16;

/// Checks every field of `message`.
pub fn message(message: &Message) -> Result<(), ValidationError> {
    match message {
        // Magic and version are checked while decoding; the role is an enum.
        Message::Hello(_) | Message::Cancel(_) => Ok(()),
        Message::Register(m) => register(m),
        Message::Registered(m) => registered(m),
        Message::LoadReport(m) => load_report(m),
        Message::RayBatch(m) => ray_batch(m),
        Message::BatchResult(m) => batch_result(m),
        Message::BatchDone(m) => batch_done(m),
        Message::BatchFailed(m) => batch_failed(m),
        Message::Goodbye(m) => goodbye(m),
        Message::Error(m) => error_message(m),
        Message::ComposerRegister(m) => composer_register(m),
        Message::OpenStream(m) => open_stream(m),
        Message::StreamOpened(m) => stream_opened(m),
        Message::ClientPose(m) => client_pose(m),
        Message::FramePlan(m) => frame_plan(m),
        Message::ReleaseTask(_) | Message::Challenge(_) | Message::Proof(_) => Ok(()),
        Message::CloseStream(m) => close_stream(m),
    }
}

fn composer_register(m: &ComposerRegister) -> Result<(), ValidationError> {
    token("composer name", &m.name, MAX_NAME_LEN)?;
    address(&m.results_address)
}

fn open_stream(m: &OpenStream) -> Result<(), ValidationError> {
    token("session name", &m.session_name, MAX_SESSION_NAME_LEN)?;
    count("offer_sdp", m.offer_sdp.len(), 1, MAX_SDP_LEN)?;
    views(m.views)?;
    image_size(m.width, m.height)?;
    // The views travel side by side in one video frame.
    image_size(m.views.saturating_mul(m.width), m.height)?;
    if !(m.target_fps.is_finite() && m.target_fps > 0.0 && m.target_fps <= MAX_TARGET_FPS) {
        return Err(ValidationError::OutOfRange {
            field: "target_fps",
            value: f64::from(m.target_fps),
            range: "(0, 240]",
        });
    }
    Ok(())
}

fn stream_opened(m: &StreamOpened) -> Result<(), ValidationError> {
    match &m.answer {
        Ok(sdp) => count("answer sdp", sdp.len(), 1, MAX_SDP_LEN),
        Err(reason) => text("answer error", reason),
    }
}

fn client_pose(m: &ClientPose) -> Result<(), ValidationError> {
    finite("client_time_ms", m.client_time_ms)?;
    count("views", m.views.len(), 1, MAX_VIEWS as usize)?;
    m.views.iter().try_for_each(camera)
}

fn frame_plan(m: &FramePlan) -> Result<(), ValidationError> {
    finite("client_time_ms", m.client_time_ms)?;
    image_size(m.width, m.height)?;
    views(m.views)?;
    count("parts", m.parts.len(), 0, MAX_PLAN_PARTS)?;
    if let Some(part) = m.parts.iter().find(|p| p.view >= m.views) {
        return Err(ValidationError::OutOfRange { field: "part view", value: f64::from(part.view), range: "< views" });
    }
    Ok(())
}

fn close_stream(m: &CloseStream) -> Result<(), ValidationError> {
    text("reason", &m.reason)
}

fn views(n: u32) -> Result<(), ValidationError> {
    if !(1..=MAX_VIEWS).contains(&n) {
        return Err(ValidationError::OutOfRange { field: "views", value: f64::from(n), range: "1..=64" });
    }
    Ok(())
}

fn finite(field: &'static str, value: f64) -> Result<(), ValidationError> {
    if !value.is_finite() {
        return Err(ValidationError::NonFinite { field });
    }
    Ok(())
}

fn register(m: &Register) -> Result<(), ValidationError> {
    worker_name(&m.name)?;
    if m.threads == 0 || m.threads > MAX_THREADS {
        return Err(ValidationError::OutOfRange { field: "threads", value: f64::from(m.threads), range: "1..=65536" });
    }
    count("kernels", m.kernels.len(), 1, MAX_KERNELS)?;
    for kind in &m.kernels {
        token("kernel kind", kind, MAX_KERNEL_NAME_LEN)?;
    }
    text("device", &m.device)?;
    non_negative("rays_per_second", m.rays_per_second)
}

fn registered(m: &Registered) -> Result<(), ValidationError> {
    let (lo, hi) = LOAD_REPORT_INTERVAL_MS;
    if !(lo..=hi).contains(&m.load_report_interval_ms) {
        return Err(ValidationError::OutOfRange {
            field: "load_report_interval_ms",
            value: f64::from(m.load_report_interval_ms),
            range: "10..=60000",
        });
    }
    Ok(())
}

fn load_report(m: &LoadReport) -> Result<(), ValidationError> {
    non_negative("recent_rays_per_second", m.recent_rays_per_second)
}

fn ray_batch(m: &RayBatch) -> Result<(), ValidationError> {
    asset_id(&m.asset_id)?;
    camera(&m.camera)?;
    pixel_set(&m.pixels, m.camera.width, m.camera.height)?;
    address(&m.composer)?;
    count("derived views", m.derived.len(), 0, MAX_VIEWS as usize)?;
    for view in &m.derived {
        camera(&view.camera)?;
        pixel_set(&view.pixels, view.camera.width, view.camera.height)?;
    }
    count("occluders", m.occluders.len(), 0, RayBatch::MAX_OCCLUDERS)?;
    for grid in &m.occluders {
        grid.validate()?;
    }
    let ReuseLimits { max_angle_deg, max_contrast, previous_frames, ahead, .. } = m.reuse;
    count("reuse previous_frames", previous_frames as usize, 0, ReuseLimits::MAX_PREVIOUS_FRAMES as usize)?;
    if ahead {
        // Kept to serve the session's next batches, and shown by no frame.
        count(
            "reuse previous_frames of a render ahead",
            previous_frames as usize,
            1,
            ReuseLimits::MAX_PREVIOUS_FRAMES as usize,
        )?;
        count("derived views of a render ahead", m.derived.len(), 0, 0)?;
    }
    if !(0.0..=90.0).contains(&max_angle_deg) {
        return Err(ValidationError::OutOfRange {
            field: "reuse max_angle_deg",
            value: f64::from(max_angle_deg),
            range: "[0, 90]",
        });
    }
    if max_contrast.is_nan() || max_contrast < 0.0 {
        return Err(ValidationError::OutOfRange {
            field: "reuse max_contrast",
            value: f64::from(max_contrast),
            range: ">= 0",
        });
    }
    Ok(())
}

fn batch_result(m: &BatchResult) -> Result<(), ValidationError> {
    image_size(m.width, m.height)?;
    // A result may hold no pixel: a compact one whose object covered none of its pixels.
    if !m.pixels.is_empty() {
        pixel_set(&m.pixels, m.width, m.height)?;
    }
    let n = m.pixels.len();
    same_len("color", m.color.len(), n)?;
    same_len("opacity", m.opacity.len(), n)?;
    same_len("depth", m.depth.len(), n)?;
    // Hot (20 bytes per pixel): branch-free folds that the compiler vectorises; find the
    // culprit only once something is wrong.
    if !m.color.as_flattened().iter().fold(true, |ok, v| ok & v.is_finite()) {
        return Err(ValidationError::NonFinite { field: "color" });
    }
    let opacity_ok = |a: &f32| (*a >= 0.0) & (*a <= 1.0);
    if !m.opacity.iter().fold(true, |ok, a| ok & opacity_ok(a)) {
        let bad = m.opacity.iter().copied().find(|a| !opacity_ok(a)).unwrap_or(f32::NAN);
        return Err(ValidationError::OutOfRange { field: "opacity", value: f64::from(bad), range: "[0, 1]" });
    }
    let depth_ok = |d: &f32| d.is_finite() & (*d >= 0.0);
    if !m.depth.iter().fold(true, |ok, d| ok & depth_ok(d)) {
        let bad = m.depth.iter().copied().find(|d| !depth_ok(d)).unwrap_or(f32::NAN);
        return Err(ValidationError::OutOfRange { field: "depth", value: f64::from(bad), range: "finite, >= 0" });
    }
    Ok(())
}

fn batch_done(m: &BatchDone) -> Result<(), ValidationError> {
    if m.pixels as usize > MAX_BATCH_PIXELS {
        return Err(ValidationError::Count { field: "pixels", len: m.pixels as usize, min: 0, max: MAX_BATCH_PIXELS });
    }
    Ok(())
}

fn batch_failed(m: &BatchFailed) -> Result<(), ValidationError> {
    text("message", &m.message)
}

fn goodbye(m: &Goodbye) -> Result<(), ValidationError> {
    text("reason", &m.reason)?;
    count("returned_batches", m.returned_batches.len(), 0, MAX_RETURNED_BATCHES)
}

fn error_message(m: &ErrorMessage) -> Result<(), ValidationError> {
    text("message", &m.message)
}

/// Image size within `1..=MAX_IMAGE_SIDE` per side.
pub fn image_size(width: u32, height: u32) -> Result<(), ValidationError> {
    if width == 0 || height == 0 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(ValidationError::ImageSize { width, height, max: MAX_IMAGE_SIDE });
    }
    Ok(())
}

/// Size in range and both matrices finite. Whether the view is rigid and the projection a
/// perspective one is the render crate's check (it has the tolerances).
pub fn camera(c: &ViewProjection) -> Result<(), ValidationError> {
    image_size(c.width, c.height)?;
    if !c.view.is_finite() {
        return Err(ValidationError::NonFinite { field: "camera view matrix" });
    }
    if !c.projection.is_finite() {
        return Err(ValidationError::NonFinite { field: "camera projection matrix" });
    }
    Ok(())
}

/// 1 to [`MAX_BATCH_PIXELS`] indices, each `< width * height`. Duplicates are allowed.
pub fn pixel_set(pixels: &[u32], width: u32, height: u32) -> Result<(), ValidationError> {
    count("pixels", pixels.len(), 1, MAX_BATCH_PIXELS)?;
    let limit = u64::from(width) * u64::from(height);
    // Max first: a single branch-free pass over the common (valid) case.
    let max = pixels.iter().copied().max().unwrap_or(0);
    if u64::from(max) >= limit {
        return Err(ValidationError::PixelOutOfImage { index: max, width, height });
    }
    Ok(())
}

/// An asset id: 1 to [`MAX_ASSET_ID_LEN`] bytes of `[A-Za-z0-9._-]`, not starting with a
/// dot and containing no `..`, so that `<dir>/<id>.<ext>` always names a file inside `dir`.
pub fn asset_id(id: &str) -> Result<(), ValidationError> {
    token("asset id", id, MAX_ASSET_ID_LEN)?;
    let bad = |reason| Err(ValidationError::BadString { field: "asset id", value: clip(id), reason });
    if id.starts_with('.') {
        return bad("it starts with a dot");
    }
    if id.contains("..") {
        return bad("it contains '..'");
    }
    Ok(())
}

/// A worker name: 1 to [`MAX_NAME_LEN`] bytes of `[A-Za-z0-9._-]`.
pub fn worker_name(name: &str) -> Result<(), ValidationError> {
    token("worker name", name, MAX_NAME_LEN)
}

/// `host:port` with a non-zero port; host of letters, digits, `.-_:` or a bracketed IPv6.
pub fn address(addr: &str) -> Result<(), ValidationError> {
    let bad = |reason| Err(ValidationError::BadString { field: "address", value: clip(addr), reason });
    if addr.is_empty() || addr.len() > MAX_ADDRESS_LEN {
        return bad("length must be 1..=255");
    }
    let Some((host, port)) = addr.rsplit_once(':') else {
        return bad("expected host:port");
    };
    if host.is_empty() || !host.bytes().all(|b| b.is_ascii_alphanumeric() || b"._-:[]".contains(&b)) {
        return bad("bad host");
    }
    match port.parse::<u16>() {
        Ok(p) if p > 0 => Ok(()),
        _ => bad("bad port"),
    }
}

fn token(field: &'static str, value: &str, max: usize) -> Result<(), ValidationError> {
    let bad = |reason| Err(ValidationError::BadString { field, value: clip(value), reason });
    if value.is_empty() || value.len() > max {
        return bad("empty or too long");
    }
    if !value.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'.' || b == b'_' || b == b'-') {
        return bad("only ASCII letters, digits, '.', '_' and '-' are allowed");
    }
    Ok(())
}

fn text(field: &'static str, value: &str) -> Result<(), ValidationError> {
    count(field, value.len(), 0, MAX_TEXT_LEN)
}

fn count(field: &'static str, len: usize, min: usize, max: usize) -> Result<(), ValidationError> {
    if len < min || len > max {
        return Err(ValidationError::Count { field, len, min, max });
    }
    Ok(())
}

fn same_len(field: &'static str, len: usize, expected: usize) -> Result<(), ValidationError> {
    if len != expected {
        return Err(ValidationError::LengthMismatch { field, len, expected });
    }
    Ok(())
}

fn non_negative(field: &'static str, value: f64) -> Result<(), ValidationError> {
    if !value.is_finite() {
        return Err(ValidationError::NonFinite { field });
    }
    if value < 0.0 {
        return Err(ValidationError::OutOfRange { field, value, range: ">= 0" });
    }
    Ok(())
}

/// At most 64 characters of untrusted text, for error messages.
fn clip(value: &str) -> String {
    value.chars().take(64).collect()
}
