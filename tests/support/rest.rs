//! One plain HTTP/1.0 request to a test's server on loopback, for the setup a test needs that
//! the product does not do itself (making a container, seeding an object, reading one back).

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// A server's answer: its status, its header lines and its body.
pub struct Answer {
    pub status: u16,
    pub head: String,
    pub body: Vec<u8>,
}

impl Answer {
    /// The body as text, for a failed request's message.
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// `method http://{address}{target}` with `headers` and `body`. HTTP/1.0, so that the answer is
/// the plain body up to the end of the connection.
pub fn request(
    address: &str,
    method: &str,
    target: &str,
    headers: &[(&str, String)],
    body: &[u8],
) -> Answer {
    try_request(address, method, target, headers, body)
        .unwrap_or_else(|e| panic!("{method} {target} to the test server at {address}: {e}"))
}

/// [`request`], an error where the server cannot be reached or stops answering: what a wait
/// for a server that is still starting polls.
pub fn try_request(
    address: &str,
    method: &str,
    target: &str,
    headers: &[(&str, String)],
    body: &[u8],
) -> std::io::Result<Answer> {
    let mut stream = TcpStream::connect(address)?;
    stream.set_read_timeout(Some(Duration::from_secs(30)))?;
    let mut request = format!("{method} {target} HTTP/1.0\r\nHost: {address}\r\n");
    for (name, value) in headers {
        request.push_str(&format!("{name}: {value}\r\n"));
    }
    request.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    stream.write_all(request.as_bytes())?;
    stream.write_all(body)?;
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer)?;
    let split = answer
        .windows(4)
        .position(|window| window == b"\r\n\r\n")
        .unwrap_or(answer.len());
    let head = String::from_utf8_lossy(&answer[..split]).into_owned();
    let body = answer.get(split + 4..).unwrap_or_default().to_vec();
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|code| code.parse().ok())
        .unwrap_or(0);
    Ok(Answer { status, head, body })
}
