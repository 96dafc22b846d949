//! The sampling rule of inner nodes: a node takes, from its children's own points, the one
//! point closest to the centre of each cell of a grid over its cube (Scheiblauer's choice of
//! representative); the children keep the rest. The grid starts at the configured cells per
//! axis and is halved while the sample would hold more than the node bound, so inner nodes are
//! even and bounded on surfaces and volumes alike.
//!
//! Ties in distance are broken by the points' content, so the choice never depends on the
//! order points arrived in.

use glam::{DVec3, UVec3};

use super::key::{NodeKey, RootCube};
use super::point::RawPoint;

/// A node's sample and what its children keep.
pub struct Sampled {
    pub parent: Vec<RawPoint>,
    pub kept: [Vec<RawPoint>; 8],
    /// Cells per axis of the grid that was used.
    pub grid: u32,
}

/// The sampling cell of `p` in `key`'s grid of `2^grid_bits` cells per axis.
pub fn sampling_cell(cube: &RootCube, key: NodeKey, grid_bits: u32, p: DVec3) -> UVec3 {
    cube.cell_at(p, u32::from(key.level) + grid_bits) - (key.cell() << grid_bits)
}

/// Bytes per candidate point a dense cell table may take (it replaces the sort when the
/// grid's cells are few for the points): within the builder's per-point reservation.
const DENSE_BYTES_PER_POINT: usize = 32;

/// Samples `key` from its children's own points with at most `max_points` points.
pub fn sample(
    cube: &RootCube,
    key: NodeKey,
    children: [Vec<RawPoint>; 8],
    grid: u32,
    max_points: usize,
) -> Sampled {
    let choice = choose(cube, key, &children, grid, max_points);
    let Choice {
        bits,
        chosen,
        cells,
        owner,
    } = choice;
    let mut children = children;
    if bits >= 2 {
        for c in 0..8 {
            weigh_child(c, bits, &mut children[c], &chosen[c], &cells[c], &owner[c]);
        }
    } else {
        weigh(cube, key, bits, &mut children, &chosen);
    }
    drop((cells, owner));
    // Each child keeps its points where they are, the taken ones moved out to the parent:
    // no second vector a child, and the kept points in the order they came.
    let taken: usize = chosen.iter().flatten().filter(|&&take| take).count();
    let mut parent = Vec::with_capacity(taken);
    for (points, chosen) in children.iter_mut().zip(&chosen) {
        let mut chosen = chosen.iter();
        points.retain(|p| {
            let take = chosen.next().is_some_and(|&take| take);
            if take {
                parent.push(*p);
            }
            !take
        });
    }
    Sampled {
        parent,
        kept: children,
        grid: 1 << bits,
    }
}

/// Which points a node takes, before their weights are set.
struct Choice {
    /// Cells per axis of the grid used, as a power of two.
    bits: u32,
    chosen: [Vec<bool>; 8],
    /// Each point's cell in that grid.
    cells: [Vec<UVec3>; 8],
    /// For each point, the index (in its child) of the point taken in its cell; meaningful
    /// when the grid has two or more cells per axis.
    owner: [Vec<u32>; 8],
}

/// The sampling choice of [`sample`]: the finest grid whose sample holds at most `max_points`.
fn choose(
    cube: &RootCube,
    key: NodeKey,
    children: &[Vec<RawPoint>; 8],
    grid: u32,
    max_points: usize,
) -> Choice {
    let finest = grid.trailing_zeros();
    // Each point's cell in the finest grid, computed once: a coarser grid's cell is a shift of
    // it, since `RootCube::cell_at` scales by powers of two, which is exact.
    let cells: [Vec<UVec3>; 8] = std::array::from_fn(|c| {
        children[c]
            .iter()
            .map(|p| sampling_cell(cube, key, finest, p.position))
            .collect()
    });
    let mut bits = finest;
    let mut keyed: Vec<u64> = Vec::new();
    let mut scratch: Vec<u64> = Vec::new();
    let mut dense: Vec<u32> = Vec::new();
    let mut chosen: [Vec<bool>; 8] = std::array::from_fn(|c| vec![false; children[c].len()]);
    let mut owner: [Vec<u32>; 8] = std::array::from_fn(|c| vec![0; children[c].len()]);
    loop {
        let shift = finest - bits;
        let cell_side = cube.side_at(key.level) / f64::from(1u32 << bits);
        let corner = cube.node_min(key);
        let distance = |p: &RawPoint, cell: UVec3| {
            p.position
                .distance_squared(corner + (cell.as_dvec3() + 0.5) * cell_side)
        };
        // Whether `p` (at squared distance `d`) beats the point now holding its cell.
        let beats = |p: &RawPoint, d: f64, held: &RawPoint, held_d: f64| {
            d < held_d || (d == held_d && p.content_cmp(held).is_lt())
        };
        let mut taken = 0;
        if bits == 0 {
            // One cell holds the whole node: the point nearest its centre.
            let mut best: Option<(usize, usize, f64)> = None;
            for (c, points) in children.iter().enumerate() {
                for (i, p) in points.iter().enumerate() {
                    let d = distance(p, UVec3::ZERO);
                    let better = best.is_none_or(|(bc, bi, bd)| beats(p, d, &children[bc][bi], bd));
                    if better {
                        best = Some((c, i, d));
                    }
                }
            }
            if let Some((c, i, _)) = best {
                chosen[c][i] = true;
                taken = 1;
            }
        } else {
            // With two or more cells per axis no cell spans two children, so each child is
            // sampled on its own, on the cells of its octant.
            let local_bits = bits - 1;
            let cell_count = 1usize << (3 * local_bits);
            for (c, points) in children.iter().enumerate() {
                let offset = NodeKey::ROOT.child(c).cell() << local_bits;
                let child_cells = &cells[c];
                let local = |i: usize| {
                    let cell = child_cells[i] >> shift;
                    let l = cell - offset;
                    (
                        cell,
                        (l.x | (l.y << local_bits) | (l.z << (2 * local_bits))) as usize,
                    )
                };
                let owners = &mut owner[c];
                if cell_count <= points.len() * DENSE_BYTES_PER_POINT / 4 {
                    dense.clear();
                    dense.resize(cell_count, u32::MAX);
                    for (i, p) in points.iter().enumerate() {
                        let (cell, index) = local(i);
                        let held = dense[index];
                        let better = held == u32::MAX || {
                            let h = &points[held as usize];
                            beats(p, distance(p, cell), h, distance(h, cell))
                        };
                        if better {
                            dense[index] = i as u32;
                        }
                    }
                    for (i, o) in owners.iter_mut().enumerate() {
                        *o = dense[local(i).1];
                    }
                    for &i in dense.iter().filter(|&&i| i != u32::MAX) {
                        chosen[c][i as usize] = true;
                        taken += 1;
                    }
                } else {
                    // Few points for many cells: sorted by cell (cache-friendly, unlike a map),
                    // points of a cell in the order they are, then the best of each run of one
                    // cell.
                    keyed.clear();
                    keyed.extend((0..points.len()).map(|i| ((local(i).1 as u64) << 32) | i as u64));
                    sort_by_cell(&mut keyed, &mut scratch, 3 * local_bits);
                    for run in keyed.chunk_by(|a, b| a >> 32 == b >> 32) {
                        let first = run[0] as u32 as usize;
                        let (cell, _) = local(first);
                        let mut best = first;
                        let mut best_d = distance(&points[first], cell);
                        for &k in &run[1..] {
                            let i = k as u32 as usize;
                            let d = distance(&points[i], cell);
                            if beats(&points[i], d, &points[best], best_d) {
                                best = i;
                                best_d = d;
                            }
                        }
                        for &k in run {
                            owners[k as u32 as usize] = best as u32;
                        }
                        chosen[c][best] = true;
                        taken += 1;
                    }
                }
            }
        }
        if taken <= max_points || bits == 0 {
            break;
        }
        chosen.iter_mut().for_each(|c| c.fill(false));
        bits -= 1;
    }
    let shift = finest - bits;
    let mut cells = cells;
    if shift > 0 {
        for cell in cells.iter_mut().flatten() {
            *cell >>= shift;
        }
    }
    Choice {
        bits,
        chosen,
        cells,
        owner,
    }
}

/// Sorts `keyed` (a cell of `cell_bits` bits above a point's index, indices ascending) by
/// cell, the points of a cell in the order they are: the comparison sort's order, by a radix
/// sort of two passes over the cell's bits, `scratch` reused from child to child.
fn sort_by_cell(keyed: &mut Vec<u64>, scratch: &mut Vec<u64>, cell_bits: u32) {
    const SMALL: usize = 256;
    if keyed.len() < SMALL || cell_bits == 0 {
        keyed.sort_unstable();
        return;
    }
    let digit_bits = cell_bits.div_ceil(2);
    let mask = (1u64 << digit_bits) - 1;
    let mut counts = vec![0usize; 2 << digit_bits];
    let (low, high) = counts.split_at_mut(1 << digit_bits);
    let digit = |k: u64, pass: u32| ((k >> (32 + pass * digit_bits)) & mask) as usize;
    for &k in keyed.iter() {
        low[digit(k, 0)] += 1;
        high[digit(k, 1)] += 1;
    }
    scratch.clear();
    scratch.resize(keyed.len(), 0);
    for (pass, table) in [low, high].into_iter().enumerate() {
        let mut start = 0;
        for count in table.iter_mut() {
            let c = *count;
            *count = start;
            start += c;
        }
        for &k in keyed.iter() {
            let at = &mut table[digit(k, pass as u32)];
            scratch[*at] = k;
            *at += 1;
        }
        std::mem::swap(keyed, scratch);
    }
}

/// [`weigh`] for one child of a grid of four or more cells per axis, where a cell lies within
/// one grandchild octant, so a taken point's heir is in its own cell unless the cell held it
/// alone: the same weights without hashing (a test compares the two). `cells` are the
/// points' cells in the node's grid of `bits` per axis; `owner` the chosen point of each one's.
fn weigh_child(
    child: usize,
    bits: u32,
    points: &mut [RawPoint],
    chosen: &[bool],
    cells: &[UVec3],
    owner: &[u32],
) {
    debug_assert!(bits >= 2);
    const NONE: u32 = u32::MAX;
    let n = points.len();
    let mut sums = vec![0u64; n];
    for (p, &o) in points.iter().zip(owner) {
        sums[o as usize] += u64::from(p.weight);
    }
    // The nearest remaining point of each taken one's cell, ties broken by content.
    let mut heirs: Vec<(u32, f64)> = vec![(NONE, 0.0); n];
    for (i, p) in points.iter().enumerate() {
        let o = owner[i] as usize;
        if chosen[i] || points[o].weight <= 1 {
            continue;
        }
        let d = p.position.distance_squared(points[o].position);
        let (h, hd) = heirs[o];
        if h == NONE || d < hd || (d == hd && p.content_cmp(&points[h as usize]).is_lt()) {
            heirs[o] = (i as u32, d);
        }
    }
    let lacking: Vec<usize> = (0..n)
        .filter(|&o| chosen[o] && points[o].weight > 1 && heirs[o].0 == NONE)
        .collect();
    if !lacking.is_empty() {
        // A cell that held only its taken point: the remaining point of the same grandchild
        // octant nearest along the Morton order of the cells.
        let base = NodeKey::ROOT.child(child).cell() * 2;
        let grandchild = |cell: UVec3| {
            let g = (cell >> (bits - 2)) - base;
            (g.x | (g.y << 1) | (g.z << 2)) as usize
        };
        let mut groups: [Vec<(u32, usize)>; 8] = Default::default();
        for i in (0..n).filter(|&i| !chosen[i]) {
            groups[grandchild(cells[i])].push((morton(cells[i]), i));
        }
        groups.iter_mut().for_each(|g| g.sort_unstable());
        for o in lacking {
            let group = &groups[grandchild(cells[o])];
            let code = morton(cells[o]);
            let k = group.partition_point(|&(m, _)| m < code);
            let near = [k.checked_sub(1), (k < group.len()).then_some(k)];
            let p = &points[o];
            let best = near.into_iter().flatten().min_by(|&a, &b| {
                let (pa, pb) = (&points[group[a].1], &points[group[b].1]);
                let (da, db) = (
                    pa.position.distance_squared(p.position),
                    pb.position.distance_squared(p.position),
                );
                da.total_cmp(&db).then(pa.content_cmp(pb))
            });
            if let Some(b) = best {
                heirs[o] = (group[b].1 as u32, 0.0);
            }
        }
    }
    for o in 0..n {
        let (heir, _) = heirs[o];
        if heir != NONE {
            let extra = points[o].weight - 1;
            let p = &mut points[heir as usize];
            p.weight = p.weight.saturating_add(extra);
        }
    }
    for (o, p) in points.iter_mut().enumerate() {
        if chosen[o] {
            p.weight = sums[o].min(u64::from(u32::MAX)) as u32;
        }
    }
}

/// Where a sampled point's weight is summed (its cell of `key`'s grid, `bits` per axis) and
/// where its child's weight may go when its cell's point is taken (that cell within the same
/// octant of the child, so that the weight counts exactly where the grandchild is not drawn).
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct WeighCell {
    cell: UVec3,
    child: u8,
    grandchild: u8,
}

/// Sets the weights of `key`'s sample (`chosen` of `children`) on a grid of any size (the
/// sampler uses it for one or two cells per axis, [`weigh_child`] otherwise): each chosen point stands for
/// the children's weights in its cell, and what it stood for in its child beyond itself goes
/// to the child's nearest remaining point in the same cell and grandchild octant, so that a
/// cut that draws the child but not that grandchild still counts every original point once
/// (`docs/perf/hq-band-on-cuts.md`). Runs after the choice: it never changes which points
/// are chosen.
fn weigh(
    cube: &RootCube,
    key: NodeKey,
    bits: u32,
    children: &mut [Vec<RawPoint>; 8],
    chosen: &[Vec<bool>; 8],
) {
    use std::collections::HashMap;
    let child_level = u32::from(key.level) + 1;
    let place = |c: usize, p: &RawPoint| {
        let grandchild = cube.cell_at(p.position, child_level + 1) - key.child(c).cell() * 2;
        WeighCell {
            cell: sampling_cell(cube, key, bits, p.position),
            child: c as u8,
            grandchild: (grandchild.x | (grandchild.y << 1) | (grandchild.z << 2)) as u8,
        }
    };
    // A cell's weight sum, and its chosen point (child, index).
    let mut cells: HashMap<UVec3, (u64, Option<(usize, usize)>)> = HashMap::new();
    for (c, points) in children.iter().enumerate() {
        for (i, p) in points.iter().enumerate() {
            let entry = cells
                .entry(sampling_cell(cube, key, bits, p.position))
                .or_default();
            entry.0 += u64::from(p.weight);
            if chosen[c][i] {
                entry.1 = Some((c, i));
            }
        }
    }
    // Each chosen point's weight in its child beyond itself, by where it may go.
    let mut orphans: HashMap<WeighCell, (usize, usize)> = HashMap::new();
    for (c, points) in children.iter().enumerate() {
        for (i, p) in points.iter().enumerate() {
            if chosen[c][i] && p.weight > 1 {
                orphans.insert(place(c, p), (c, i));
            }
        }
    }
    // The nearest remaining point to each taken one, ties broken by content.
    let mut heirs: HashMap<(usize, usize), (usize, f64)> = HashMap::new();
    if !orphans.is_empty() {
        for (c, points) in children.iter().enumerate() {
            for (i, p) in points.iter().enumerate() {
                if chosen[c][i] {
                    continue;
                }
                let Some(&(oc, oi)) = orphans.get(&place(c, p)) else {
                    continue;
                };
                let d = p.position.distance_squared(children[oc][oi].position);
                let better = heirs.get(&(oc, oi)).is_none_or(|&(h, hd)| {
                    d < hd || (d == hd && p.content_cmp(&points[h]).is_lt())
                });
                if better {
                    heirs.insert((oc, oi), (i, d));
                }
            }
        }
    }
    // A taken point whose cell has no other point of its grandchild octant: the remaining
    // point of that octant nearest along the Morton order of the cells (rare, so cheap).
    let lacking: Vec<(usize, usize)> = orphans
        .values()
        .copied()
        .filter(|o| !heirs.contains_key(o))
        .collect();
    if !lacking.is_empty() {
        let mut groups: HashMap<(u8, u8), Vec<(u32, usize)>> = HashMap::new();
        for (c, points) in children.iter().enumerate() {
            for (i, p) in points.iter().enumerate() {
                if !chosen[c][i] {
                    let at = place(c, p);
                    groups
                        .entry((at.child, at.grandchild))
                        .or_default()
                        .push((morton(at.cell), i));
                }
            }
        }
        groups.values_mut().for_each(|g| g.sort_unstable());
        for (oc, oi) in lacking {
            let p = &children[oc][oi];
            let at = place(oc, p);
            let Some(group) = groups.get(&(at.child, at.grandchild)) else {
                continue;
            };
            let code = morton(at.cell);
            let k = group.partition_point(|&(m, _)| m < code);
            let near = [k.checked_sub(1), (k < group.len()).then_some(k)];
            let best = near.into_iter().flatten().min_by(|&a, &b| {
                let (pa, pb) = (&children[oc][group[a].1], &children[oc][group[b].1]);
                let (da, db) = (
                    pa.position.distance_squared(p.position),
                    pb.position.distance_squared(p.position),
                );
                da.total_cmp(&db).then(pa.content_cmp(pb))
            });
            if let Some(b) = best {
                heirs.insert((oc, oi), (group[b].1, 0.0));
            }
        }
    }
    for ((oc, oi), (heir, _)) in heirs {
        let extra = children[oc][oi].weight - 1;
        let p = &mut children[oc][heir];
        p.weight = p.weight.saturating_add(extra);
    }
    for (sum, taken) in cells.into_values() {
        if let Some((c, i)) = taken {
            children[c][i].weight = sum.min(u64::from(u32::MAX)) as u32;
        }
    }
}

/// The Morton code of a cell of a grid of at most 2^10 cells per axis.
fn morton(cell: UVec3) -> u32 {
    let spread = |v: u32| {
        let mut v = v & 0x3ff;
        v = (v | (v << 16)) & 0x0300_00ff;
        v = (v | (v << 8)) & 0x0300_f00f;
        v = (v | (v << 4)) & 0x030c_30c3;
        (v | (v << 2)) & 0x0924_9249
    };
    spread(cell.x) | (spread(cell.y) << 1) | (spread(cell.z) << 2)
}

#[cfg(test)]
pub(crate) mod tests {
    use std::collections::HashMap;

    use super::*;

    /// `points` of `key` by child.
    fn split(cube: &RootCube, key: NodeKey, points: &[RawPoint]) -> [Vec<RawPoint>; 8] {
        let mut children: [Vec<RawPoint>; 8] = Default::default();
        for p in points {
            let c = cube.cell_at(p.position, u32::from(key.level) + 1) - key.cell() * 2;
            children[(c.x | (c.y << 1) | (c.z << 2)) as usize].push(*p);
        }
        children
    }

    /// A repeatable sequence of numbers in [0, 1) (a linear congruential generator).
    pub(crate) fn unit_random(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            (state >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The per-child weighing gives the general one's weights on grids of four to 128 cells per
    /// axis, with points that already stand for others (as in upper levels), crowded cells and
    /// cells holding one point alone, and a grid halved to keep the sample small.
    #[test]
    fn per_child_weights_equal_the_general_ones() {
        let cube = RootCube {
            min: DVec3::new(-50.0, 10.0, 7.0),
            side: 256.0,
        };
        let key = NodeKey::new(2, UVec3::new(3, 1, 2));
        let (min, side) = (cube.node_min(key), cube.side_at(2));
        let mut next = unit_random(777);
        let mut points = Vec::new();
        for i in 0..6000u32 {
            // Half spread through the node, half crowded into a corner of it.
            let spread = if i % 2 == 0 { 1.0 } else { 0.1 };
            points.push(RawPoint {
                position: min + DVec3::new(next(), next(), next()) * side * spread,
                rgb: [i as u16; 3],
                intensity: i as u16,
                classification: 0,
                return_number: 0,
                weight: 1 + (next() * 4.0) as u32,
                row: 0,
            });
        }
        for (grid, max_points) in [
            (4, usize::MAX),
            (8, usize::MAX),
            (32, usize::MAX),
            (128, usize::MAX),
            (128, 400),
        ] {
            let children = split(&cube, key, &points);
            let choice = choose(&cube, key, &children, grid, max_points);
            assert!(choice.bits >= 2, "grid {grid}");
            let mut general = children.clone();
            weigh(&cube, key, choice.bits, &mut general, &choice.chosen);
            let mut per_child = children.clone();
            for (c, points) in per_child.iter_mut().enumerate() {
                weigh_child(
                    c,
                    choice.bits,
                    points,
                    &choice.chosen[c],
                    &choice.cells[c],
                    &choice.owner[c],
                );
            }
            assert_ne!(general, children, "grid {grid}: no weight moved");
            assert_eq!(per_child, general, "grid {grid}");
        }
    }

    /// The radix sort by cell gives the comparison sort's order, cells of 3 to 18 bits.
    #[test]
    fn the_sort_by_cell_is_the_comparison_sort() {
        let mut next = unit_random(4242);
        let mut scratch = Vec::new();
        for (cell_bits, n) in [(3, 300), (9, 5_000), (18, 20_000), (18, 100)] {
            let keyed: Vec<u64> = (0..n)
                .map(|i| ((next() * f64::from(1u32 << cell_bits)) as u64) << 32 | i as u64)
                .collect();
            let mut radix = keyed.clone();
            sort_by_cell(&mut radix, &mut scratch, cell_bits);
            let mut expected = keyed;
            expected.sort_unstable();
            assert_eq!(radix, expected, "{cell_bits} bits");
        }
    }

    /// Brute force: in every cell the chosen point is the one nearest the cell's centre, and
    /// every occupied cell has one, on both the dense table (grid 8) and the sorted runs (grid 128).
    #[test]
    fn each_cell_gives_its_point_nearest_the_centre() {
        let cube = RootCube {
            min: DVec3::new(100.0, 200.0, 300.0),
            side: 64.0,
        };
        let key = NodeKey::new(1, UVec3::new(1, 0, 1));
        let (min, side) = (cube.node_min(key), cube.side_at(1));
        let mut next = unit_random(12345);
        let points: Vec<RawPoint> = (0..3000)
            .map(|i| RawPoint {
                position: min + DVec3::new(next(), next(), next()) * side,
                rgb: [0; 3],
                intensity: i,
                classification: 0,
                return_number: 0,
                weight: 1,
                row: 0,
            })
            .collect();
        for grid in [8u32, 128] {
            let bits = grid.trailing_zeros();
            let children = split(&cube, key, &points);
            let sampled = sample(&cube, key, children, grid, usize::MAX);
            assert_eq!(sampled.grid, grid);
            let kept: usize = sampled.kept.iter().map(Vec::len).sum();
            assert_eq!(sampled.parent.len() + kept, points.len());
            let cell_side = side / f64::from(grid);
            let mut nearest: HashMap<UVec3, (f64, u16)> = HashMap::new();
            for p in &points {
                let cell = sampling_cell(&cube, key, bits, p.position);
                let d = p
                    .position
                    .distance_squared(min + (cell.as_dvec3() + 0.5) * cell_side);
                let e = nearest.entry(cell).or_insert((d, p.intensity));
                if d < e.0 {
                    *e = (d, p.intensity);
                }
            }
            let mut chosen: Vec<u16> = sampled.parent.iter().map(|p| p.intensity).collect();
            let mut expected: Vec<u16> = nearest.values().map(|&(_, i)| i).collect();
            chosen.sort_unstable();
            expected.sort_unstable();
            assert_eq!(chosen, expected, "grid {grid}");
        }
    }
}
