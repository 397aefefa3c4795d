//! Steps 2 and 3: seed pairs from the epipolar bands, completed in the
//! other cameras into candidate groups of three or more.

use super::{size, GroupFit, Search, NONE};
use crate::photogrammetry::correspond::epipolar::closest_approach;

/// How far around a pair's predicted image a third camera is searched, in
/// band half-widths.
const COMPLETION_RADIUS: f64 = 3.0;

/// Per pair and other camera, the most targets (the best fitting) that may
/// complete the pair's group. More arise only where the band is wide for
/// the target density; the candidates beyond the best few are then
/// practically never the particle's image, and their combinations would
/// multiply the work and memory.
const MAX_CANDIDATES_PER_CAMERA: usize = 3;

/// Per target of a seed camera, the most candidate groups kept (the largest
/// with the smallest spread): a target ends in at most one particle, and
/// this bounds the candidates' memory by the target count.
const MAX_GROUPS_PER_TARGET: usize = 8;

/// Candidate groups: per group, one target (or NONE) per camera, in a flat
/// array with a stride of the camera count.
#[derive(Default)]
pub(super) struct CandidateGroups {
    pub(super) members: Vec<u32>,
    pub(super) sizes: Vec<usize>,
    pub(super) spreads: Vec<f64>,
    /// The largest miss of a member (px).
    pub(super) largest: Vec<f64>,
    /// Whether the group is its seed target's best (the largest, with the
    /// smallest spread): the noise estimate takes one group per target.
    pub(super) best: Vec<bool>,
}

impl CandidateGroups {
    fn len(&self) -> usize {
        self.sizes.len()
    }
}

/// Scratch space of the completion, reused from target to target.
pub(super) struct Completion {
    partners: Vec<(usize, Option<crate::photogrammetry::camera::Ray>)>,
    near: Vec<Vec<u32>>,
    members: Vec<u32>,
    group: Vec<u32>,
    seen: Vec<usize>,
    choice: Vec<usize>,
    traced: Vec<bool>,
    fits: Vec<(f64, u32)>,
    /// This target's candidate groups: (size, fit, offset in own_members).
    own: Vec<(usize, GroupFit, usize)>,
    own_members: Vec<u32>,
}

impl Completion {
    pub(super) fn new(count: usize) -> Self {
        Completion {
            partners: Vec::new(),
            near: vec![Vec::new(); count],
            members: vec![NONE; count],
            group: vec![NONE; count],
            seen: Vec::with_capacity(count),
            choice: Vec::with_capacity(count),
            traced: vec![false; count],
            fits: Vec::new(),
            own: Vec::new(),
            own_members: Vec::new(),
        }
    }
}

impl Search<'_, '_> {
    /// Steps 2 and 3: candidate groups of three or more cameras, for every
    /// unused target of seed camera i.
    pub(super) fn candidate_groups(&mut self, seed: (usize, usize)) -> CandidateGroups {
        let mut groups = CandidateGroups::default();
        let mut scratch = Completion::new(self.frames.len());
        for a in 0..self.frames[seed.0].targets.len() {
            if self.should_stop(a) {
                break;
            }
            self.complete(seed, a, &mut scratch, &mut groups);
        }
        groups
    }

    /// Steps 2 and 3 for target `a` of seed camera i: its candidate groups
    /// (at most [`MAX_GROUPS_PER_TARGET`]) appended to `groups`; how many
    /// were added.
    ///
    /// The point where a pair's rays meet is uncertain along their epipolar
    /// lines, most where those lines run nearly parallel in a third camera,
    /// so the third camera is searched within `COMPLETION_RADIUS` (3) band
    /// half-widths of its image, and a target there is kept only if its ray
    /// meets the pair's within the band.
    pub(super) fn complete(
        &mut self,
        (i, j): (usize, usize),
        a: usize,
        scratch: &mut Completion,
        groups: &mut CandidateGroups,
    ) -> usize {
        let count = self.frames.len();
        let band = self.band_px;
        if self.used[i][a] {
            return 0;
        }
        let Some(ray_a) = self.frames[i].ray(a) else {
            return 0;
        };
        let Completion {
            partners,
            near,
            members,
            group,
            seen,
            choice,
            traced,
            fits,
            own,
            own_members,
        } = scratch;
        partners.clear();
        // Each partner's ray is read as the band finds it, from the cache
        // line its position was just tested from.
        let frame_j = &self.frames[j];
        self.band(i, a, j, |b| partners.push((b, frame_j.ray(b))));
        if partners.is_empty() {
            return 0;
        }
        own.clear();
        own_members.clear();
        // The ray's images in the other cameras, traced on demand.
        traced.fill(false);
        for &(b, ray_b) in partners.iter() {
            let Some(t) = ray_b.and_then(|ray_b| closest_approach(&ray_a, &ray_b)) else {
                continue;
            };
            seen.clear();
            members.fill(NONE);
            members[i] = a as u32;
            members[j] = b as u32;
            for k in 0..count {
                near[k].clear();
                if k == i || k == j {
                    continue;
                }
                if !traced[k] {
                    traced[k] = true;
                    self.trace(i, a, k);
                }
                // Where the pair's point images, to within half the rays'
                // gap (the curve follows ray a).
                let Some(pixel) = self.curves[k].at(t) else {
                    continue;
                };
                let reference = &self.frames[i].targets[a];
                let mut list = std::mem::take(&mut near[k]);
                self.near(k, pixel, COMPLETION_RADIUS * band, reference, &mut list);
                // Only targets whose rays meet the pair's, the best few (see
                // MAX_CANDIDATES_PER_CAMERA).
                fits.clear();
                fits.extend(list.iter().filter_map(|&c| {
                    members[k] = c;
                    let fit = self.fit(members, |_| false);
                    members[k] = NONE;
                    fit.filter(|f| f.largest <= band).map(|f| (f.largest, c))
                }));
                fits.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
                fits.truncate(MAX_CANDIDATES_PER_CAMERA);
                list.clear();
                list.extend(fits.iter().map(|&(_, c)| c));
                if !list.is_empty() {
                    seen.push(k);
                }
                near[k] = list;
            }
            if seen.is_empty() {
                continue;
            }
            // Every combination of one target per camera that has any;
            // targets that each fit the pair may not fit together (one
            // imaging another particle), so the worst is dropped until they
            // do.
            choice.clear();
            choice.resize(seen.len(), 0usize);
            loop {
                group.copy_from_slice(members);
                for (slot, &k) in seen.iter().enumerate() {
                    group[k] = near[k][choice[slot]];
                }
                if let Some(fit) = self.trim(group, band, |k| k == i || k == j) {
                    own.push((size(group), fit, own_members.len()));
                    own_members.extend_from_slice(group);
                }
                // Next combination (odometer).
                let mut slot = 0;
                while slot < seen.len() {
                    choice[slot] += 1;
                    if choice[slot] < near[seen[slot]].len() {
                        break;
                    }
                    choice[slot] = 0;
                    slot += 1;
                }
                if slot == seen.len() {
                    break;
                }
            }
        }
        // The target's best candidates only (see MAX_GROUPS_PER_TARGET):
        // memory stays linear in the targets.
        own.sort_unstable_by(|x, y| y.0.cmp(&x.0).then(x.1.spread.total_cmp(&y.1.spread)));
        let before = groups.len();
        for (rank, &(size, fit, at)) in own.iter().take(MAX_GROUPS_PER_TARGET).enumerate() {
            groups
                .members
                .extend_from_slice(&own_members[at..at + count]);
            groups.sizes.push(size);
            groups.spreads.push(fit.spread);
            groups.largest.push(fit.largest);
            groups.best.push(rank == 0);
        }
        groups.len() - before
    }
}
