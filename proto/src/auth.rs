//! The farm credential: a shared secret that every farm process proves it holds, in both
//! directions, right after the [`Hello`](crate::Hello)s.
//!
//! Each side sends a [`Challenge`] with 32 fresh random bytes, then a [`Proof`]: the
//! HMAC-SHA256 under the secret of a domain label, the prover's and the verifier's roles,
//! the verifier's nonce and the prover's own nonce. The verifier's fresh nonce stops replay
//! of an old proof; the roles stop a proof from being reflected back to the process that
//! asked for it (a master's proof never passes for a worker's). The secret never crosses
//! the wire. A side without a secret (an *open* farm) sends an empty proof and accepts any;
//! a side with one refuses a peer whose proof is empty or wrong
//! ([`ProtoError::Unauthenticated`]).
//!
//! What this does not give: confidentiality or integrity of the frames after the handshake
//! (an attacker on the path could inject into an authenticated TCP stream); clusters whose
//! farm traffic crosses untrusted links need a tunnel or TLS around the farm sockets.

use std::fmt;
use std::path::Path;

use hmac::{Hmac, Mac};
use serde::{Deserialize, Serialize};
use sha2::Sha256;
use thiserror::Error;

use crate::error::ProtoError;
use crate::messages::Role;

/// Bytes of a nonce and of a proof.
pub const NONCE_LEN: usize = 32;
/// Shortest secret accepted, bytes (after trimming white space): 128 bits of a random
/// hex string's 256.
pub const MIN_SECRET_LEN: usize = 16;
/// Longest secret file read, bytes.
const MAX_SECRET_FILE: u64 = 4096;
/// Separates these MACs from any other use of the same secret.
const DOMAIN: &[u8] = b"nephele farm credential v1";

/// The environment variable holding the secret itself.
pub const SECRET_ENV: &str = "NEPHELE_FARM_SECRET";
/// The environment variable naming a file that holds the secret.
pub const SECRET_FILE_ENV: &str = "NEPHELE_FARM_SECRET_FILE";

/// A side's challenge: fresh random bytes the peer must bind its proof to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Challenge {
    pub nonce: [u8; NONCE_LEN],
}

/// A side's answer to the peer's [`Challenge`]; `None` from a side without a secret.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Proof {
    pub mac: Option<[u8; NONCE_LEN]>,
}

#[derive(Debug, Error)]
pub enum SecretError {
    #[error("reading the farm secret file {path}: {source}")]
    Read { path: String, source: std::io::Error },
    #[error("the farm secret file {path} is larger than {MAX_SECRET_FILE} bytes")]
    TooLarge { path: String },
    #[error("the farm secret from {from} has {len} bytes; at least {MIN_SECRET_LEN} are needed")]
    TooShort { from: String, len: usize },
    #[error("no random numbers from the operating system: {0}")]
    Random(String),
}

/// The farm's shared secret. Its `Debug` does not show it.
#[derive(Clone, PartialEq, Eq)]
pub struct FarmSecret {
    key: Vec<u8>,
}

impl fmt::Debug for FarmSecret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "FarmSecret({} bytes)", self.key.len())
    }
}

impl FarmSecret {
    /// A secret from its text (surrounding white space, such as a file's last newline, is
    /// not part of it). `from` names the source for the error.
    pub fn from_text(text: &str, from: &str) -> Result<FarmSecret, SecretError> {
        let key = text.trim().as_bytes().to_vec();
        if key.len() < MIN_SECRET_LEN {
            return Err(SecretError::TooShort { from: from.to_owned(), len: key.len() });
        }
        Ok(FarmSecret { key })
    }

    /// Reads a secret file (at most 4 KiB).
    pub fn read_file(path: &Path) -> Result<FarmSecret, SecretError> {
        let shown = path.display().to_string();
        let read = |source| SecretError::Read { path: shown.clone(), source };
        let size = std::fs::metadata(path).map_err(read)?.len();
        if size > MAX_SECRET_FILE {
            return Err(SecretError::TooLarge { path: shown });
        }
        let text = std::fs::read(path).map_err(read)?;
        FarmSecret::from_text(&String::from_utf8_lossy(&text), &shown)
    }

    /// A fresh secret: 32 random bytes as 64 hex digits (printable, for files and the
    /// environment).
    pub fn generate() -> Result<FarmSecret, SecretError> {
        let mut bytes = [0u8; 32];
        getrandom::fill(&mut bytes).map_err(|e| SecretError::Random(e.to_string()))?;
        Ok(FarmSecret { key: hex(&bytes).into_bytes() })
    }

    /// The secret's text, to hand to a child process or write to a file.
    pub fn expose(&self) -> &str {
        // Built from text or from hex digits only.
        std::str::from_utf8(&self.key).unwrap_or_default()
    }

    fn mac(&self, prover: Role, verifier: Role, verifier_nonce: &[u8], prover_nonce: &[u8]) -> Hmac<Sha256> {
        // HMAC takes keys of any length.
        let mut mac = <Hmac<Sha256> as Mac>::new_from_slice(&self.key).unwrap_or_else(|_| unreachable!());
        mac.update(DOMAIN);
        mac.update(&[prover.to_byte(), verifier.to_byte()]);
        mac.update(verifier_nonce);
        mac.update(prover_nonce);
        mac
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Whether `us` sends its proof before reading the peer's: the lower role proves first (a
/// worker or tool before the composer before the master), so that the side that accepted
/// the connection answers a wrong proof with an error instead of a proof of its own. Equal
/// roles both send at once (never waiting on each other).
pub fn proves_first(us: Role, peer: Role) -> bool {
    let rank = |r: Role| match r {
        Role::Tool => 0,
        Role::Worker => 1,
        Role::Composer => 2,
        Role::Master => 3,
    };
    rank(us) <= rank(peer)
}

/// A fresh nonce.
pub fn nonce() -> Result<[u8; NONCE_LEN], ProtoError> {
    let mut nonce = [0u8; NONCE_LEN];
    getrandom::fill(&mut nonce).map_err(|e| ProtoError::Io(std::io::Error::other(format!("no random nonce: {e}"))))?;
    Ok(nonce)
}

/// Our proof for the peer: we are `prover`, answering `verifier`'s `their_nonce`, having
/// sent `our_nonce`.
pub fn prove(
    secret: Option<&FarmSecret>,
    prover: Role,
    verifier: Role,
    their_nonce: &[u8; NONCE_LEN],
    our_nonce: &[u8; NONCE_LEN],
) -> Proof {
    Proof { mac: secret.map(|s| s.mac(prover, verifier, their_nonce, our_nonce).finalize().into_bytes().into()) }
}

/// Checks the peer's proof (in constant time). Without a secret of ours every proof passes.
pub fn verify(
    secret: Option<&FarmSecret>,
    peer: Role,
    us: Role,
    our_nonce: &[u8; NONCE_LEN],
    their_nonce: &[u8; NONCE_LEN],
    proof: &Proof,
) -> Result<(), ProtoError> {
    let Some(secret) = secret else { return Ok(()) };
    let Some(mac) = proof.mac else {
        return Err(ProtoError::Unauthenticated(format!("the {peer} has no farm secret; this farm requires one")));
    };
    secret
        .mac(peer, us, our_nonce, their_nonce)
        .verify_slice(&mac)
        .map_err(|_| ProtoError::Unauthenticated(format!("the {peer}'s proof of the farm secret is wrong")))
}
