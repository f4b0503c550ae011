//! nephele-master (being written)
