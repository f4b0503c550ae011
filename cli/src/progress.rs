//! Progress bars for long work (indicatif), hidden when asked or when stderr is no terminal.

use indicatif::{ProgressBar, ProgressStyle};

#[derive(Debug, Clone, Copy)]
pub struct Progress {
    quiet: bool,
}

impl Progress {
    pub fn new(quiet: bool) -> Self {
        Progress { quiet }
    }

    /// A bar of `total` steps labelled `what` (e.g. "rows").
    pub fn bar(&self, total: u64, message: &str, unit: &str) -> ProgressBar {
        if self.quiet {
            return ProgressBar::hidden();
        }
        let bar = ProgressBar::new(total);
        let template = format!("{{msg}} [{{elapsed_precise}}] {{wide_bar}} {{pos}}/{{len}} {unit} (eta {{eta}})");
        if let Ok(style) = ProgressStyle::with_template(&template) {
            bar.set_style(style);
        }
        bar.set_message(message.to_string());
        bar
    }
}

impl nephele_bench::Progress for Progress {
    fn bar(&self, total: u64, message: &str, unit: &str) -> ProgressBar {
        Progress::bar(self, total, message, unit)
    }
}
