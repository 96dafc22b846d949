//! Wrong tokens from one client address are slowed, then refused for a while: a token given
//! to the login form or as `Authorization: Bearer` counts against its address when it is no
//! token of this daemon (the worker token, a cookie that has expired or a missing credential
//! are no guesses and count nothing).
//!
//! From [`LoginLimit::failures_before_slowing`] wrong tokens on, each answer to another waits
//! [`LoginLimit::delay_per_failure`] longer; at [`LoginLimit::failures_before_refusing`] the
//! address is refused every token, right or wrong, with HTTP 429 and `Retry-After`, until
//! [`LoginLimit::window`] has passed since its last wrong token. Failures further apart than
//! the window are forgotten, and a right token forgets them too. IPv6 addresses count by
//! their /64 network, which one client usually holds whole. The addresses followed are
//! bounded ([`LoginLimit::addresses`]): when full, the quietest is forgotten.

use std::collections::HashMap;
use std::net::{IpAddr, Ipv6Addr};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How wrong tokens are slowed and refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoginLimit {
    /// Wrong tokens from an address answered at once; each one after waits longer.
    pub failures_before_slowing: u32,
    /// How much longer each wrong token past `failures_before_slowing` waits for its answer.
    pub delay_per_failure: Duration,
    /// Wrong tokens after which the address is refused.
    pub failures_before_refusing: u32,
    /// How long failures are remembered, and an address refused, after its last wrong token.
    pub window: Duration,
    /// The most addresses followed at once.
    pub addresses: usize,
}

impl LoginLimit {
    /// The dashboard's limit: three mistypes pass at once, ten wrong tokens lock the address
    /// out for five minutes, so that a guesser tries a few thousand tokens a day.
    pub const DEFAULT: Self = Self {
        failures_before_slowing: 3,
        delay_per_failure: Duration::from_millis(500),
        failures_before_refusing: 10,
        window: Duration::from_secs(300),
        addresses: 10_000,
    };
}

impl Default for LoginLimit {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// An address's wrong tokens within the window.
#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
}

/// The wrong tokens of each client address.
pub struct LoginAttempts {
    limit: LoginLimit,
    failures: Mutex<HashMap<IpAddr, Failures>>,
}

/// An address refused: how long until it may try again.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Refused {
    pub retry_after: Duration,
}

impl Refused {
    /// `Retry-After` in whole seconds, rounded up so that a retry then is let through.
    pub fn retry_after_seconds(&self) -> u64 {
        let whole = self.retry_after.as_secs();
        whole + u64::from(self.retry_after.subsec_nanos() > 0)
    }
}

/// The key `address` counts under: itself, or its /64 network for IPv6.
fn key(address: IpAddr) -> IpAddr {
    match address {
        IpAddr::V6(v6) => match v6.to_ipv4_mapped() {
            Some(v4) => IpAddr::V4(v4),
            None => {
                let network = u128::from(v6) & !((1u128 << 64) - 1);
                IpAddr::V6(Ipv6Addr::from(network))
            }
        },
        v4 => v4,
    }
}

impl LoginAttempts {
    pub fn new(limit: LoginLimit) -> Self {
        Self {
            limit,
            failures: Mutex::default(),
        }
    }

    fn failures(&self) -> std::sync::MutexGuard<'_, HashMap<IpAddr, Failures>> {
        self.failures
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Whether `address` may give a token at `now`.
    pub fn check(&self, address: IpAddr, now: Instant) -> Result<(), Refused> {
        let failures = self.failures();
        let Some(seen) = failures.get(&key(address)) else {
            return Ok(());
        };
        let until = seen.last + self.limit.window;
        if seen.count >= self.limit.failures_before_refusing && now < until {
            return Err(Refused {
                retry_after: until - now,
            });
        }
        Ok(())
    }

    /// Counts a wrong token from `address` at `now`; returns the address's wrong tokens in
    /// the window and how long to wait before answering this one.
    pub fn failed(&self, address: IpAddr, now: Instant) -> (u32, Duration) {
        let limit = self.limit;
        let mut failures = self.failures();
        let address = key(address);
        if !failures.contains_key(&address) && failures.len() >= limit.addresses {
            failures.retain(|_, seen| now.saturating_duration_since(seen.last) < limit.window);
            if failures.len() >= limit.addresses {
                let quietest = failures
                    .iter()
                    .min_by_key(|(_, seen)| seen.last)
                    .map(|(address, _)| *address);
                if let Some(quietest) = quietest {
                    failures.remove(&quietest);
                }
            }
        }
        let seen = failures.entry(address).or_insert(Failures {
            count: 0,
            last: now,
        });
        if now.saturating_duration_since(seen.last) >= limit.window {
            seen.count = 0;
        }
        seen.count = seen.count.saturating_add(1);
        seen.last = now;
        let beyond = seen.count.saturating_sub(limit.failures_before_slowing);
        (seen.count, limit.delay_per_failure.saturating_mul(beyond))
    }

    /// A right token from `address`: its failures are forgotten.
    pub fn succeeded(&self, address: IpAddr) {
        self.failures().remove(&key(address));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMIT: LoginLimit = LoginLimit {
        failures_before_slowing: 2,
        delay_per_failure: Duration::from_millis(100),
        failures_before_refusing: 4,
        window: Duration::from_secs(60),
        addresses: 3,
    };

    fn ip(text: &str) -> IpAddr {
        text.parse().expect("an address")
    }

    #[test]
    fn wrong_tokens_are_slowed_then_refused_until_the_window_passes() {
        let attempts = LoginAttempts::new(LIMIT);
        let (guesser, start) = (ip("192.0.2.7"), Instant::now());
        let delays: Vec<Duration> = (0..4)
            .map(|n| {
                let at = start + Duration::from_secs(n);
                assert_eq!(attempts.check(guesser, at), Ok(()), "try {n}");
                attempts.failed(guesser, at).1
            })
            .collect();
        let ms = |n| Duration::from_millis(n);
        assert_eq!(delays, [ms(0), ms(0), ms(100), ms(200)]);
        let last = start + Duration::from_secs(3);
        let refused = attempts
            .check(guesser, last + Duration::from_millis(500))
            .expect_err("refused");
        assert_eq!(refused.retry_after, Duration::from_millis(59_500));
        assert_eq!(refused.retry_after_seconds(), 60);
        assert_eq!(attempts.check(ip("192.0.2.8"), last), Ok(()), "another");
        assert_eq!(attempts.check(guesser, last + LIMIT.window), Ok(()));
        assert_eq!(
            attempts.failed(guesser, last + LIMIT.window),
            (1, Duration::ZERO),
            "failures a window apart are forgotten"
        );
    }

    #[test]
    fn a_right_token_forgets_the_failures() {
        let attempts = LoginAttempts::new(LIMIT);
        let (client, now) = (ip("192.0.2.7"), Instant::now());
        for _ in 0..3 {
            attempts.failed(client, now);
        }
        attempts.succeeded(client);
        assert_eq!(attempts.failed(client, now), (1, Duration::ZERO));
    }

    #[test]
    fn ipv6_counts_by_network_and_the_addresses_followed_are_bounded() {
        let attempts = LoginAttempts::new(LIMIT);
        let now = Instant::now();
        for n in 0..4 {
            attempts.failed(ip(&format!("2001:db8::{n}")), now);
        }
        assert!(attempts.check(ip("2001:db8::99"), now).is_err());
        assert_eq!(attempts.check(ip("2001:db8:0:1::1"), now), Ok(()));
        assert_eq!(key(ip("::ffff:192.0.2.7")), ip("192.0.2.7"));
        for n in 0..10 {
            let at = now + Duration::from_millis(n);
            attempts.failed(ip(&format!("198.51.100.{n}")), at);
        }
        assert!(attempts.failures().len() <= LIMIT.addresses);
    }
}
