//! Which points of the other set each E-step workgroup visits (`glsl/include/cpd.glsl`).
//!
//! A term exp(-d^2 / (2 s2)) of a denominator (which also holds the outlier term c) is
//! negligible once it is below 2^-24 c / max(M, N): all such terms of one denominator
//! together are below 2^-24 of it, float32's rounding. So the E-step needs only the pairs
//! closer than the cutoff r with exp(-r^2 / (2 s2)) = 2^-24 c / max(M, N). The sums of
//! the second pass lose as little in absolute terms: P1 of a source point at most 2^-24
//! in all (a point with no target near reads 0 instead of about 1e-8), the pull at most
//! 2^-24 r and the spread 2^-24 r^2. Both sets are sorted into cells
//! of width at least r (Morton order, so that consecutive points are near each other); a
//! workgroup's ROWS x 64 consecutive own points then visit the other points of the cells
//! next to theirs, as a few ranges of the other set's sorted order. While the sets span
//! fewer than [`MIN_CELLS`] cells along every axis (sigma large, early iterations) every
//! workgroup visits the whole other set, in order, as before.
//!
//! Every visited pair is computed exactly; only negligible pairs are left out. The
//! order of the ranges is fixed by the sort, so the sums are the same on every run.

use glam::DVec3;

/// Own points one workgroup serves (`ROWS` x 64).
pub const POINTS_PER_GROUP: usize = 8 * 64;
/// Fewer cells than this along every axis: no grid, the whole other set.
pub const MIN_CELLS: u32 = 4;
/// Cells along one axis at most (10 bits of a 30-bit Morton key).
const MAX_CELLS: u32 = 1024;
/// The loop cost of a range beyond its points (subgroup padding and loop set-up), in
/// points, when ranges are cut into pieces of at most `span`.
const RANGE_COST: u32 = 16;

/// The distance past which a term is negligible (module docs), for sigma^2, log c and
/// the larger set's size; infinite where nothing is.
pub fn cutoff(sigma2: f64, log_c: f64, points: usize) -> f64 {
    let exponent = (points.max(1) as f64).ln() + 24.0 * std::f64::consts::LN_2 - log_c;
    let r = (2.0 * sigma2 * exponent).sqrt();
    if r.is_finite() && r > 0.0 {
        r
    } else {
        f64::INFINITY
    }
}

/// A grid of cubic cells over both sets.
#[derive(Clone, Debug)]
pub struct Grid {
    lo: DVec3,
    width: f64,
    cells: [u32; 3],
}

impl Grid {
    /// Cells at least `width` wide over `points`, or `None` when they would span fewer
    /// than [`MIN_CELLS`] cells along every axis.
    pub fn new<'a>(points: impl Iterator<Item = &'a DVec3> + Clone, width: f64) -> Option<Self> {
        let lo = points.clone().fold(DVec3::INFINITY, |a, &p| a.min(p));
        let hi = points.fold(DVec3::NEG_INFINITY, |a, &p| a.max(p));
        let extent = hi - lo;
        if !width.is_finite() || !extent.is_finite() {
            return None;
        }
        // Wider cells where the extent would need more than MAX_CELLS.
        let width = width.max(extent.max_element() / (MAX_CELLS - 1) as f64);
        if width <= 0.0 {
            return None;
        }
        let cells = extent
            .to_array()
            .map(|e| ((e / width).floor() as u32 + 1).min(MAX_CELLS));
        (cells.iter().any(|&c| c >= MIN_CELLS)).then_some(Self { lo, width, cells })
    }

    fn cell(&self, p: DVec3) -> [u32; 3] {
        let c = ((p - self.lo) / self.width).floor().to_array();
        std::array::from_fn(|k| (c[k].max(0.0) as u32).min(self.cells[k] - 1))
    }

    /// The Morton key of a cell: the bits of x, y, z interleaved.
    fn key(cell: [u32; 3]) -> u32 {
        let spread = |v: u32| {
            let mut x = v & 0x3ff;
            x = (x | (x << 16)) & 0x0300_00ff;
            x = (x | (x << 8)) & 0x0300_f00f;
            x = (x | (x << 4)) & 0x030c_30c3;
            (x | (x << 2)) & 0x0924_9249
        };
        spread(cell[0]) | (spread(cell[1]) << 1) | (spread(cell[2]) << 2)
    }

    /// The indices of `points` in Morton order of their cells (ties by index), with each
    /// sorted point's cell.
    pub fn sort(&self, points: &[DVec3]) -> (Vec<u32>, Vec<[u32; 3]>) {
        let cells: Vec<[u32; 3]> = points.iter().map(|&p| self.cell(p)).collect();
        let mut order: Vec<u32> = (0..points.len() as u32).collect();
        order.sort_by_key(|&i| (Self::key(cells[i as usize]), i));
        let sorted = order.iter().map(|&i| cells[i as usize]).collect();
        (order, sorted)
    }
}

/// The table the E-step shaders read (`ranges` in `glsl/include/cpd.glsl`), and the
/// number of pieces (dispatches): for `groups` workgroups over the own set (sorted cells
/// `own`), the ranges of the other set (sorted cells `other`, `other_count` points) each
/// visits, cut into pieces of about `span` points. Without a grid (`own`/`other` empty)
/// each workgroup visits the whole other set.
pub fn plan(
    grid: Option<&Grid>,
    own: &[[u32; 3]],
    other: &[[u32; 3]],
    groups: usize,
    other_count: u32,
    span: u32,
) -> (Vec<[u32; 2]>, u32) {
    assert!(
        span > 2 * RANGE_COST,
        "pieces of {span} points are too short"
    );
    let Some(grid) = grid else {
        // The whole other set in spans of `span`, the same for every workgroup.
        let spans: Vec<Vec<[u32; 2]>> = crate::gpu::spans(other_count, span)
            .map(|(first, end)| vec![[first, end]])
            .collect();
        return table_of(&vec![spans; groups]);
    };
    let per_group: Vec<Vec<[u32; 2]>> = {
        // Each occupied cell's range in the other set's sorted order.
        let mut cell_ranges = std::collections::HashMap::new();
        let mut start = 0usize;
        while start < other.len() {
            let mut end = start + 1;
            while end < other.len() && other[end] == other[start] {
                end += 1;
            }
            cell_ranges.insert(other[start], [start as u32, end as u32]);
            start = end;
        }
        (0..groups)
            .map(|g| {
                let mine = &own[(g * POINTS_PER_GROUP).min(own.len())
                    ..((g + 1) * POINTS_PER_GROUP).min(own.len())];
                let mut cells: Vec<[u32; 3]> = mine.to_vec();
                cells.dedup();
                let mut near: Vec<[u32; 3]> = Vec::new();
                for c in cells {
                    for dz in -1i64..=1 {
                        for dy in -1i64..=1 {
                            for dx in -1i64..=1 {
                                let n = [c[0] as i64 + dx, c[1] as i64 + dy, c[2] as i64 + dz];
                                if (0..3).all(|k| n[k] >= 0 && n[k] < grid.cells[k] as i64) {
                                    near.push(n.map(|v| v as u32));
                                }
                            }
                        }
                    }
                }
                let mut ranges: Vec<[u32; 2]> = near
                    .iter()
                    .filter_map(|c| cell_ranges.get(c).copied())
                    .collect();
                ranges.sort_unstable();
                ranges.dedup();
                // Ranges that touch become one.
                let mut merged: Vec<[u32; 2]> = Vec::with_capacity(ranges.len());
                for r in ranges {
                    match merged.last_mut() {
                        Some(last) if last[1] >= r[0] => last[1] = last[1].max(r[1]),
                        _ => merged.push(r),
                    }
                }
                merged
            })
            .collect()
    };
    // Each workgroup's ranges in pieces of at most `span` points (counting RANGE_COST
    // per range), a range cut where a piece is full.
    let pieces_of: Vec<Vec<Vec<[u32; 2]>>> = per_group
        .iter()
        .map(|ranges| {
            let mut pieces = vec![Vec::new()];
            let mut room = span;
            for &[mut first, end] in ranges {
                while first < end {
                    if room <= RANGE_COST {
                        pieces.push(Vec::new());
                        room = span;
                    }
                    let take = (end - first).min(room - RANGE_COST);
                    pieces
                        .last_mut()
                        .expect("one piece at least")
                        .push([first, first + take]);
                    room -= take + RANGE_COST;
                    first += take;
                }
            }
            pieces
        })
        .collect();
    table_of(&pieces_of)
}

/// The table of [`plan`] from each workgroup's pieces of ranges.
fn table_of(pieces_of: &[Vec<Vec<[u32; 2]>>]) -> (Vec<[u32; 2]>, u32) {
    let groups = pieces_of.len();
    let count = pieces_of.iter().map(Vec::len).max().unwrap_or(1).max(1);
    let mut table = vec![[0u32, 0u32]; count * groups];
    for (g, pieces) in pieces_of.iter().enumerate() {
        for (p, ranges) in pieces.iter().enumerate() {
            table[p * groups + g] = [table.len() as u32, ranges.len() as u32];
            table.extend_from_slice(ranges);
        }
    }
    (table, count as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points(n: usize) -> Vec<DVec3> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 0.618_034;
                DVec3::new(t.fract(), (t * 7.3).fract(), (t * 3.1).fract() * 0.5)
            })
            .collect()
    }

    /// Every pair closer than the cell width is visited by the workgroup of its own point.
    #[test]
    fn every_near_pair_is_visited() {
        let (own, other) = (
            points(1500),
            points(1700).iter().map(|p| *p * 1.01).collect::<Vec<_>>(),
        );
        let width = 0.07;
        let grid = Grid::new(own.iter().chain(&other), width).expect("a grid");
        let (own_order, own_cells) = grid.sort(&own);
        let (other_order, other_cells) = grid.sort(&other);
        let groups = own.len().div_ceil(POINTS_PER_GROUP);
        let (table, pieces) = plan(
            Some(&grid),
            &own_cells,
            &other_cells,
            groups,
            other.len() as u32,
            300,
        );
        assert!(pieces > 1, "the test should cut ranges into pieces");
        let mut visited_pairs = 0usize;
        for g in 0..groups {
            let mut visited = vec![0u32; other.len()];
            for p in 0..pieces as usize {
                let [offset, count] = table[p * groups + g];
                let ranges = &table[offset as usize..(offset + count) as usize];
                let cost: u32 = ranges.iter().map(|r| r[1] - r[0] + RANGE_COST).sum();
                assert!(cost <= 300, "piece {p} of group {g} costs {cost}");
                for r in ranges {
                    for j in r[0]..r[1] {
                        visited[j as usize] += 1;
                    }
                }
            }
            assert!(visited.iter().all(|&v| v <= 1), "a point visited twice");
            for i in g * POINTS_PER_GROUP..((g + 1) * POINTS_PER_GROUP).min(own.len()) {
                let x = own[own_order[i] as usize];
                for (j, &o) in other_order.iter().enumerate() {
                    if (other[o as usize] - x).length() < width {
                        assert_eq!(
                            visited[j], 1,
                            "own {i} and other {j} are near but not visited"
                        );
                    }
                }
            }
            visited_pairs += visited.iter().filter(|&&v| v > 0).count() * POINTS_PER_GROUP;
        }
        assert!(
            visited_pairs < own.len() * other.len() / 2,
            "the grid should skip far pairs"
        );
    }

    #[test]
    fn without_a_grid_each_group_visits_everything_in_spans() {
        let (table, pieces) = plan(None, &[], &[], 3, 20_000, 8192);
        assert_eq!(pieces, 3);
        for g in 0..3 {
            let mut next = 0;
            for p in 0..3 {
                let [offset, count] = table[p * 3 + g];
                for r in &table[offset as usize..(offset + count) as usize] {
                    assert_eq!(r[0], next);
                    next = r[1];
                }
            }
            assert_eq!(next, 20_000);
        }
    }

    #[test]
    fn large_sigma_needs_no_grid_and_small_sigma_does() {
        let p = points(1000);
        let log_c = -3.0;
        assert!(Grid::new(p.iter(), cutoff(0.5, log_c, 1000)).is_none());
        assert!(Grid::new(p.iter(), cutoff(1e-4, log_c, 1000)).is_some());
        assert_eq!(cutoff(f64::INFINITY, log_c, 10), f64::INFINITY);
    }
}
