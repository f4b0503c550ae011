//! What a browser test reads from and does to the Nephele client page (`client/nephele.js`,
//! `window.nephele`), whatever service sits behind it: the in-process [`crate::farm`] today,
//! the whole service (`nephele up`) in the full end-to-end test.

use std::time::Duration;

use serde_json::Value;

use crate::browser::{Browser, LogEntry, Result};

/// The client's connection state (`window.nephele.state`): `idle`, `connecting`,
/// `streaming`, `farm busy, retrying in N s`, `reconnecting in ...`, `error: ...`.
pub fn state(browser: &Browser) -> Result<String> {
    Ok(browser
        .execute("return window.nephele ? window.nephele.state : null;", Vec::new())?
        .as_str()
        .unwrap_or("")
        .to_string())
}

/// Waits until the data channel is open (`state == "streaming"`).
pub fn wait_streaming(browser: &Browser, limit: Duration) -> Result<()> {
    browser.wait_until("window.nephele && window.nephele.state === 'streaming'", limit)?;
    Ok(())
}

/// The session id the master gave this tab.
pub fn session_id(browser: &Browser) -> Result<Option<String>> {
    Ok(browser
        .execute("return window.nephele ? window.nephele.sessionId : null;", Vec::new())?
        .as_str()
        .map(str::to_string))
}

/// Sets the orbit camera (radians, metres), as a user's drag would.
pub fn set_orbit(browser: &Browser, azimuth: f64, elevation: f64, radius: f64) -> Result<()> {
    browser.execute(
        "window.nephele.setOrbit(arguments[0], arguments[1], arguments[2]);",
        vec![azimuth.into(), elevation.into(), radius.into()],
    )?;
    Ok(())
}

/// The receiver's video statistics from `RTCPeerConnection.getStats()`: the `inbound-rtp`
/// video entry (`framesDecoded`, `framesReceived`, `frameWidth`, `bytesReceived`, ...), or
/// `Null` before the track exists.
pub fn inbound_video_stats(browser: &Browser) -> Result<Value> {
    browser.eval_promise(
        "(async () => {
            const pc = window.nephele && window.nephele.pc;
            if (!pc) return null;
            let found = null;
            (await pc.getStats()).forEach((s) => { if (s.type === 'inbound-rtp' && s.kind === 'video') found = s; });
            return found && JSON.parse(JSON.stringify(found));
        })()",
    )
}

pub fn frames_decoded(browser: &Browser) -> Result<u64> {
    Ok(inbound_video_stats(browser)?["framesDecoded"].as_u64().unwrap_or(0))
}

/// The picture the `<video>` element shows now, read back through a canvas: mean of R, G and
/// B over `[x0, x1) x [y0, y1)` given as fractions of the frame, or `None` before the first frame.
pub fn mean_grey(browser: &Browser, region: [f64; 4]) -> Result<Option<f64>> {
    Ok(mean_rgb(browser, region)?.map(|[r, g, b]| (r + g + b) / 3.0))
}

/// Like [`mean_grey`], per channel: the means of R, G and B (0-255).
pub fn mean_rgb(browser: &Browser, region: [f64; 4]) -> Result<Option<[f64; 3]>> {
    let value = browser.execute(
        "const v = document.getElementById('video');
         if (!v || v.readyState < 2 || !v.videoWidth) return null;
         const [fx0, fy0, fx1, fy1] = arguments[0];
         const c = document.createElement('canvas');
         c.width = v.videoWidth; c.height = v.videoHeight;
         const g = c.getContext('2d', { willReadFrequently: true });
         g.drawImage(v, 0, 0);
         const x0 = Math.floor(fx0 * c.width), y0 = Math.floor(fy0 * c.height);
         const w = Math.max(1, Math.floor(fx1 * c.width) - x0), h = Math.max(1, Math.floor(fy1 * c.height) - y0);
         const d = g.getImageData(x0, y0, w, h).data;
         const s = [0, 0, 0];
         for (let i = 0; i < d.length; i += 4) { s[0] += d[i]; s[1] += d[i + 1]; s[2] += d[i + 2]; }
         return s.map((v) => v / (d.length / 4));",
        vec![serde_json::json!(region)],
    )?;
    let Some(means) = value.as_array() else { return Ok(None) };
    let channel = |i: usize| means.get(i).and_then(Value::as_f64).unwrap_or(f64::NAN);
    Ok(Some([channel(0), channel(1), channel(2)]))
}

/// Console errors, except the browser's own request for a favicon (the client has none).
pub fn page_errors(log: &[LogEntry]) -> Vec<&LogEntry> {
    log.iter().filter(|e| e.level == "SEVERE" && !e.message.contains("favicon.ico")).collect()
}

/// Payload types of an SDP's video section mapped to H.264 with `packetization-mode=1`.
pub fn h264_mode1_payload_types(sdp: &str) -> Vec<u32> {
    let mut in_video = false;
    let mut h264 = Vec::new();
    let mut mode1 = Vec::new();
    for line in sdp.lines().map(str::trim_end) {
        if let Some(m) = line.strip_prefix("m=") {
            in_video = m.starts_with("video ");
        } else if !in_video {
            continue;
        } else if let Some(rest) = line.strip_prefix("a=rtpmap:") {
            if let Some((pt, codec)) = rest.split_once(' ')
                && codec.eq_ignore_ascii_case("H264/90000")
                && let Ok(pt) = pt.parse::<u32>()
            {
                h264.push(pt);
            }
        } else if let Some(rest) = line.strip_prefix("a=fmtp:")
            && let Some((pt, params)) = rest.split_once(' ')
            && params.split(';').any(|p| p.trim() == "packetization-mode=1")
            && let Ok(pt) = pt.parse::<u32>()
        {
            mode1.push(pt);
        }
    }
    h264.retain(|pt| mode1.contains(pt));
    h264
}

/// A scripted WebXR device (`navigator.xr`, `XRWebGLLayer`), to inject with
/// [`Browser::add_script_on_new_document`] before opening the page: see the script's header.
pub const MOCK_XR: &str = include_str!("mock_xr.js");

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_h264_mode_1_in_the_video_section_only() {
        let sdp = "v=0\r\nm=audio 9 x 111\r\na=rtpmap:111 H264/90000\r\na=fmtp:111 packetization-mode=1\r\n\
                   m=video 9 UDP/TLS/RTP/SAVPF 96 102 104\r\na=rtpmap:96 VP8/90000\r\na=rtpmap:102 H264/90000\r\n\
                   a=fmtp:102 level-asymmetry-allowed=1;packetization-mode=1;profile-level-id=42e01f\r\n\
                   a=rtpmap:104 H264/90000\r\na=fmtp:104 packetization-mode=0\r\nm=application 9 x\r\n";
        assert_eq!(h264_mode1_payload_types(sdp), vec![102]);
        assert!(h264_mode1_payload_types("v=0\r\nm=video 9 x 96\r\na=rtpmap:96 VP8/90000\r\n").is_empty());
    }
}
