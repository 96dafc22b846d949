//! Progress on long work: one spinner style and one counting bar for every command.

use indicatif::ProgressBar;

/// A spinner showing `message`, ticking until it is finished.
pub fn spinner(message: String) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message);
    spinner.enable_steady_tick(std::time::Duration::from_millis(100));
    spinner
}

/// A bar counting `total` items of `unit` (e.g. points) with `message`, drawn only on a
/// terminal.
pub fn counter(total: u64, unit: &str, message: String) -> ProgressBar {
    if !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        return ProgressBar::hidden();
    }
    let template = format!("{{msg}} {{bar:40}} {{pos}}/{{len}} {unit} {{eta}}");
    ProgressBar::new(total)
        .with_style(
            indicatif::ProgressStyle::with_template(&template)
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        )
        .with_message(message)
}
