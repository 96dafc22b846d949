//! Buffers a partition's build reuses from one partition to the next: the points read from its
//! files, their attribute rows, their Z-curve order with its sort's second buffer, and each
//! point's run. Allocated afresh, a partition of a million points takes a hundred MB and more
//! of fresh pages from the kernel (the allocator maps blocks this large and unmaps them when
//! they are freed), each faulted in and zeroed again (docs/perf/lod-build-memory-churn.md).
//!
//! The budget bounds them like any buffer: a scratch in use is held under its partition's
//! reservation, grown by what the scratch keeps beyond the rows and order the partition reserves
//! anyway, and a scratch idle between partitions keeps a reservation of exactly what it holds.
//! Idle scratches are dropped whenever a unit needs their memory.

use std::sync::{Mutex, MutexGuard};

use super::memory::Reservation;
use super::morton::OrderBuffers;
use super::point::RawPoint;

/// The buffers of one partition's build.
#[derive(Default)]
pub struct PartitionScratch {
    pub points: Vec<RawPoint>,
    pub rows: Vec<u8>,
    pub order: OrderBuffers,
    pub run_of: Vec<u32>,
}

/// Bytes of the room of `v`.
fn room<T>(v: &Vec<T>) -> u64 {
    (v.capacity() * std::mem::size_of::<T>()) as u64
}

/// Bytes of `count` values of `T`.
fn bytes_of<T>(count: u64) -> u64 {
    count * std::mem::size_of::<T>() as u64
}

/// The smallest buffer of a partition's points worth keeping: glibc's largest threshold for
/// mapping a block afresh (`DEFAULT_MMAP_THRESHOLD_MAX` on 64-bit hosts). Smaller blocks come
/// from its arenas, which keep freed ones for the next partition, so a scratch would only hold
/// memory the allocator already reuses (on 16 threads, partitions of 80,000 points took more
/// page faults with scratches than without). The crate's own tests keep every partition's, so
/// that their checks of the store and the budget cover that path too.
const KEPT_MIN_POINT_BYTES: u64 = if cfg!(test) { 1 } else { 32 << 20 };

impl PartitionScratch {
    /// Whether a partition of `count` points is built in a scratch kept for the next one.
    pub fn worth_keeping(count: u64) -> bool {
        bytes_of::<RawPoint>(count) >= KEPT_MIN_POINT_BYTES
    }

    /// Bytes its buffers hold room for.
    pub fn held_bytes(&self) -> u64 {
        room(&self.points)
            + room(&self.rows)
            + room(&self.order.entries)
            + room(&self.order.sorted)
            + room(&self.run_of)
    }

    /// Bytes it holds once its buffers have room for a partition of `count` points with
    /// attribute rows of `row_bytes`: none shrinks.
    fn grown_bytes(&self, count: u64, row_bytes: usize) -> u64 {
        let order_bytes = bytes_of::<(u64, u32)>(count);
        room(&self.points).max(bytes_of::<RawPoint>(count))
            + room(&self.rows).max(count * row_bytes as u64)
            + room(&self.order.entries).max(order_bytes)
            + room(&self.order.sorted).max(order_bytes)
            + room(&self.run_of).max(bytes_of::<u32>(count))
    }

    /// What a partition of `count` points reserves beyond its own bytes to be built in this
    /// scratch: all it holds but the rows and the order's entries, which the partition's own
    /// reservation counts for as long as it is built. A build without a scratch frees the
    /// points read, the sort's second buffer and the runs' indices once the points are in their
    /// runs; a scratch keeps them for the next partition.
    pub fn extra_bytes(&self, count: u64, row_bytes: usize) -> u64 {
        let counted = count * row_bytes as u64 + bytes_of::<(u64, u32)>(count);
        self.grown_bytes(count, row_bytes).saturating_sub(counted)
    }

    /// The rows' buffer, emptied, with room for `count` rows of `row_bytes` (exactly, where it
    /// grows, as [`Self::extra_bytes`] counted).
    pub fn take_rows(&mut self, count: usize, row_bytes: usize) -> Vec<u8> {
        let mut rows = std::mem::take(&mut self.rows);
        rows.clear();
        rows.reserve_exact(count * row_bytes);
        rows
    }
}

/// Scratches idle between partitions, each with a reservation of what it holds.
pub struct ScratchPool<'m> {
    idle: Mutex<Vec<(PartitionScratch, Reservation<'m>)>>,
}

impl<'m> ScratchPool<'m> {
    pub fn new() -> Self {
        Self {
            idle: Mutex::new(Vec::new()),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Vec<(PartitionScratch, Reservation<'m>)>> {
        self.idle
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// An idle scratch with its reservation: the one holding the most (partitions are built
    /// largest first, so it is likely to need no more room).
    pub fn take(&self) -> Option<(PartitionScratch, Reservation<'m>)> {
        let mut idle = self.lock();
        let most = (0..idle.len()).max_by_key(|&i| idle[i].0.held_bytes())?;
        Some(idle.swap_remove(most))
    }

    /// Keeps `scratch` for another partition, `reservation` shrunk to what it holds; one that
    /// holds more than its reservation is dropped.
    pub fn put(&self, scratch: PartitionScratch, mut reservation: Reservation<'m>) {
        let held = scratch.held_bytes();
        if held > reservation.bytes() {
            return;
        }
        reservation.shrink_to(held);
        self.lock().push((scratch, reservation));
    }

    /// Drops every idle scratch, releasing its memory; whether there was one.
    pub fn release_idle(&self) -> bool {
        let idle = std::mem::take(&mut *self.lock());
        !idle.is_empty()
    }

    /// Bytes the idle scratches hold.
    #[cfg(test)]
    pub fn idle_bytes(&self) -> u64 {
        self.lock().iter().map(|(_, r)| r.bytes()).sum()
    }
}

impl Default for ScratchPool<'_> {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lod::memory::MemoryMeter;

    /// A scratch grown for a partition and pooled holds a reservation of exactly its room, within
    /// what the partition reserved; released, the meter gets it back.
    #[test]
    fn an_idle_scratch_holds_a_reservation_of_its_room() {
        let meter = MemoryMeter::new(1 << 30);
        let pool = ScratchPool::new();
        let count = 10_000u64;
        let row_bytes = 16;
        let mut scratch = PartitionScratch::default();
        let own = 200 * count;
        let extra = scratch.extra_bytes(count, row_bytes);
        let mut reservation = meter.try_reserve(own, "partition").expect("fits");
        reservation.absorb(meter.try_reserve(extra, "scratch").expect("fits"));
        // Grown as a build grows them.
        let n = count as usize;
        scratch.points.reserve_exact(n);
        let rows = scratch.take_rows(n, row_bytes);
        scratch.rows = rows;
        scratch.order.entries.reserve_exact(n);
        scratch.order.sorted.reserve_exact(n);
        scratch.run_of.reserve_exact(n);
        let held = scratch.held_bytes();
        assert!(held <= own + extra);
        assert_eq!(held, extra + count * (row_bytes as u64 + 16));
        pool.put(scratch, reservation);
        assert_eq!(pool.idle_bytes(), held);
        let rest = meter
            .try_reserve((1 << 30) - held, "rest")
            .expect("the rest fits");
        assert!(
            meter.try_reserve(1, "more").is_err(),
            "the idle room is held"
        );
        drop(rest);
        // Taken again for a partition no larger, it needs nothing beyond its room.
        let (scratch, reservation) = pool.take().expect("idle");
        assert_eq!(reservation.bytes(), held);
        assert_eq!(
            scratch.extra_bytes(count, row_bytes),
            held - count * (row_bytes as u64 + 16)
        );
        pool.put(scratch, reservation);
        assert!(pool.release_idle());
        assert!(!pool.release_idle());
        let all = meter
            .try_reserve(1 << 30, "all")
            .expect("every byte released");
        assert_eq!(all.bytes(), 1 << 30);
    }

    /// A scratch that holds more than its reservation is not kept.
    #[test]
    fn a_scratch_beyond_its_reservation_is_dropped() {
        let meter = MemoryMeter::new(1 << 20);
        let pool = ScratchPool::new();
        let mut scratch = PartitionScratch::default();
        scratch.run_of.reserve_exact(1000);
        let reservation = meter.try_reserve(100, "too little").expect("fits");
        pool.put(scratch, reservation);
        assert_eq!(pool.idle_bytes(), 0);
        assert!(pool.take().is_none());
        assert!(meter.try_reserve(1 << 20, "all").is_ok());
    }
}
