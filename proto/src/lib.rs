//! `nephele-proto`: every message that crosses a Nephele process boundary (master, workers,
//! composer), with its framing, versioning and validation.
//!
//! Empty for now: the messages arrive with the ray-level scheduling work (issue 4). The crate
//! exists so that the dependency direction of the workspace is fixed from the start:
//! `proto` and `core-render` depend on nothing of ours; services depend on them.
