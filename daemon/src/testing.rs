//! Test helpers (the `testing` feature, for other crates' tests): a real small disk to fill.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

/// A real small disk: a tmpfs of a few MiB on a new folder, so that writes fail with ENOSPC
/// as on a full disk. Mounted directly where the process may mount (root), else in a user
/// and mount namespace of its own (`unshare`), reached through `/proc/<pid>/root` of the
/// process holding that namespace. Unmounted and removed when dropped, also when a test
/// fails; whatever runs on it must be stopped first.
pub struct SmallDisk {
    mount_point: PathBuf,
    /// Where the disk is reached from this process (and its children).
    path: PathBuf,
    /// The process whose mount namespace holds the disk, when mounted with `unshare`.
    holder: Option<Child>,
}

impl SmallDisk {
    /// A tmpfs of `mib` MiB, or None where this process can mount none (the reason is
    /// printed: a test then says it is skipped, and why).
    pub fn mount(mib: u32) -> Option<Self> {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let mount_point = std::env::temp_dir().join(format!(
            "pointfarm-small-disk-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::SeqCst)
        ));
        if let Err(e) = std::fs::create_dir_all(&mount_point) {
            eprintln!("no small disk: creating {}: {e}", mount_point.display());
            return None;
        }
        let size = format!("size={mib}m");
        let direct = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &size, "tmpfs"])
            .arg(&mount_point)
            .output();
        let direct_error = match direct {
            Ok(output) if output.status.success() => {
                return Some(Self {
                    path: mount_point.clone(),
                    mount_point,
                    holder: None,
                })
            }
            Ok(output) => String::from_utf8_lossy(&output.stderr).trim().to_string(),
            Err(e) => e.to_string(),
        };
        match Self::mount_in_namespace(&mount_point, &size) {
            Ok(disk) => Some(disk),
            Err(namespace_error) => {
                let _ = std::fs::remove_dir(&mount_point);
                eprintln!(
                    "no small disk, the test is skipped: mounting a tmpfs failed \
                     (mount: {direct_error}; unshare: {namespace_error})"
                );
                None
            }
        }
    }

    /// Mounts the tmpfs in a new user and mount namespace held by a sleeping process.
    fn mount_in_namespace(mount_point: &Path, size: &str) -> Result<Self, String> {
        let script = format!(
            "mount -t tmpfs -o {size} tmpfs '{}' && echo mounted && exec sleep 100000",
            mount_point.display()
        );
        let mut holder = Command::new("unshare")
            .args(["--user", "--map-root-user", "--mount", "sh", "-c", &script])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| e.to_string())?;
        let mut said = String::new();
        if let Some(stdout) = holder.stdout.as_mut() {
            use std::io::Read;
            let mut byte = [0u8; 1];
            while !said.ends_with('\n') && stdout.read(&mut byte).unwrap_or(0) == 1 {
                said.push(byte[0] as char);
            }
        }
        if said.trim() != "mounted" {
            let _ = holder.kill();
            let output = holder.wait_with_output().map_err(|e| e.to_string())?;
            return Err(String::from_utf8_lossy(&output.stderr).trim().to_string());
        }
        let path = PathBuf::from(format!("/proc/{}/root", holder.id())).join(
            mount_point
                .strip_prefix("/")
                .map_err(|_| "the mount point is not absolute".to_string())?,
        );
        Ok(Self {
            mount_point: mount_point.to_owned(),
            path,
            holder: Some(holder),
        })
    }

    /// The disk's root folder.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Fills the disk to its last byte with the file `name`; returns the file's path. Delete
    /// it to give the space back.
    pub fn fill(&self, name: &str) -> PathBuf {
        let filler = self.path.join(name);
        let mut file = std::fs::File::create(&filler).expect("create the filler file");
        let block = vec![0xa5u8; 64 << 10];
        // Smaller and smaller writes use up what a page-sized rest still holds.
        for size in [block.len(), 4096, 512, 1] {
            while file.write_all(&block[..size]).is_ok() {}
        }
        let _ = file.sync_all();
        filler
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        match self.holder.as_mut() {
            // The namespace, and its mount, end with the process that holds them.
            Some(holder) => {
                let _ = holder.kill();
                let _ = holder.wait();
            }
            None => {
                // Lazily: a process of a failed test may still hold a file there.
                for _ in 0..50 {
                    let unmounted = Command::new("umount")
                        .arg("--lazy")
                        .arg(&self.mount_point)
                        .status()
                        .is_ok_and(|s| s.success());
                    if unmounted {
                        break;
                    }
                    std::thread::sleep(Duration::from_millis(100));
                }
            }
        }
        let _ = std::fs::remove_dir(&self.mount_point);
    }
}
