//! Progress bars (hidden when stderr is not a terminal, e.g. in CI).

use indicatif::{ProgressBar, ProgressStyle};

/// A bar over `len` items with a message slot for live figures.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len);
    let style = ProgressStyle::with_template(&format!(
        "{what:>10} [{{elapsed_precise}}] {{bar:30.cyan/blue}} {{pos}}/{{len}} ({{eta}} left) {{msg}}"
    ))
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    pb.set_style(style);
    pb
}
