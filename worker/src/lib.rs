//! nephele-worker (being written)
