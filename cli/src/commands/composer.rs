//! `nephele composer`: runs a composer process (depth fusion, H.264, WebRTC).

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::{Context, Result};
use nephele_composer::service::{Composer, ComposerConfig, FrameSource};
use nephele_composer::webrtc::{IceServer, MdnsMode, RtcConfig};
use nephele_shutdown::Shutdown;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum Source {
    /// Frame plans and batch results from render workers on the results listener.
    Workers,
    /// A synthetic two-object scene rendered in-process from each viewer's pose (no farm needed).
    TestPattern,
}

/// Runs a composer: it answers WebRTC offers over HTTP (`POST /v1/sessions` with
/// `{"sdp": OFFER}`), gathers worker results on a TCP listener, fuses them by depth, encodes
/// H.264 (constrained baseline, IPPP) and streams each viewer's frames; poses come back over
/// the viewer's data channel. Stop it with Ctrl-C.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// HTTP signalling endpoint (`POST /v1/sessions`, `GET /v1/sessions`, `DELETE /v1/sessions/ID`).
    #[arg(long, default_value = "127.0.0.1:8090")]
    http: SocketAddr,
    /// TCP listener for frame plans and worker batch results.
    #[arg(long, default_value = "127.0.0.1:8091")]
    results: SocketAddr,
    /// The results listener's address as workers must dial it, `HOST:PORT`, told to the
    /// master (default: the bound `--results` address; set it when binding 0.0.0.0, e.g.
    /// `composer:8091` on a container network).
    #[arg(long, value_name = "HOST:PORT", value_parser = parse_host_port)]
    advertise_results: Option<String>,
    /// Where frames come from.
    #[arg(long, value_enum, default_value = "workers")]
    source: Source,
    /// STUN or TURN server, repeatable: `stun:HOST:PORT` or `turn:USER:PASSWORD@HOST:PORT`.
    #[arg(long = "ice-server", value_name = "URL")]
    ice_servers: Vec<String>,
    /// Public address to announce in place of the interfaces' own (1:1 NAT, containers); repeatable.
    #[arg(long = "public-ip", value_name = "IP")]
    public_ips: Vec<String>,
    /// UDP port range for ICE, `MIN-MAX` (default: any ephemeral port).
    #[arg(long, value_name = "MIN-MAX", value_parser = parse_port_range)]
    udp_ports: Option<(u16, u16)>,
    /// Do not offer loopback (127.0.0.1) host candidates.
    #[arg(long)]
    no_loopback: bool,
    /// Send each video frame as one burst. By default its packets leave no faster than 2.5
    /// times the encoder's target bitrate after a burst of 40 ms at that rate (WebRTC's
    /// pacer), so that a keyframe large for its rate does not overflow a short router queue
    /// on the way; ordinary frames fit the burst and leave at once.
    #[arg(long)]
    no_pacing: bool,
    /// Resolve browsers' mDNS `.local` host candidates by multicast DNS (off: the browser is
    /// found as a peer-reflexive candidate instead, which works across hosts too).
    #[arg(long)]
    mdns: bool,
    /// Stream frame rate.
    #[arg(long, default_value_t = 30.0)]
    fps: f32,
    /// Encoder bitrate in kbit/s (default: about 0.1 bit per pixel per frame).
    #[arg(long, value_name = "KBPS")]
    bitrate: Option<u32>,
    /// View size until a viewer's first pose says otherwise.
    #[arg(long, default_value = "640x480", value_parser = super::parse_size)]
    view: (u32, u32),
    /// Frame deadline for the test pattern, ms.
    #[arg(long, default_value_t = 40)]
    deadline_ms: u64,
    /// Most concurrent viewers; more get HTTP 503 with Retry-After.
    #[arg(long, default_value_t = 64)]
    max_sessions: usize,
    /// The master's farm listener (`HOST:PORT`): register there, take viewer sessions, frame
    /// plans and worker results (proto v2) from the farm and send poses back. The results
    /// listener then speaks the farm protocol instead of the interim framing.
    #[arg(long, value_name = "HOST:PORT")]
    master: Option<String>,
    /// The composer's name in the master's `GET /v1/farm`.
    #[arg(long, default_value = "composer")]
    name: String,
    #[command(flatten)]
    farm_secret: crate::commands::FarmSecretArgs,
    #[command(flatten)]
    operator_token: crate::commands::OperatorTokenArgs,
}

fn parse_host_port(text: &str) -> Result<String, String> {
    nephele_proto::validate::address(text).map_err(|e| e.to_string())?;
    Ok(text.to_string())
}

fn parse_port_range(text: &str) -> Result<(u16, u16), String> {
    let (lo, hi) = text.split_once('-').ok_or_else(|| format!("expected MIN-MAX, got '{text}'"))?;
    let lo: u16 = lo.trim().parse().map_err(|_| format!("bad port '{lo}'"))?;
    let hi: u16 = hi.trim().parse().map_err(|_| format!("bad port '{hi}'"))?;
    if lo == 0 || lo > hi {
        return Err(format!("empty port range '{text}'"));
    }
    Ok((lo, hi))
}

pub fn run(args: Args) -> Result<()> {
    let ice_servers = args.ice_servers.iter().map(|s| IceServer::parse(s)).collect::<Result<Vec<_>, _>>()?;
    let config = ComposerConfig {
        http_addr: args.http,
        results_addr: args.results,
        advertise_results: args.advertise_results,
        rtc: RtcConfig {
            ice_servers,
            include_loopback: !args.no_loopback,
            // An empty `--public-ip ''` (a compose file's unset variable) announces nothing.
            nat_1to1_ips: args.public_ips.into_iter().filter(|ip| !ip.trim().is_empty()).collect(),
            udp_ports: args.udp_ports,
            mdns: if args.mdns { MdnsMode::Query } else { MdnsMode::Off },
            pacing: !args.no_pacing,
            ..RtcConfig::default()
        },
        source: match args.source {
            Source::Workers => FrameSource::Workers,
            Source::TestPattern => FrameSource::TestPattern,
        },
        fps: args.fps,
        bitrate_bps: args.bitrate.map(|k| k.saturating_mul(1000)),
        default_view: args.view,
        frame_budget: Duration::from_millis(args.deadline_ms),
        max_sessions: args.max_sessions,
        master: args.master,
        name: args.name,
        farm_secret: args.farm_secret.resolve()?,
        farm_tls: args.farm_secret.resolve_tls(true)?,
        operator_token: args.operator_token.resolve()?.map(|(_, kept)| kept),
    };
    let runtime =
        tokio::runtime::Builder::new_multi_thread().enable_all().build().context("starting the async runtime")?;
    let shutdown = Shutdown::on_signals().context("installing the Ctrl-C and SIGTERM handlers")?;
    runtime.block_on(async move {
        let composer = Composer::start(config).await?;
        println!(
            "composer: signalling on http://{}/v1/sessions, worker results on {}",
            composer.http_addr(),
            composer.results_addr()
        );
        shutdown.wait().await;
        println!("composer: stopping");
        composer.shutdown().await;
        anyhow::Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn port_ranges_parse() {
        assert_eq!(parse_port_range("50000-50100"), Ok((50000, 50100)));
        assert!(parse_port_range("5-1").is_err());
        assert!(parse_port_range("0-10").is_err());
        assert!(parse_port_range("x").is_err());
    }
}
