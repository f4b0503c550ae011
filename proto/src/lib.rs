//! nephele-proto (being written)
