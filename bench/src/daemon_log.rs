//! Numbers read from a daemon's log lines, which the figures through a real `pointfarm serve`
//! take their times from.

/// The number following `key` (`" seconds="`) in a log line, quoted or not.
pub fn number_after(line: &str, key: &str) -> Option<f64> {
    let at = line.find(key)? + key.len();
    let number: String = line[at..]
        .trim_start_matches('"')
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.')
        .collect();
    number.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::number_after;

    #[test]
    fn a_number_is_read_quoted_or_not() {
        let line = r#"INFO updated seconds="1.25" regions_kept=85 "done""#;
        assert_eq!(number_after(line, " seconds="), Some(1.25));
        assert_eq!(number_after(line, " regions_kept="), Some(85.0));
        assert_eq!(number_after(line, " points="), None);
    }
}
