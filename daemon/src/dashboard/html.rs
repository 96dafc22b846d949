//! The pages' HTML: one layout (navigation, the stylesheet and script, a logout button), the
//! login form, and the small formatting every page shares. Everything a user or worker
//! named (job, dataset, worker and file names, errors) is escaped.

use std::collections::BTreeMap;
use std::fmt::Write;

use crate::model::{Job, JobState};

/// `text` safe in HTML text and in quoted attributes.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// `text` as one path segment of a URL (job ids are safe already; this keeps them so).
pub fn segment(text: &str) -> String {
    form_urlencoded::byte_serialize(text.as_bytes())
        .collect::<String>()
        .replace('+', "%20")
}

/// The pages in the navigation, with the path each is at.
const SECTIONS: [(&str, &str); 3] = [
    ("Jobs", "/"),
    ("Workers", "/workers"),
    ("Datasets", "/datasets"),
];

/// A whole page: `title`, the section it belongs to (highlighted in the navigation), the
/// `page` name its script reads, its `data` attributes and its `body`.
pub fn layout(title: &str, section: &str, page: &str, data: &str, body: &str) -> String {
    let mut nav = String::new();
    for (name, path) in SECTIONS {
        let current = if name == section {
            " aria-current=\"page\""
        } else {
            ""
        };
        let _ = write!(nav, "<a href=\"{path}\"{current}>{name}</a>");
    }
    format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>{title} · pointfarm</title>\
         <link rel=\"stylesheet\" href=\"/assets/dashboard.css\">\
         <script src=\"/assets/dashboard.js\" defer></script></head>\
         <body data-page=\"{page}\"{data}><header><strong class=\"brand\">pointfarm</strong>\
         <nav>{nav}</nav><span class=\"live\" aria-live=\"polite\"></span><form method=\"post\" action=\"/logout\" class=\"logout\">\
         <button type=\"submit\">Log out</button></form></header>\
         <main>{body}</main></body></html>\n",
        title = escape(title),
    )
}

/// The login form, with `message` when a token was refused.
pub fn login_page(message: Option<&str>, next: &str) -> String {
    let message = message
        .map(|m| format!("<p class=\"error\" role=\"alert\">{}</p>", escape(m)))
        .unwrap_or_default();
    format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>Log in · pointfarm</title>\
         <link rel=\"stylesheet\" href=\"/assets/dashboard.css\"></head>\
         <body data-page=\"login\"><main class=\"login\"><h1>pointfarm</h1>{message}\
         <form method=\"post\" action=\"/login\">\
         <label for=\"token\">Client token (<code>--token</code>)</label>\
         <input id=\"token\" name=\"token\" type=\"password\" autocomplete=\"current-password\" \
         required autofocus>\
         <input type=\"hidden\" name=\"next\" value=\"{next}\">\
         <button type=\"submit\">Log in</button></form></main></body></html>\n",
        next = escape(next),
    )
}

/// A page that says what went wrong.
pub fn error_page(section: &str, message: &str) -> String {
    layout(
        "Error",
        section,
        "error",
        "",
        &format!("<p class=\"error\" role=\"alert\">{}</p>", escape(message)),
    )
}

/// A state as a badge the stylesheet colors.
pub fn state_badge(state: JobState) -> String {
    let name = state.name();
    format!("<span class=\"state state-{name}\">{name}</span>")
}

/// A job's labels as chips (`key=value`), each a link to `link(key, value)`: the jobs list
/// filtered by it.
pub fn label_chips(
    labels: &BTreeMap<String, String>,
    link: impl Fn(&str, &str) -> String,
) -> String {
    let mut out = String::from("<span class=\"labels\">");
    for (key, value) in labels {
        let _ = write!(
            out,
            "<a class=\"chip\" href=\"{href}\">{key}={value}</a>",
            href = escape(&link(key, value)),
            key = escape(key),
            value = escape(value),
        );
    }
    out.push_str("</span>");
    out
}

/// Bytes in binary units, as the CLI prints them: `1.5 GiB`.
pub fn bytes(n: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut value = n as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit < UNITS.len() - 1 {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{n} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// A span of seconds as people read it: `45 s`, `3 min 20 s`, `2 h 5 min`.
pub fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        0..=59 => format!("{s} s"),
        60..=3599 => format!("{} min {} s", s / 60, s % 60),
        _ => format!("{} h {} min", s / 3600, (s % 3600) / 60),
    }
}

/// The seconds left of a running job at `now_ms`, at the pace of its frames so far; `None`
/// before its first frame and once it has ended.
pub fn eta_seconds(job: &Job, now_ms: i64) -> Option<f64> {
    if job.state != JobState::Running || job.frames_done == 0 {
        return None;
    }
    let elapsed_s = (now_ms - job.created_unix_ms).max(0) as f64 / 1000.0;
    let left = job.frames_total.saturating_sub(job.frames_done) as f64;
    Some(elapsed_s / job.frames_done as f64 * left)
}

/// A time as UTC, to the second: `2026-12-06 00:12:03`.
pub fn time(unix_ms: i64) -> String {
    let seconds = unix_ms.div_euclid(1000);
    let (days, of_day) = (seconds.div_euclid(86_400), seconds.rem_euclid(86_400));
    // Days to a civil date (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02}",
        of_day / 3600,
        (of_day % 3600) / 60,
        of_day % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_escaped() {
        assert_eq!(
            escape("<img src=x onerror=\"a('b')\">&"),
            "&lt;img src=x onerror=&quot;a(&#39;b&#39;)&quot;&gt;&amp;"
        );
        assert_eq!(segment("a b/c"), "a%20b%2Fc");
    }

    #[test]
    fn sizes_spans_and_times_read_as_people_write_them() {
        assert_eq!(bytes(512), "512 B");
        assert_eq!(bytes(3 << 29), "1.5 GiB");
        assert_eq!(duration(45.2), "45 s");
        assert_eq!(duration(200.0), "3 min 20 s");
        assert_eq!(duration(7500.0), "2 h 5 min");
        assert_eq!(time(0), "1970-01-01 00:00:00");
        assert_eq!(time(1_796_515_923_000), "2026-12-06 00:12:03");
    }
}
