//! One module per subcommand; each parses its own arguments and calls into the libraries.

pub mod bake;
pub mod composer;
pub mod dataset;
pub mod distill;
pub mod eval;
pub mod first_start;
pub mod invite;
pub mod loadgen;
pub mod master;
pub mod pathtrace;
pub mod probe;
pub mod render;
pub mod scenes;
pub mod secret;
pub mod simulate;
pub mod train;
pub mod train_gi;
pub mod up;
pub mod worker;

use anyhow::{Context, Result};
use glam::Vec3;

pub use nephele_geometry::camera::parse_size;

/// Parses `x,y,z` into a finite vector.
pub fn parse_vec3(text: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = text.split(',').collect();
    if parts.len() != 3 {
        return Err(format!("expected x,y,z, got '{text}'"));
    }
    let mut v = [0.0f32; 3];
    for (slot, part) in v.iter_mut().zip(parts) {
        *slot = part.trim().parse().map_err(|_| format!("'{part}' is not a number"))?;
        if !slot.is_finite() {
            return Err(format!("'{part}' is not finite"));
        }
    }
    Ok(Vec3::from(v))
}

/// Parses a background colour name or `r,g,b` in [0, 1].
pub fn parse_background(text: &str) -> Result<[f32; 3], String> {
    match text {
        "white" => Ok([1.0; 3]),
        "black" => Ok([0.0; 3]),
        _ => {
            let v = parse_vec3(text).map_err(|e| format!("{e} (or use 'white' / 'black')"))?;
            if v.min_element() < 0.0 || v.max_element() > 1.0 {
                return Err(format!("background '{text}' must lie in [0, 1]"));
            }
            Ok(v.to_array())
        }
    }
}

/// Opens the device `--device` asks for: the kernels' accelerator (`None` for the CPU) and
/// the label a worker reports (`cpu (AVX2+FMA)`, or the GPU adapter's name).
pub fn open_device(
    choice: nephele_gpu::DeviceChoice,
    simd: nephele_nn::SimdMode,
) -> Result<(Option<std::sync::Arc<dyn nephele_kernels::assets::Accelerator>>, String)> {
    use anyhow::Context;
    let accelerator = nephele_gpu::accelerator(choice).with_context(|| format!("--device {choice}"))?;
    let label = match &accelerator {
        Some(gpu) => gpu.label(),
        None => format!("cpu ({})", simd.describe()),
    };
    tracing::info!(device = %label, asked = %choice, "kernels' device");
    Ok((accelerator, label))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_vectors_and_backgrounds_parse_or_fail_clearly() {
        assert_eq!(parse_size("800x600"), Ok((800, 600)));
        assert!(parse_size("0x10").is_err());
        assert!(parse_size("800").is_err());
        assert!(parse_size("99999x10").is_err());
        assert_eq!(parse_vec3("1, 2,3"), Ok(Vec3::new(1.0, 2.0, 3.0)));
        assert!(parse_vec3("1,2").is_err());
        assert!(parse_vec3("1,nan,2").is_err());
        assert_eq!(parse_background("white"), Ok([1.0; 3]));
        assert!(parse_background("2,0,0").is_err());
        assert_eq!("0.9".parse::<AdmitUpTo>(), Ok(AdmitUpTo(Some(0.9))));
        assert_eq!("OFF".parse::<AdmitUpTo>(), Ok(AdmitUpTo(None)));
        for bad in ["0", "-1", "nan", "inf", "most"] {
            assert!(bad.parse::<AdmitUpTo>().is_err(), "{bad}");
        }
        // `up` hands its value on to the master as text.
        for admit in [AdmitUpTo(Some(0.75)), AdmitUpTo(None)] {
            assert_eq!(admit.to_string().parse::<AdmitUpTo>(), Ok(admit));
        }
    }
}

/// The farm's credential options, shared by `master`, `composer`, `worker` and `up`.
#[derive(Debug, Clone, clap::Args)]
pub struct FarmSecretArgs {
    /// File holding the farm secret that the master, the composer and every worker must
    /// share (at least 16 bytes; `nephele secret --out FILE` writes a fresh one).
    /// Without it the secret comes from the file named by $NEPHELE_FARM_SECRET_FILE, else
    /// from $NEPHELE_FARM_SECRET itself; with neither, the farm is open (any process that
    /// reaches the farm port may join). Never on the command line, where `ps` would show it.
    #[arg(long, value_name = "FILE")]
    pub farm_secret_file: Option<std::path::PathBuf>,
    /// TLS between the farm's processes, for farms that cross machines: a folder holding the
    /// farm certificate `farm.crt` and, for the master and the composer (which listen), its
    /// key `farm.key` (`nephele up --farm-tls DIR` makes both when the folder has none;
    /// workers need only `farm.crt`). Every farm connection is then TLS and trusts that
    /// certificate alone; the farm secret is still proved inside. Without it (or
    /// $NEPHELE_FARM_TLS_DIR) the farm's links are plain TCP.
    #[arg(long, value_name = "DIR")]
    pub farm_tls: Option<std::path::PathBuf>,
}

/// The environment variable naming the farm TLS folder (`--farm-tls`).
pub const FARM_TLS_ENV: &str = "NEPHELE_FARM_TLS_DIR";

/// A file named by a flag, else by an environment variable (the secrets' files: farm secret,
/// viewer key, operator token).
fn flag_or_env_file(flag: &Option<std::path::PathBuf>, env: &str) -> Option<std::path::PathBuf> {
    flag.clone().or_else(|| std::env::var_os(env).map(Into::into))
}

impl FarmSecretArgs {
    /// The farm TLS folder, from the flag, then the environment.
    pub fn tls_dir(&self) -> Option<std::path::PathBuf> {
        flag_or_env_file(&self.farm_tls, FARM_TLS_ENV)
    }

    /// The farm TLS settings (`None`: plain TCP); `listens`: this process serves a farm port
    /// and needs the key.
    pub fn resolve_tls(&self, listens: bool) -> Result<Option<nephele_transport::FarmTls>> {
        let Some(dir) = self.tls_dir() else { return Ok(None) };
        let tls = nephele_transport::FarmTls::load(&dir)
            .with_context(|| format!("the farm TLS folder {} (--farm-tls)", dir.display()))?;
        if listens && !tls.can_accept() {
            anyhow::bail!(
                "the farm TLS folder {} has no {}: the master and the composer listen and need the key",
                dir.display(),
                nephele_transport::KEY_FILE
            );
        }
        Ok(Some(tls))
    }

    /// The secret, from the flag, then the environment; `None`: an open farm.
    pub fn resolve(&self) -> Result<Option<nephele_proto::auth::FarmSecret>> {
        use nephele_proto::auth::{FarmSecret, SECRET_ENV, SECRET_FILE_ENV};
        let file = flag_or_env_file(&self.farm_secret_file, SECRET_FILE_ENV);
        if let Some(path) = file {
            return Ok(Some(FarmSecret::read_file(&path)?));
        }
        match std::env::var(SECRET_ENV) {
            Ok(text) => Ok(Some(FarmSecret::from_text(&text, SECRET_ENV)?)),
            Err(std::env::VarError::NotPresent) => Ok(None),
            Err(e) => anyhow::bail!("${SECRET_ENV}: {e}"),
        }
    }
}

/// `--admit-up-to` of `master` and `up`: a fraction of the farm's measured throughput, or
/// `off` (only Algorithm 1's starvation refusal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdmitUpTo(pub Option<f64>);

impl std::str::FromStr for AdmitUpTo {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if text.eq_ignore_ascii_case("off") {
            return Ok(AdmitUpTo(None));
        }
        match text.parse::<f64>() {
            Ok(f) if f.is_finite() && f > 0.0 => Ok(AdmitUpTo(Some(f))),
            _ => Err(format!("'{text}': a positive fraction such as 0.9, or off")),
        }
    }
}

impl std::fmt::Display for AdmitUpTo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            Some(fraction) => write!(f, "{fraction}"),
            None => f.write_str("off"),
        }
    }
}

/// HTTPS for the master's page and API, shared by `master` and `up`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct TlsArgs {
    /// Serve the page and the API over HTTPS with this certificate chain (PEM, leaf first),
    /// with `--tls-key`.
    #[arg(long, value_name = "PEM", requires = "tls_key", conflicts_with = "tls_self_signed")]
    pub tls_cert: Option<std::path::PathBuf>,
    /// The private key of `--tls-cert` (PEM).
    #[arg(long, value_name = "PEM", requires = "tls_cert")]
    pub tls_key: Option<std::path::PathBuf>,
    /// Serve HTTPS with a self-signed certificate made for this machine (localhost, the
    /// loopback addresses, the host name, its LAN address and every `--tls-name`), cached in
    /// `--tls-dir` and valid for a year. Browsers warn once: compare the SHA-256 fingerprint
    /// printed at start with theirs. Browsers show WebXR only on secure pages, so this is what
    /// lets a headset on the LAN enter VR. `nephele loadgen --tls-ca DIR/cert.pem` trusts it.
    #[arg(long)]
    pub tls_self_signed: bool,
    /// Another name or address the self-signed certificate covers (repeatable).
    #[arg(long = "tls-name", value_name = "NAME", requires = "tls_self_signed")]
    pub tls_names: Vec<String>,
    /// Folder of the self-signed certificate [default: the cache folder's `tls/`].
    #[arg(long, value_name = "DIR", requires = "tls_self_signed")]
    pub tls_dir: Option<std::path::PathBuf>,
}

impl TlsArgs {
    /// Where the self-signed certificate lives.
    pub fn self_signed_dir(&self) -> std::path::PathBuf {
        self.tls_dir.clone().unwrap_or_else(|| first_start::cache_root().join("tls"))
    }

    /// The server configuration asked for, if any (making the self-signed certificate when
    /// needed), with a line for the user about it.
    pub fn resolve(&self) -> Result<Option<nephele_master::tls::ServerTls>> {
        use nephele_master::tls::{ServerTls, default_names};
        if let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) {
            return Ok(Some(ServerTls::from_pem_files(cert, key)?));
        }
        if !self.tls_self_signed {
            return Ok(None);
        }
        let names = default_names(&self.tls_names);
        let dir = self.self_signed_dir();
        let (tls, made) = ServerTls::self_signed(&dir, &names)?;
        tracing::info!(
            certificate = %tls.cert_path.display(),
            names = %names.join(", "),
            "{} self-signed certificate",
            if made { "made a" } else { "using the cached" }
        );
        Ok(Some(tls))
    }

    /// The same flags, for a child `nephele master`.
    pub fn to_args(&self) -> Vec<std::ffi::OsString> {
        let mut args: Vec<std::ffi::OsString> = Vec::new();
        if let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) {
            args.extend(["--tls-cert".into(), cert.into(), "--tls-key".into(), key.into()]);
        }
        if self.tls_self_signed {
            args.extend(["--tls-self-signed".into(), "--tls-dir".into(), self.self_signed_dir().into()]);
            for name in &self.tls_names {
                args.extend(["--tls-name".into(), name.into()]);
            }
        }
        args
    }
}

/// The viewer key (`master`, `up`, `invite`): invitations are signed with it, and a master
/// that has one opens sessions only for valid invitations.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ViewerKeyArgs {
    /// File holding the viewer key (at least 16 bytes; `nephele secret --out FILE` writes
    /// one). A master given one opens sessions only for invitation links signed with it
    /// (`nephele invite`); 401 without an invitation, 403 for a wrong, altered or expired
    /// one. Default: the file named by $NEPHELE_VIEWER_KEY_FILE; with neither, anyone who
    /// reaches the master may open sessions.
    #[arg(long, value_name = "FILE")]
    pub viewer_key_file: Option<std::path::PathBuf>,
}

/// The environment variable naming the viewer key's file.
pub const VIEWER_KEY_FILE_ENV: &str = "NEPHELE_VIEWER_KEY_FILE";

/// The operators' token (`master`, `up`, `composer`, `worker`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct OperatorTokenArgs {
    /// File holding the operators' bearer token (at least 16 bytes; `nephele secret --out
    /// FILE` writes one). With one, the operators' endpoints (`GET /metrics` everywhere; the
    /// master's `GET /v1/farm`, the master's and the composer's `GET /v1/sessions`) answer 401
    /// unless the request carries `Authorization: Bearer TOKEN` (Prometheus: `authorization:
    /// {credentials_file: FILE}`); `/livez`, `/readyz`, the page, signalling and the viewers'
    /// API need none. Default: the file named by $NEPHELE_OPERATOR_TOKEN_FILE; with neither,
    /// those endpoints are open to whoever reaches them.
    #[arg(long, value_name = "FILE")]
    pub operator_token_file: Option<std::path::PathBuf>,
}

/// The environment variable naming the operators' token file.
pub const OPERATOR_TOKEN_FILE_ENV: &str = "NEPHELE_OPERATOR_TOKEN_FILE";

impl OperatorTokenArgs {
    /// The token's file, from the flag or the environment.
    pub fn file(&self) -> Option<std::path::PathBuf> {
        flag_or_env_file(&self.operator_token_file, OPERATOR_TOKEN_FILE_ENV)
    }

    /// The token as read (for `up`'s own requests) and as the master keeps it.
    pub fn resolve(&self) -> Result<Option<(String, nephele_telemetry::OperatorToken)>> {
        let Some(path) = self.file() else { return Ok(None) };
        // The same rules as a farm secret's file (size, trimming, at least 16 bytes).
        let secret = nephele_proto::auth::FarmSecret::read_file(&path)?;
        let token = secret.expose().to_string();
        let kept = nephele_telemetry::OperatorToken::new(&token)
            .ok_or_else(|| anyhow::anyhow!("the operator token in {} is too short", path.display()))?;
        Ok(Some((token, kept)))
    }
}

impl ViewerKeyArgs {
    /// The key's file, from the flag or the environment.
    pub fn file(&self) -> Option<std::path::PathBuf> {
        flag_or_env_file(&self.viewer_key_file, VIEWER_KEY_FILE_ENV)
    }

    pub fn resolve(&self) -> Result<Option<nephele_master::access::ViewerKey>> {
        let Some(path) = self.file() else { return Ok(None) };
        // The same rules as a farm secret's file (size, trimming, at least 16 bytes).
        let secret = nephele_proto::auth::FarmSecret::read_file(&path)?;
        let key = nephele_master::access::ViewerKey::new(secret.expose().as_bytes())
            .ok_or_else(|| anyhow::anyhow!("the viewer key in {} is too short", path.display()))?;
        Ok(Some(key))
    }
}
