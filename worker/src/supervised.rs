//! The worker's side of being supervised (`pointfarm worker --supervised`, the daemon's
//! embedded worker): its standard input is a pipe from the daemon, and the worker exits as
//! soon as that pipe closes, so no orphan goes on rendering after its daemon is gone.

/// In the worker process started by a supervisor: exits the process as soon as its standard
/// input closes, which happens when the daemon exits, however it ends.
pub fn exit_when_supervisor_exits() -> std::io::Result<()> {
    std::thread::Builder::new()
        .name("supervisor-watch".into())
        .spawn(|| {
            let _ = std::io::copy(&mut std::io::stdin(), &mut std::io::sink());
            eprintln!("the daemon that supervised this worker is gone: exiting");
            std::process::exit(1);
        })
        .map(|_| ())
}
