//! Step 4's end: targets exchanged between accepted groups (and with
//! unused targets) where that fits both better.

use nalgebra::Vector2;

use super::{size, Search, NONE};

impl Search<'_, '_> {
    /// The sum of squared misses of a group's rays (px^2).
    fn cost(&self, members: &[u32]) -> f64 {
        let size = size(members) as f64;
        self.fit(members, |_| false)
            .map_or(f64::INFINITY, |f| f.spread * f.spread * size)
    }

    /// Exchanges of targets between accepted groups (and with unused
    /// targets) where that lowers their summed squared misses.
    ///
    /// Best-first selection decides two groups that compete for two nearly
    /// coincident targets by the first group alone; where two particles'
    /// images nearly coincide in one camera, that gives each the other's
    /// target about as often as not. Comparing both assignments at once
    /// settles it by all the evidence.
    pub(super) fn improve(&mut self) {
        self.pencil_grids.fill_with(|| None);
        let count = self.frames.len();
        let radius = 2.0 * self.acceptance;
        let radius_sq = radius * radius;
        let neighbours = |k: usize, t: usize, out: &mut Vec<u32>| {
            let frame = &self.frames[k];
            let position = frame.position(t);
            let margin = Vector2::repeat(radius);
            frame.grid.visit(position - margin, position + margin, |c| {
                if c != t && (frame.position(c) - position).norm_squared() <= radius_sq {
                    out.push(c as u32);
                }
            });
        };
        // Most targets have no other within the radius. Found in one pass
        // in memory order, they are skipped below without a search.
        let mut nearby = Vec::new();
        let crowded: Vec<Vec<bool>> = (0..count)
            .map(|k| {
                (0..self.frames[k].targets.len())
                    .map(|t| {
                        nearby.clear();
                        neighbours(k, t, &mut nearby);
                        !nearby.is_empty()
                    })
                    .collect()
            })
            .collect();
        let mut p_alternative = vec![NONE; count];
        let mut q_alternative = vec![NONE; count];
        for p in 0..self.accepted.len() / count {
            if super::stop_at(self.cancel.as_ref(), &mut self.stopped, p) {
                return;
            }
            for k in 0..count {
                let t = self.group(p)[k];
                if t == NONE || !crowded[k][t as usize] {
                    continue;
                }
                nearby.clear();
                neighbours(k, t as usize, &mut nearby);
                for &other in &nearby {
                    let q = self.owner[k][other as usize];
                    if q as usize == p {
                        continue;
                    }
                    p_alternative.copy_from_slice(self.group(p));
                    p_alternative[k] = other;
                    let p_cost = self.cost(self.group(p));
                    if q == NONE {
                        if self.cost(&p_alternative) < p_cost {
                            self.used[k][t as usize] = false;
                            self.owner[k][t as usize] = NONE;
                            self.used[k][other as usize] = true;
                            self.owner[k][other as usize] = p as u32;
                            self.accepted[p * count..(p + 1) * count]
                                .copy_from_slice(&p_alternative);
                            break;
                        }
                        continue;
                    }
                    let q = q as usize;
                    q_alternative.copy_from_slice(self.group(q));
                    q_alternative[k] = t;
                    let before = p_cost + self.cost(self.group(q));
                    if self.cost(&p_alternative) + self.cost(&q_alternative) < before {
                        self.owner[k][t as usize] = q as u32;
                        self.owner[k][other as usize] = p as u32;
                        self.accepted[p * count..(p + 1) * count].copy_from_slice(&p_alternative);
                        self.accepted[q * count..(q + 1) * count].copy_from_slice(&q_alternative);
                        break;
                    }
                }
            }
        }
    }
}
