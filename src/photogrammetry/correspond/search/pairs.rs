//! Step 5: with two cameras enough (`min_cameras = 2`), the pairs among
//! the targets still unused that are each other's single candidate.

use super::{Search, NONE};

impl Search<'_, '_> {
    /// Step 5: unambiguous pairs among the unused targets.
    pub(super) fn pairs(&mut self) {
        let count = self.frames.len();
        let mut candidates: Vec<(f64, [(usize, u32); 2])> = Vec::new();
        let mut found = Vec::with_capacity(4);
        let mut members = vec![NONE; count];
        for i in 0..count {
            for j in i + 1..count {
                for a in 0..self.frames[i].targets.len() {
                    if self.should_stop(a) {
                        return;
                    }
                    if self.used[i][a] {
                        continue;
                    }
                    found.clear();
                    self.band(i, a, j, |b| found.push(b));
                    let [b] = found[..] else {
                        continue;
                    };
                    found.clear();
                    self.band(j, b, i, |c| found.push(c));
                    if found[..] != [a] {
                        continue;
                    }
                    members.fill(NONE);
                    members[i] = a as u32;
                    members[j] = b as u32;
                    if let Some(fit) = self.fit(&members, |_| false) {
                        if fit.largest <= self.acceptance {
                            candidates.push((fit.spread, [(i, a as u32), (j, b as u32)]));
                        }
                    }
                }
            }
        }
        candidates.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
        for (_, pair) in candidates {
            if pair.iter().any(|&(k, t)| self.used[k][t as usize]) {
                continue;
            }
            members.fill(NONE);
            for (k, t) in pair {
                members[k] = t;
            }
            self.keep(&members);
        }
    }
}
