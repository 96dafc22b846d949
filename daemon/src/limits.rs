//! Bounds on the text clients send: names, ids and request ids are checked against these before
//! anything is stored, looked up or echoed, so that one client cannot grow every listing past
//! what a response may carry, nor fill error messages with its input.

use crate::error::DaemonError;

/// A dataset's name (an upload's file name, or the name given at registration).
pub const MAX_NAME_BYTES: usize = 256;
/// A server-side path given to `RegisterDataset`.
pub const MAX_PATH_BYTES: usize = 4096;
/// A submission's idempotency key.
pub const MAX_REQUEST_ID_BYTES: usize = 128;
/// A dataset, job or lease id: the daemon's own ids are far shorter.
pub const MAX_ID_BYTES: usize = 64;
/// A worker's name, shown in leases and logs.
pub const MAX_WORKER_NAME_BYTES: usize = 128;
/// A worker's reason for failing a frame, kept in the job's error: longer reasons are cut.
pub const MAX_REASON_BYTES: usize = 4096;
/// The longest message a status carries back to a client.
pub const MAX_MESSAGE_BYTES: usize = 2048;

/// `value` of `field` is at most `max` bytes long; the error does not repeat the value.
pub fn check_length(field: &str, value: &str, max: usize) -> Result<(), DaemonError> {
    if value.len() <= max {
        return Ok(());
    }
    Err(DaemonError::invalid(
        field,
        format!("is {} bytes long; at most {max} are accepted", value.len()),
    ))
}

/// An id, checked as [`check_length`] does with [`MAX_ID_BYTES`].
pub fn check_id(field: &str, id: &str) -> Result<(), DaemonError> {
    check_length(field, id, MAX_ID_BYTES)
}

/// `text` cut to at most `max` bytes at a character boundary, marked with an ellipsis when cut.
pub fn truncated(text: &str, max: usize) -> String {
    if text.len() <= max {
        return text.to_string();
    }
    let mut end = max.saturating_sub('…'.len_utf8());
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", &text[..end])
}

/// A worker's reason for failing a frame or a video, as the job keeps it: cut to
/// [`MAX_REASON_BYTES`], and said to be missing when the worker sent none.
pub fn failure_reason(reason: &str) -> String {
    if reason.is_empty() {
        "the worker gave no reason".to_string()
    } else {
        truncated(reason, MAX_REASON_BYTES)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lengths_are_checked_without_echoing_the_value() {
        assert!(check_length("name", "scan.laz", MAX_NAME_BYTES).is_ok());
        let long = "x".repeat(MAX_NAME_BYTES + 1);
        let message = check_length("name", &long, MAX_NAME_BYTES)
            .expect_err("too long")
            .to_string();
        assert_eq!(message, "name: is 257 bytes long; at most 256 are accepted");
    }

    #[test]
    fn truncation_keeps_characters_whole() {
        assert_eq!(truncated("short", 10), "short");
        let cut = truncated(&"é".repeat(100), 11);
        assert!(cut.len() <= 11, "{cut}");
        assert!(cut.ends_with('…'));
        assert!(cut.starts_with("ééé"));
    }

    #[test]
    fn a_failure_reason_is_cut_and_never_empty() {
        assert_eq!(failure_reason(""), "the worker gave no reason");
        assert_eq!(failure_reason("disk full"), "disk full");
        let kept = failure_reason(&"x".repeat(MAX_REASON_BYTES * 2));
        assert!(
            kept.len() <= MAX_REASON_BYTES && kept.ends_with('…'),
            "{kept}"
        );
    }
}
