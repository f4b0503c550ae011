//! Fuzzes the `.nolf` asset loader: arbitrary bytes must give `Ok` or a typed error, never a
//! panic, an abort or an allocation out of proportion to the input.
//!
//! Run: `cd kernels/fuzz && cargo fuzz run asset_load` (cargo-fuzz needs a nightly
//! compiler; `RUSTC_BOOTSTRAP=1 cargo fuzz run asset_load` works with a stable one).
//! Half of the inputs get their checksums repaired first, so that mutations reach the
//! section parsers instead of stopping at the CRC check.

#![no_main]

use libfuzzer_sys::fuzz_target;
use nephele_kernels::inolf::asset::{Asset, reseal_checksums};

fuzz_target!(|data: &[u8]| {
    let _ = Asset::from_bytes(data);
    if data.first().is_some_and(|b| b & 1 == 1) {
        let mut fixed = data.to_vec();
        if reseal_checksums(&mut fixed) {
            let _ = Asset::from_bytes(&fixed);
        }
    }
});
