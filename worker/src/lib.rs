//! `nephele-worker`: the render worker process (receives ray batches over TCP, runs the
//! kernels of `nephele-render`, sends results to the composer).
//!
//! Empty for now: it arrives with the ray-level scheduling work (issue 4).
