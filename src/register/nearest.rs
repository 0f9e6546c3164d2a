//! Nearest points among a fixed set in 3D: a uniform grid of about one point per cell,
//! searched in growing shells of cells, exact (the same nearest point as a scan, the
//! first in the set's order among equally near ones).

use std::collections::HashMap;

use glam::DVec3;

/// `points` bucketed by cell.
pub(super) struct Nearest<'a> {
    points: &'a [DVec3],
    cell: f64,
    cells: HashMap<[i64; 3], Vec<usize>>,
    /// The least and the greatest cell index on each axis that holds points.
    low: [i64; 3],
    high: [i64; 3],
}

impl<'a> Nearest<'a> {
    /// The grid of `points` (not empty, finite), cells sized for about one point each.
    pub(super) fn new(points: &'a [DVec3]) -> Self {
        debug_assert!(!points.is_empty() && points.iter().all(|p| p.is_finite()));
        let (low, high) = points.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(l, h), &p| (l.min(p), h.max(p)),
        );
        let extent = (high - low).max_element();
        let cell = match extent > 0.0 && extent.is_finite() {
            true => extent / (points.len() as f64).cbrt().max(1.0),
            false => 1.0,
        };
        let mut cells: HashMap<[i64; 3], Vec<usize>> = HashMap::new();
        for (i, &p) in points.iter().enumerate() {
            cells.entry(key(p, cell)).or_default().push(i);
        }
        Self {
            points,
            cell,
            cells,
            low: key(low, cell),
            high: key(high, cell),
        }
    }

    /// The point nearest to `q`.
    pub(super) fn nearest(&self, q: DVec3) -> DVec3 {
        let c = key(q, self.cell);
        // The shells (cells at Chebyshev distance r from q's) that meet the occupied box.
        let first = (0..3)
            .map(|k| (self.low[k] - c[k]).max(c[k] - self.high[k]).max(0))
            .max()
            .unwrap_or(0);
        let last = (0..3)
            .map(|k| (c[k] - self.low[k]).abs().max((self.high[k] - c[k]).abs()))
            .max()
            .unwrap_or(0);
        // (squared distance, index): the index breaks ties as a scan in order would.
        let mut best = (f64::INFINITY, usize::MAX);
        for r in first..=last {
            // Within the occupied box only: a far query meets few of a shell's cells.
            let range = |k: usize| (self.low[k] - c[k]).max(-r)..=(self.high[k] - c[k]).min(r);
            for i in range(0) {
                for j in range(1) {
                    for k in range(2) {
                        if i.abs().max(j.abs()).max(k.abs()) != r {
                            continue;
                        }
                        let Some(items) = self.cells.get(&[c[0] + i, c[1] + j, c[2] + k]) else {
                            continue;
                        };
                        for &index in items {
                            let d = (self.points[index] - q).length_squared();
                            if d < best.0 || (d == best.0 && index < best.1) {
                                best = (d, index);
                            }
                        }
                    }
                }
            }
            // A point in shell r + 1 or beyond is at least r cells from q (q lies in its
            // own cell).
            let clear = r as f64 * self.cell;
            if best.0 < clear * clear {
                break;
            }
        }
        self.points[best.1]
    }
}

fn key(p: DVec3, cell: f64) -> [i64; 3] {
    (p / cell).floor().to_array().map(|x| x as i64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The grid finds what a scan finds, for queries near, among and far from the points.
    #[test]
    fn the_grid_finds_what_a_scan_finds() {
        let mut state = 0x2545F4914F6CDD1Du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let points: Vec<DVec3> = (0..700)
            .map(|_| DVec3::new(next() * 0.1, next() * 0.02, next() * 0.05))
            .collect();
        let grid = Nearest::new(&points);
        for scale in [0.01, 0.1, 1.0, 30.0] {
            for _ in 0..300 {
                let q = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * scale;
                let scan = points
                    .iter()
                    .copied()
                    .min_by(|a, b| {
                        (*a - q)
                            .length_squared()
                            .total_cmp(&(*b - q).length_squared())
                    })
                    .unwrap();
                assert_eq!(grid.nearest(q), scan, "query {q}");
            }
        }
        // One point, and points all in one place.
        let one = [DVec3::new(1.0, 2.0, 3.0)];
        assert_eq!(Nearest::new(&one).nearest(DVec3::ZERO), one[0]);
        let same = [DVec3::ONE; 4];
        assert_eq!(Nearest::new(&same).nearest(DVec3::ZERO), DVec3::ONE);
    }
}
