//! The `nephele` command, built as a binary of this package so that `cargo test` builds it
//! together with the integration tests that run it (see `nephele_tests::nephele_bin`).

fn main() -> std::process::ExitCode {
    nephele_cli::main()
}
