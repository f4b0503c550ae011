//! The `nephele` binary: everything is in the library (see `lib.rs`).

fn main() -> std::process::ExitCode {
    nephele_cli::main()
}
