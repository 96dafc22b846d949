//! Progress on long work: one spinner style for every command.

use indicatif::ProgressBar;

/// A spinner showing `message`, ticking until it is finished.
pub fn spinner(message: String) -> ProgressBar {
    let spinner = ProgressBar::new_spinner().with_message(message);
    spinner.enable_steady_tick(std::time::Duration::from_millis(100));
    spinner
}
