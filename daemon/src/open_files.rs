//! The process's limit on open files. Every connection, dataset file, store and frame takes
//! a descriptor, and the usual soft limit (1,024) is far below what a farm's daemon or worker
//! needs under load, while the hard limit is usually generous: the process raises its soft
//! limit to the hard one at start, and sizes its connection bounds by what it got.

/// Raises the soft open-file limit to the hard limit, where it is lower; returns the soft
/// limit in force afterwards (`u64::MAX` for none).
#[cfg(unix)]
pub fn raise_soft_limit() -> u64 {
    use rustix::process::{getrlimit, setrlimit, Resource, Rlimit};

    let limit = getrlimit(Resource::Nofile);
    let current = limit.current.unwrap_or(u64::MAX);
    let maximum = limit.maximum.unwrap_or(u64::MAX);
    if current >= maximum {
        return current;
    }
    let raised = Rlimit {
        current: limit.maximum,
        maximum: limit.maximum,
    };
    match setrlimit(Resource::Nofile, raised) {
        Ok(()) => {
            tracing::info!(from = current, to = maximum, "raised the open-file limit");
            maximum
        }
        Err(error) => {
            tracing::warn!(%error, limit = current, "could not raise the open-file limit");
            current
        }
    }
}

#[cfg(not(unix))]
pub fn raise_soft_limit() -> u64 {
    u64::MAX
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    #[test]
    fn the_soft_limit_ends_at_the_hard_limit() {
        let raised = raise_soft_limit();
        let limit = rustix::process::getrlimit(rustix::process::Resource::Nofile);
        assert_eq!(limit.current, limit.maximum);
        assert_eq!(raised, limit.current.unwrap_or(u64::MAX));
    }
}
