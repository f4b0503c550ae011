//! nephele-composer (being written)
