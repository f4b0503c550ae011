//! `nephele secret`: writes a fresh secret (a farm secret, a viewer key) to a file, or the
//! farm's TLS certificate and key to a folder.

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
/// channel you trust (scp, a secret store). With `--farm-tls`, writes instead the farm's TLS
/// certificate and key into the folder `--out` (`farm.crt`, `farm.key`), for `--farm-tls DIR`
/// of the master, the composer and the workers (workers need only `farm.crt`).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The file to write (with `--farm-tls`, the folder).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Write a farm TLS certificate (self-signed, for the name `nephele-farm`) and its key
    /// into the folder `--out` instead of a secret.
    #[arg(long)]
    farm_tls: bool,
    /// Keep an existing file (checking that it holds a usable secret) instead of refusing to
    /// overwrite it: for start-up scripts that run on every start.
    #[arg(long)]
    if_missing: bool,
}

pub fn run(args: Args) -> Result<()> {
    if args.farm_tls {
        return farm_tls(&args);
    }
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

/// `--farm-tls`: the farm certificate and key in the folder `--out`.
fn farm_tls(args: &Args) -> Result<()> {
    use nephele_transport::{CERT_FILE, FarmTls};
    let dir = &args.out;
    if dir.join(CERT_FILE).exists() {
        if !args.if_missing {
            bail!(
                "{} exists; not overwriting the farm certificate (pass --if-missing to keep it)",
                dir.join(CERT_FILE).display()
            );
        }
        let kept = FarmTls::load(dir).with_context(|| format!("the farm TLS folder {}", dir.display()))?;
        anyhow::ensure!(kept.can_accept(), "{} holds a certificate without its key", dir.display());
        println!("farm certificate kept: {}", dir.display());
        return Ok(());
    }
    FarmTls::generate(dir)?;
    println!("farm certificate and key written: {}", dir.display());
    Ok(())
}
