//! Invitations (`Authorization: Bearer v1.SCENE.EXPIRES.HMAC`) are read from anyone who can
//! reach the master. On arbitrary bytes `ViewerKey::check` must not panic, and must accept
//! nothing but what the key itself signed; and every invitation the key signs, for any scene
//! name (dots, newlines, the wildcard) and any expiry, opens that scene until it expires.
#![no_main]

use libfuzzer_sys::fuzz_target;
use nephele_master::access::{ANY_SCENE, Denied, ViewerKey};

fuzz_target!(|data: &[u8]| {
    let key = ViewerKey::new(b"a fuzzing key of 32 bytes, fixed").expect("long enough");
    // Arbitrary text as a token, checked against a scene taken from the same bytes.
    let text = String::from_utf8_lossy(data);
    let (token, scene) = text.split_once('\u{0}').unwrap_or((&text, "default"));
    let now = 1_700_000_000;
    if key.check(token, scene, now).is_ok() {
        // Only a token this key signed: re-signing what it claims gives the same token.
        let (body, _) = token.rsplit_once('.').expect("accepted tokens have a MAC");
        let (rest, expires) = body.rsplit_once('.').expect("and an expiry");
        let invited = rest.strip_prefix("v1.").expect("and the version");
        let expires: u64 = expires.parse().expect("a number");
        assert_eq!(key.invite(invited, expires), token, "accepted a token the key did not sign");
    }
    // Round trip: an invitation for this scene opens it before it expires, not after, and
    // opens no other scene unless it is the wildcard.
    let expires = data.iter().take(8).fold(0u64, |a, &b| (a << 8) | u64::from(b));
    let invitation = key.invite(scene, expires);
    if expires > 0 {
        assert_eq!(key.check(&invitation, scene, expires - 1), Ok(()), "{invitation:?}");
    }
    assert!(matches!(key.check(&invitation, scene, expires), Err(Denied::Expired { .. })));
    if scene != ANY_SCENE && expires > 0 {
        let other = format!("{scene}x");
        assert!(matches!(key.check(&invitation, &other, expires - 1), Err(Denied::WrongScene { .. })));
    }
});
