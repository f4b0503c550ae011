//! Who may open viewer sessions: signed, expiring invitations per scene, and a per-address
//! rate limit on session creation.
//!
//! * An **invitation** is `v1.SCENE.EXPIRES.MAC`: the scene it opens (`*`: any), its end in
//!   Unix seconds, and the HMAC-SHA256 of both under the master's viewer key. The master keeps
//!   no list: whoever holds the key (`nephele invite`) can mint links, a link cannot be
//!   altered to another scene or a later end, and it stops working at its end. The page takes
//!   it from its URL (`?invite=...`) and sends it as `Authorization: Bearer ...` with the
//!   session request; without a viewer key the master asks for none.
//! * An **operator token** (opt-in) guards the operators' endpoints (`GET /v1/farm`, `GET
//!   /metrics`, `GET /v1/sessions`): with one, they answer 401 unless the request carries
//!   `Authorization: Bearer TOKEN`. Probes (`/livez`, `/readyz`) stay open for orchestrators.
//! * The **rate limit** is a token bucket per client address: `burst` session requests at
//!   once, then `per_minute`; beyond it `POST /v1/sessions` answers 429 with `Retry-After`.
//!   Refusals for capacity (503) and for access (401/403) count against it too, so retry
//!   loops and guessing are slowed alike. Behind a reverse proxy every client has the
//!   proxy's address: set the limit for the proxy, or off.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::Duration;

use hmac::{Hmac, Mac};
use sha2::Sha256;
use thiserror::Error;

/// Separates invitation MACs from any other use of the key.
const DOMAIN: &[u8] = b"nephele viewer invitation v1";
/// The scene of an invitation valid for every scene.
pub const ANY_SCENE: &str = "*";

/// The operators' token is the same on every process (`nephele_telemetry`).
pub use nephele_telemetry::OperatorToken;

/// The key invitations are signed with (at least 16 bytes). Its `Debug` does not show it.
#[derive(Clone, PartialEq, Eq)]
pub struct ViewerKey(Vec<u8>);

impl std::fmt::Debug for ViewerKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ViewerKey({} bytes)", self.0.len())
    }
}

impl ViewerKey {
    pub fn new(bytes: &[u8]) -> Option<ViewerKey> {
        (bytes.len() >= 16).then(|| ViewerKey(bytes.to_vec()))
    }

    fn mac(&self, scene: &str, expires: u64) -> Hmac<Sha256> {
        // HMAC takes keys of any length.
        let mut mac = <Hmac<Sha256> as Mac>::new_from_slice(&self.0).unwrap_or_else(|_| unreachable!());
        mac.update(DOMAIN);
        mac.update(scene.as_bytes());
        mac.update(b"\n");
        mac.update(expires.to_string().as_bytes());
        mac
    }

    /// An invitation to `scene` (or [`ANY_SCENE`]) until `expires` (Unix seconds).
    pub fn invite(&self, scene: &str, expires: u64) -> String {
        let mac: [u8; 32] = self.mac(scene, expires).finalize().into_bytes().into();
        let hex: String = mac.iter().map(|b| format!("{b:02x}")).collect();
        format!("v1.{scene}.{expires}.{hex}")
    }

    /// Checks `token` for a session on `scene` at `now` (Unix seconds).
    pub fn check(&self, token: &str, scene: &str, now: u64) -> Result<(), Denied> {
        let (body, mac) = token.rsplit_once('.').ok_or(Denied::Malformed)?;
        let (rest, expires) = body.rsplit_once('.').ok_or(Denied::Malformed)?;
        let invited = rest.strip_prefix("v1.").ok_or(Denied::Malformed)?;
        let expires: u64 = expires.parse().map_err(|_| Denied::Malformed)?;
        if mac.len() != 64 {
            return Err(Denied::Malformed);
        }
        let mut bytes = [0u8; 32];
        for (i, byte) in bytes.iter_mut().enumerate() {
            *byte = u8::from_str_radix(mac.get(2 * i..2 * i + 2).ok_or(Denied::Malformed)?, 16)
                .map_err(|_| Denied::Malformed)?;
        }
        // The signature first: nothing of an unsigned token is believed.
        self.mac(invited, expires).verify_slice(&bytes).map_err(|_| Denied::BadSignature)?;
        if now >= expires {
            return Err(Denied::Expired { ago_s: now - expires });
        }
        if invited != ANY_SCENE && invited != scene {
            return Err(Denied::WrongScene { invited: invited.to_string() });
        }
        Ok(())
    }
}

/// Why a session request was refused access.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum Denied {
    #[error("this service needs an invitation: open the link you were given (Authorization: Bearer INVITATION)")]
    Missing,
    #[error("the invitation is malformed")]
    Malformed,
    #[error("the invitation's signature is wrong (not made with this service's key, or altered)")]
    BadSignature,
    #[error("the invitation expired {ago_s} s ago")]
    Expired { ago_s: u64 },
    #[error("the invitation is for scene {invited:?}, not this one")]
    WrongScene { invited: String },
}

impl Denied {
    /// 401 when nothing was presented (the client should ask for credentials), 403 when
    /// what was presented is refused.
    pub fn is_missing(&self) -> bool {
        matches!(self, Denied::Missing)
    }
}

/// Token buckets per client address.
#[derive(Debug)]
pub struct RateLimiter {
    burst: f64,
    per_second: f64,
    buckets: Mutex<HashMap<IpAddr, Bucket>>,
}

#[derive(Debug, Clone, Copy)]
struct Bucket {
    tokens: f64,
    at: f64,
}

/// Most addresses remembered; beyond it, full buckets are forgotten first.
const MAX_BUCKETS: usize = 65_536;

impl RateLimiter {
    /// `burst` requests at once, refilled at `per_minute`. `None` if either is 0 (no limit).
    pub fn new(burst: u32, per_minute: u32) -> Option<RateLimiter> {
        (burst > 0 && per_minute > 0).then(|| RateLimiter {
            burst: f64::from(burst),
            per_second: f64::from(per_minute) / 60.0,
            buckets: Mutex::new(HashMap::new()),
        })
    }

    /// Takes one request of `ip` at `now` (seconds on any monotonic clock): `Err(wait)` when
    /// its bucket is empty, with the time until it holds one again.
    pub fn take(&self, ip: IpAddr, now: f64) -> Result<(), Duration> {
        let mut buckets = self.buckets.lock().unwrap_or_else(|p| p.into_inner());
        if buckets.len() >= MAX_BUCKETS && !buckets.contains_key(&ip) {
            let (burst, rate) = (self.burst, self.per_second);
            buckets.retain(|_, b| b.tokens + (now - b.at) * rate < burst);
            if buckets.len() >= MAX_BUCKETS {
                // Every remembered address is still limited: refuse newcomers rather than
                // forget who is being limited.
                return Err(Duration::from_secs_f64(1.0 / rate));
            }
        }
        let bucket = buckets.entry(ip).or_insert(Bucket { tokens: self.burst, at: now });
        bucket.tokens = (bucket.tokens + (now - bucket.at).max(0.0) * self.per_second).min(self.burst);
        bucket.at = now;
        if bucket.tokens >= 1.0 {
            bucket.tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - bucket.tokens) / self.per_second))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key() -> ViewerKey {
        ViewerKey::new(b"the viewer key of this test").expect("key")
    }

    #[test]
    fn invitations_open_their_scene_until_they_expire() {
        let k = key();
        let token = k.invite("default", 1_000);
        assert!(k.check(&token, "default", 999).is_ok());
        assert_eq!(k.check(&token, "default", 1_000), Err(Denied::Expired { ago_s: 0 }));
        assert_eq!(k.check(&token, "room-day", 10), Err(Denied::WrongScene { invited: "default".into() }));
        let any = k.invite(ANY_SCENE, 1_000);
        assert!(k.check(&any, "room-day", 10).is_ok());
        // Scene names with dots survive the format.
        let dotted = k.invite("lego.v2", 50);
        assert!(k.check(&dotted, "lego.v2", 10).is_ok());
    }

    #[test]
    fn altered_foreign_and_garbage_invitations_are_refused() {
        let k = key();
        let token = k.invite("default", 1_000);
        // A later end or another scene with the old signature.
        let later = token.replacen(".1000.", ".9999.", 1);
        assert_eq!(k.check(&later, "default", 10), Err(Denied::BadSignature));
        let other = token.replacen("v1.default.", "v1.room-day.", 1);
        assert_eq!(k.check(&other, "room-day", 10), Err(Denied::BadSignature));
        let foreign = ViewerKey::new(b"somebody else's viewer key").expect("key").invite("default", 1_000);
        assert_eq!(k.check(&foreign, "default", 10), Err(Denied::BadSignature));
        for garbage in ["", "v1", "v1.default.1000", "v2.default.1000.00", "v1.default.x.00", &token[..token.len() - 1]]
        {
            assert_eq!(k.check(garbage, "default", 10), Err(Denied::Malformed), "{garbage:?}");
        }
        let not_hex = format!("v1.default.1000.{}", "zz".repeat(32));
        assert_eq!(k.check(&not_hex, "default", 10), Err(Denied::Malformed));
        assert!(ViewerKey::new(b"short").is_none());
    }

    #[test]
    fn the_rate_limit_allows_a_burst_then_the_rate_per_address() {
        let limiter = RateLimiter::new(3, 60).expect("limiter");
        let (a, b): (IpAddr, IpAddr) = ("10.0.0.1".parse().expect("ip"), "10.0.0.2".parse().expect("ip"));
        for _ in 0..3 {
            assert!(limiter.take(a, 0.0).is_ok());
        }
        let wait = limiter.take(a, 0.0).expect_err("burst spent");
        assert!((wait.as_secs_f64() - 1.0).abs() < 1e-9, "{wait:?}");
        // Another address has its own bucket.
        assert!(limiter.take(b, 0.0).is_ok());
        // One token a second comes back; never more than the burst.
        assert!(limiter.take(a, 1.0).is_ok());
        assert!(limiter.take(a, 1.0).is_err());
        for _ in 0..3 {
            assert!(limiter.take(a, 100.0).is_ok());
        }
        assert!(limiter.take(a, 100.0).is_err());
        assert!(RateLimiter::new(0, 60).is_none() && RateLimiter::new(5, 0).is_none());
    }
}
