use super::*;

use tokio::io::{AsyncReadExt, AsyncWriteExt};

fn limits(max_connections: usize, max_unadmitted: usize) -> ConnectionLimits {
    ConnectionLimits {
        max_connections,
        max_unadmitted,
        first_request_timeout: Duration::from_millis(300),
        idle_timeout: Duration::from_millis(300),
    }
}

/// [`limits`] under which a connection waits a minute for its first call: long enough that
/// only the limits on connections close one during a test.
fn patient_limits(max_connections: usize, max_unadmitted: usize) -> ConnectionLimits {
    ConnectionLimits {
        first_request_timeout: Duration::from_secs(60),
        ..limits(max_connections, max_unadmitted)
    }
}

async fn listener(limits: ConnectionLimits) -> (Listener, SocketAddr) {
    let tcp = TcpListener::bind(("127.0.0.1", 0)).await.expect("bind");
    let address = tcp.local_addr().expect("address");
    (Listener::new(tcp, limits), address)
}

/// Reads from `connection` until it fails or ends: a closed connection fails.
async fn read_until_closed(mut connection: Connection) -> io::Error {
    let mut buffer = [0u8; 16];
    loop {
        match connection.read(&mut buffer).await {
            Ok(0) => return io::Error::new(io::ErrorKind::UnexpectedEof, "peer closed"),
            Ok(_) => {}
            Err(error) => return error,
        }
    }
}

#[test]
fn limits_follow_the_open_file_limit() {
    let small = ConnectionLimits::for_open_files(1024);
    assert_eq!(small.max_connections, 512);
    assert_eq!(small.max_unadmitted, 128);
    assert_eq!(
        ConnectionLimits::for_open_files(u64::MAX).max_connections,
        MAX_CONNECTIONS_CAP
    );
    assert_eq!(ConnectionLimits::for_open_files(0).max_connections, 16);
}

#[tokio::test]
async fn accepted_sockets_have_nodelay_and_keepalive() {
    let (mut listener, address) = listener(limits(8, 4)).await;
    let _client = TcpStream::connect(address).await.expect("connect");
    let connection = listener.accept().await.expect("accept");
    assert!(connection.get_ref().nodelay().expect("nodelay"));
    #[cfg(unix)]
    assert!(rustix::net::sockopt::socket_keepalive(connection.get_ref()).expect("keepalive"));
    assert_eq!(connection.info().remote_addr(), _client.local_addr().ok());
}

#[tokio::test]
async fn a_connection_without_an_admitted_call_is_closed_in_time() {
    let (mut listener, address) = listener(limits(8, 4)).await;
    let _client = TcpStream::connect(address).await.expect("connect");
    let connection = listener.accept().await.expect("accept");
    let started = Instant::now();
    let error = tokio::time::timeout(Duration::from_secs(5), read_until_closed(connection))
        .await
        .expect("closed within the bound");
    assert_eq!(error.kind(), io::ErrorKind::TimedOut, "{error}");
    assert!(started.elapsed() >= Duration::from_millis(250));
}

#[tokio::test]
async fn an_admitted_connection_lives_while_a_request_is_in_flight_then_idles_out() {
    let (mut listener, address) = listener(limits(8, 4)).await;
    let mut client = TcpStream::connect(address).await.expect("connect");
    let mut connection = listener.accept().await.expect("accept");
    connection.info().admit();
    let request = RequestInFlight::begin(connection.info().state.clone());
    // Well past both timeouts, bytes still flow while the request is in flight.
    tokio::time::sleep(Duration::from_millis(700)).await;
    client.write_all(b"ping").await.expect("write");
    let mut buffer = [0u8; 4];
    connection.read_exact(&mut buffer).await.expect("read");
    drop(request);
    let started = Instant::now();
    let error = tokio::time::timeout(Duration::from_secs(5), read_until_closed(connection))
        .await
        .expect("closed once idle");
    assert!(error.to_string().contains("idle"), "{error}");
    assert!(started.elapsed() >= Duration::from_millis(250));
}

#[tokio::test]
async fn a_new_connection_displaces_the_oldest_waiting_one() {
    let (mut listener, address) = listener(patient_limits(8, 2)).await;
    let mut clients = Vec::new();
    let mut connections = Vec::new();
    for _ in 0..3 {
        clients.push(TcpStream::connect(address).await.expect("connect"));
        connections.push(listener.accept().await.expect("accept"));
    }
    let mut connections = connections.into_iter();
    let oldest = connections.next().expect("the first");
    let error = tokio::time::timeout(Duration::from_secs(5), read_until_closed(oldest))
        .await
        .expect("displaced at once");
    assert!(error.to_string().contains("too many"), "{error}");
    // The others wait on.
    for mut waiting in connections {
        let mut buffer = [0u8; 1];
        let read = tokio::time::timeout(Duration::from_millis(100), waiting.read(&mut buffer));
        assert!(read.await.is_err(), "still open");
    }
}

#[tokio::test]
async fn past_the_connection_limit_admitted_connections_are_kept_and_new_ones_refused() {
    let (mut listener, address) = listener(patient_limits(2, 2)).await;
    let mut kept = Vec::new();
    for _ in 0..2 {
        let client = TcpStream::connect(address).await.expect("connect");
        let connection = listener.accept().await.expect("accept");
        connection.info().admit();
        kept.push((client, connection));
    }
    assert_eq!(listener.open_connections(), 2);
    // The third is refused (closed by the listener), the fourth too; a fifth gets in once
    // one of the kept ones closes.
    let mut refused = TcpStream::connect(address).await.expect("connect");
    let accept = tokio::time::timeout(Duration::from_millis(300), listener.accept()).await;
    assert!(accept.is_err(), "no connection past the limit");
    let mut buffer = [0u8; 1];
    assert_eq!(refused.read(&mut buffer).await.unwrap_or(0), 0, "closed");
    drop(kept.pop());
    let _late = TcpStream::connect(address).await.expect("connect");
    let accepted = tokio::time::timeout(Duration::from_secs(5), listener.accept()).await;
    assert!(accepted.is_ok(), "room again");
}
