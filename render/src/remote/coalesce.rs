//! Merging nearby byte ranges into fewer requests, and cutting the answers back apart.

use std::ops::Range;

/// Merges ranges whose gap is at most `gap` bytes, as long as a merged range stays within
/// `max_merged` bytes; the result is sorted and covers every input range.
pub(crate) fn coalesce(ranges: &[Range<u64>], gap: u64, max_merged: u64) -> Vec<Range<u64>> {
    let mut sorted: Vec<Range<u64>> = ranges.iter().filter(|r| r.start < r.end).cloned().collect();
    sorted.sort_by_key(|range| (range.start, range.end));
    let mut merged: Vec<Range<u64>> = Vec::with_capacity(sorted.len());
    for range in sorted {
        if let Some(last) = merged.last_mut() {
            let end = last.end.max(range.end);
            if range.start <= last.end.saturating_add(gap) && end - last.start <= max_merged {
                last.end = end;
                continue;
            }
        }
        merged.push(range);
    }
    merged
}

/// Where `range` lies within the merged range that covers it, as offsets into its bytes.
pub(crate) fn locate(merged: &[Range<u64>], range: &Range<u64>) -> Option<(usize, Range<usize>)> {
    let index = merged.partition_point(|candidate| candidate.end < range.end);
    let covering = merged.get(index)?;
    if covering.start > range.start || covering.end < range.end {
        return None;
    }
    let start = usize::try_from(range.start - covering.start).ok()?;
    let end = usize::try_from(range.end - covering.start).ok()?;
    Some((index, start..end))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merges_near_ranges_only() {
        let merged = coalesce(&[100..200, 0..10, 15..20, 5000..5001, 195..300], 10, 1000);
        assert_eq!(merged, vec![0..20, 100..300, 5000..5001]);
    }

    #[test]
    fn stops_growing_at_the_bound() {
        let merged = coalesce(&[0..600, 600..1200], 0, 1000);
        assert_eq!(merged, vec![0..600, 600..1200]);
    }

    #[test]
    fn locates_every_input() {
        let ranges = [100..200, 0..10, 15..20, 195..300, 150..160];
        let merged = coalesce(&ranges, 10, 1000);
        for range in &ranges {
            let (index, within) = locate(&merged, range).expect("covered");
            let covering = &merged[index];
            assert_eq!(covering.start + within.start as u64, range.start);
            assert_eq!(covering.start + within.end as u64, range.end);
        }
    }
}
