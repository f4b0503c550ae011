//! `nephele invite`: a signed, expiring invitation link to a scene.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, bail};

/// Prints an invitation link for a master that requires them (`nephele master
/// --viewer-key-file FILE`): opening it starts a session on `--scene` until it expires. The
/// link carries the invitation as `?invite=...`; the page sends it with its session request,
/// and `nephele loadgen --url LINK` does too. Anyone holding the link can use it until then,
/// so send it like a password; the master keeps no list, so an invitation cannot be revoked
/// early except by changing the viewer key (which ends them all).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The scene the invitation opens, or `*` for every scene.
    #[arg(long)]
    scene: String,
    /// Hours until it expires.
    #[arg(long, default_value_t = 24.0)]
    hours: f64,
    /// The master's page, as the invited will open it.
    #[arg(long, default_value = "http://127.0.0.1:8080/")]
    url: String,
    #[command(flatten)]
    key: crate::commands::ViewerKeyArgs,
}

pub fn run(args: Args) -> Result<()> {
    let Some(key) = args.key.resolve()? else {
        bail!("no viewer key: pass --viewer-key-file FILE (the master's) or set ${}", super::VIEWER_KEY_FILE_ENV);
    };
    if !(args.hours.is_finite() && args.hours > 0.0 && args.hours <= 24.0 * 366.0) {
        bail!("--hours must be in (0, 8784], got {}", args.hours);
    }
    if args.scene.is_empty() || args.scene.contains(['&', '#', '?', '/', ' ']) {
        bail!("--scene {:?} is not a scene name", args.scene);
    }
    let now = SystemTime::now().duration_since(UNIX_EPOCH).context("the clock is before 1970")?;
    let expires = (now + Duration::from_secs_f64(args.hours * 3600.0)).as_secs();
    let token = key.invite(&args.scene, expires);
    let base = args.url.split(['?', '#']).next().unwrap_or("");
    let scene =
        if args.scene == nephele_master::access::ANY_SCENE { String::new() } else { format!("scene={}&", args.scene) };
    println!("{base}?{scene}invite={token}");
    eprintln!("valid for {} h (until Unix time {expires}) for scene {:?}", args.hours, args.scene);
    Ok(())
}
