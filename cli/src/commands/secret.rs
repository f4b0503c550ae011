//! `nephele secret`: writes a fresh secret (a farm secret, a viewer key) to a file.

use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use nephele_proto::auth::FarmSecret;

/// Writes a fresh secret (32 random bytes as 64 hex digits) to `--out`, readable by its owner
/// only. As a farm secret, give the same file to the master, the composer and every worker
/// (`--farm-secret-file FILE` or `NEPHELE_FARM_SECRET_FILE=FILE`): each proves it holds it
/// when it joins the farm and refuses peers that do not. As a viewer key, give it to the
/// master (`--viewer-key-file`) and to `nephele invite`. Copy it to other machines over a
/// channel you trust (scp, a secret store).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The file to write.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Keep an existing file (checking that it holds a usable secret) instead of refusing to
    /// overwrite it: for start-up scripts that run on every start.
    #[arg(long)]
    if_missing: bool,
}

pub fn run(args: Args) -> Result<()> {
    if args.out.exists() {
        if !args.if_missing {
            bail!("{} exists; not overwriting a secret (remove it first, or pass --if-missing)", args.out.display());
        }
        FarmSecret::read_file(&args.out)?;
        println!("secret kept: {}", args.out.display());
        return Ok(());
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let secret = FarmSecret::generate()?;
    // create_new: never follows a link planted at the path, never truncates a file a
    // concurrent start just wrote; mode 0600 from the first byte.
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    writeln!(file, "{}", secret.expose()).with_context(|| format!("writing {}", args.out.display()))?;
    file.sync_all().with_context(|| format!("writing {}", args.out.display()))?;
    println!("secret written: {}", args.out.display());
    Ok(())
}
