//! Fuzzes the `.nelf` (NeLF) and `.ngi` (stereo GI) decoders: arbitrary bytes must give `Ok`
//! or a typed error, never a panic, an abort or an allocation out of proportion to the input.
//!
//! Run: `cd kernels/fuzz && cargo fuzz run model_load` (cargo-fuzz needs a nightly compiler;
//! `RUSTC_BOOTSTRAP=1 cargo fuzz run model_load` works with a stable one). Half of the inputs
//! get their trailing checksum repaired first, so that mutations reach the header and payload
//! parsers instead of stopping at the CRC check. The first byte picks the decoder; the seeded
//! property tests next to each decoder (`nelf/tests.rs`, `gi.rs`) run the same in CI.

#![no_main]

use libfuzzer_sys::fuzz_target;
use nephele_kernels::assets::reseal_trailing_crc;
use nephele_kernels::gi::GiModel;
use nephele_kernels::nelf::NelfModel;

fuzz_target!(|data: &[u8]| {
    let Some((&selector, rest)) = data.split_first() else {
        return;
    };
    let decode = |bytes: &[u8]| {
        if selector & 2 == 0 {
            let _ = NelfModel::from_bytes(bytes);
        } else {
            let _ = GiModel::from_bytes(bytes);
        }
    };
    decode(rest);
    if selector & 1 == 1 {
        let mut fixed = rest.to_vec();
        if reseal_trailing_crc(&mut fixed) {
            decode(&fixed);
        }
    }
});
