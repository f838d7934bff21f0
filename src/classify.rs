//! The rules of docs/contract.md §4 that turn one ray's hits into "these casters are
//! useful for this light". Pure functions over hit lists: no geometry, no
//! I/O, so the rules can be tested on hand-written hit lists and shared by
//! the BVH path and the brute-force oracle.
//!
//! Face culling and the below-ground test need geometry and happen before a
//! hit reaches this module; what arrives here has survived them.
//!
//! # Tolerances
//! - `epsilon` (settings `tieEpsilon`, metres along the ray): casters whose
//!   hits lie within `t1 + epsilon` of the nearest caster hit `t1` tie with
//!   it (coplanar casters, as under a LEQUAL depth test), and hits at
//!   `t >= t1 - epsilon` count as "behind".
//! - Hits on the same caster are merged into one surface crossing when they
//!   lie within `epsilon` of the *first* hit of their run (greedy clusters
//!   from the nearest hit on). The trace module already gives a shared edge
//!   or vertex to exactly one triangle; this merge additionally absorbs the
//!   duplicate hits of overlapping triangles of one group. Greedy clusters
//!   have a property the early cut-off relies on: adding hits never lowers
//!   the number of crossings (greedy covering is optimal, and a superset
//!   never needs fewer intervals).

/// A hit that survived face culling and the below-ground test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayHit {
    /// Distance along the (unit) ray, metres.
    pub t: f32,
    /// Caster id (index into the bake's caster table).
    pub caster: u32,
    /// The hit is on a receiver-only instance (`castsShadow` false): it can
    /// be "behind" a caster but is never a caster itself.
    pub receiver_only: bool,
    /// The hit's group is alpha-tested: it drops out of the Opaque pass.
    pub alpha_tested: bool,
}

/// Which passes a light needs: both when it reaches an alpha-tested group,
/// otherwise the All pass alone decides everything.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Passes {
    AllOnly,
    AllAndOpaque,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Pass {
    All,
    Opaque,
}

impl Pass {
    fn keeps(self, hit: &RayHit) -> bool {
        match self {
            Pass::All => true,
            Pass::Opaque => !hit.alpha_tested,
        }
    }
}

fn passes(passes: Passes) -> &'static [Pass] {
    match passes {
        Passes::AllOnly => &[Pass::All],
        Passes::AllAndOpaque => &[Pass::All, Pass::Opaque],
    }
}

/// Sorts hits into the canonical order (t, then caster) so every later
/// step is independent of the order the traversal found them in.
pub fn sort_hits(hits: &mut [RayHit]) {
    hits.sort_unstable_by(|a, b| a.t.total_cmp(&b.t).then(a.caster.cmp(&b.caster)));
}

/// Evaluates one ray: calls `useful` for every caster the ray proves useful
/// (a caster may be reported once per pass). `hits` must be sorted with
/// [`sort_hits`].
pub fn classify_ray(hits: &[RayHit], epsilon: f32, which: Passes, mut useful: impl FnMut(u32)) {
    for &pass in passes(which) {
        let Some(t1) = nearest_caster(hits, pass) else {
            continue;
        };
        if crossings_from(hits, pass, t1 - epsilon, epsilon).count < 2 {
            continue;
        }
        for hit in hits {
            if hit.t > t1 + epsilon {
                break;
            }
            if pass.keeps(hit) && !hit.receiver_only {
                useful(hit.caster);
            }
        }
    }
}

/// One pass's depths along a ray, for the filter margin
/// (`bake::filter_margin`): what a shadow map stores at the texel (`front`,
/// the nearest caster hit; `f32::INFINITY` when none) and the farthest
/// receiving surface (`far`, the farthest hit of the pass, caster or
/// receiver-only; `f32::NEG_INFINITY` when none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PassDepths {
    pub front: f32,
    pub far: f32,
}

impl PassDepths {
    pub const NONE: PassDepths = PassDepths {
        front: f32::INFINITY,
        far: f32::NEG_INFINITY,
    };
}

/// How many passes `which` evaluates (All first, then Opaque).
pub fn pass_count(which: Passes) -> usize {
    passes(which).len()
}

/// Pass `pass` (an index below [`pass_count`]) of `hits` (sorted, every hit
/// of the ray: no cut-off): its depths, and each caster of its front set
/// handed to `front` (the casters a K = 0 ray would prove useful, given
/// something behind).
pub fn pass_depths(
    hits: &[RayHit],
    which: Passes,
    pass: usize,
    epsilon: f32,
    mut front: impl FnMut(u32),
) -> PassDepths {
    let pass = passes(which)[pass];
    let far = hits
        .iter()
        .rev()
        .find(|h| pass.keeps(h))
        .map_or(f32::NEG_INFINITY, |h| h.t);
    let Some(t1) = nearest_caster(hits, pass) else {
        return PassDepths {
            far,
            ..PassDepths::NONE
        };
    };
    for hit in hits.iter().take_while(|h| h.t <= t1 + epsilon) {
        if pass.keeps(hit) && !hit.receiver_only {
            front(hit.caster);
        }
    }
    PassDepths { front: t1, far }
}

/// How far along the ray hits can still change [`classify_ray`]'s answer,
/// given the hits found so far (sorted). Hits beyond the returned distance
/// cannot: the nearest caster cannot move past it, the front set ends before
/// it, and at least two crossings behind the front are already found (the
/// crossing count only grows as hits are added). `f32::INFINITY` while some
/// pass is still undecided.
pub fn cutoff(hits: &[RayHit], epsilon: f32, which: Passes) -> f32 {
    let mut cut = 0.0f32;
    for &pass in passes(which) {
        let Some(t1) = nearest_caster(hits, pass) else {
            return f32::INFINITY;
        };
        let crossings = crossings_from(hits, pass, t1 - epsilon, epsilon);
        if crossings.count < 2 {
            return f32::INFINITY;
        }
        cut = cut.max(t1 + epsilon).max(crossings.reached_at);
    }
    // One more epsilon so a hit found later that ties at the boundary (or a
    // node box touching it) is still visited.
    cut + epsilon
}

fn nearest_caster(hits: &[RayHit], pass: Pass) -> Option<f32> {
    hits.iter()
        .find(|h| pass.keeps(h) && !h.receiver_only)
        .map(|h| h.t)
}

struct Crossings {
    count: usize,
    /// The t of the hit that brought `count` to its value.
    reached_at: f32,
}

/// Surface crossings among the pass's hits at `t >= from`, counting up to
/// two (all the rules need): hits on one caster within `epsilon` of its
/// run's first hit are one crossing. Runs on the hot path of every hit, so
/// no allocation: at most two runs can be open before the count reaches 2.
fn crossings_from(hits: &[RayHit], pass: Pass, from: f32, epsilon: f32) -> Crossings {
    // (caster, t of the first hit of its current run).
    let mut runs = [(0u32, 0.0f32); 2];
    let mut count = 0;
    let mut reached_at = f32::NEG_INFINITY;
    for hit in hits.iter().filter(|h| h.t >= from && pass.keeps(h)) {
        if let Some((_, start)) = runs[..count]
            .iter()
            .find(|(caster, _)| *caster == hit.caster)
        {
            if hit.t - *start <= epsilon {
                continue;
            }
        }
        runs[count] = (hit.caster, hit.t);
        count += 1;
        reached_at = hit.t;
        if count == runs.len() {
            break;
        }
    }
    Crossings { count, reached_at }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EPS: f32 = 1e-4;

    fn caster(t: f32, caster: u32) -> RayHit {
        RayHit {
            t,
            caster,
            receiver_only: false,
            alpha_tested: false,
        }
    }

    fn receiver(t: f32, id: u32) -> RayHit {
        RayHit {
            receiver_only: true,
            ..caster(t, id)
        }
    }

    fn alpha(t: f32, id: u32) -> RayHit {
        RayHit {
            alpha_tested: true,
            ..caster(t, id)
        }
    }

    fn useful(mut hits: Vec<RayHit>, which: Passes) -> Vec<u32> {
        sort_hits(&mut hits);
        let mut out = Vec::new();
        classify_ray(&hits, EPS, which, |c| out.push(c));
        out.sort_unstable();
        out.dedup();
        out
    }

    #[test]
    fn a_caster_with_something_behind_is_useful_and_only_the_front_one() {
        // A box (two crossings) over the ground: the box's front face is
        // first; the ground is behind.
        let hits = vec![caster(5.0, 1), caster(6.0, 1), caster(10.0, 2)];
        assert_eq!(useful(hits, Passes::AllOnly), vec![1]);
    }

    #[test]
    fn a_lone_single_crossing_is_not_useful() {
        assert_eq!(
            useful(vec![caster(5.0, 1)], Passes::AllOnly),
            Vec::<u32>::new()
        );
        assert_eq!(useful(vec![], Passes::AllOnly), Vec::<u32>::new());
    }

    #[test]
    fn a_closed_mesh_over_the_void_is_useful_through_itself() {
        // Front and back face of one double-sided closed mesh: two crossings.
        assert_eq!(
            useful(vec![caster(1.0, 3), caster(2.0, 3)], Passes::AllOnly),
            vec![3]
        );
    }

    #[test]
    fn duplicate_hits_of_one_surface_merge() {
        // Three triangles of one group meeting at the ray within epsilon:
        // one crossing, nothing behind.
        let hits = vec![
            caster(1.0, 3),
            caster(1.0 + 0.5 * EPS, 3),
            caster(1.0 + 0.9 * EPS, 3),
        ];
        assert_eq!(useful(hits, Passes::AllOnly), Vec::<u32>::new());
    }

    #[test]
    fn merging_runs_from_the_first_hit_cannot_be_bridged() {
        // 0, 0.6ε, 1.2ε on one caster: the run starting at 0 covers 0.6ε but
        // not 1.2ε, so that is a second crossing (a chain would merge all).
        let hits = vec![
            caster(1.0, 3),
            caster(1.0 + 0.6 * EPS, 3),
            caster(1.0 + 1.2 * EPS, 3),
        ];
        assert_eq!(useful(hits, Passes::AllOnly), vec![3]);
    }

    #[test]
    fn coplanar_casters_tie_and_both_are_useful() {
        // Decal on a wall: two casters at the same depth, wall's back behind.
        let hits = vec![caster(4.0, 7), caster(4.0 + 0.5 * EPS, 8), caster(4.5, 8)];
        assert_eq!(useful(hits, Passes::AllOnly), vec![7, 8]);
        // Even alone two coplanar casters pass: two fragments under LEQUAL.
        assert_eq!(
            useful(vec![caster(4.0, 7), caster(4.0, 8)], Passes::AllOnly),
            vec![7, 8]
        );
        // Beyond epsilon the second is behind, not tied.
        let hits = vec![caster(4.0, 7), caster(4.0 + 2.0 * EPS, 8)];
        assert_eq!(useful(hits, Passes::AllOnly), vec![7]);
    }

    #[test]
    fn receivers_count_behind_but_are_never_useful() {
        assert_eq!(
            useful(vec![caster(2.0, 1), receiver(3.0, 9)], Passes::AllOnly),
            vec![1]
        );
        // A receiver in front of the caster does not count as behind it.
        assert_eq!(
            useful(vec![receiver(1.0, 9), caster(2.0, 1)], Passes::AllOnly),
            Vec::<u32>::new()
        );
        // Receivers alone make nothing useful.
        assert_eq!(
            useful(vec![receiver(1.0, 9), receiver(2.0, 9)], Passes::AllOnly),
            Vec::<u32>::new()
        );
    }

    #[test]
    fn alpha_tested_canopy_never_culls_what_is_below_it() {
        // Canopy (alpha-tested, one card) above a roof above the ground.
        let hits = vec![
            alpha(1.0, 5),
            caster(3.0, 6),
            caster(4.0, 6),
            caster(9.0, 2),
        ];
        // All pass: the canopy is in front with things behind → useful.
        // Opaque pass: the roof is in front → useful too.
        assert_eq!(useful(hits.clone(), Passes::AllAndOpaque), vec![5, 6]);
        // With one pass only the canopy would win.
        assert_eq!(useful(hits, Passes::AllOnly), vec![5]);
    }

    #[test]
    fn alpha_tested_receivers_drop_out_of_the_opaque_pass() {
        let hidden_alpha_receiver = RayHit {
            receiver_only: true,
            ..alpha(3.0, 9)
        };
        // Opaque pass: only the caster remains: not useful there. All pass:
        // the caster has the receiver behind it → useful.
        // All pass: the caster has the receiver behind it → useful. Opaque
        // pass: the alpha-tested receiver is gone, nothing behind the caster.
        let hits = vec![caster(2.0, 1), hidden_alpha_receiver];
        assert_eq!(useful(hits.clone(), Passes::AllAndOpaque), vec![1]);
        let mut sorted = hits;
        sort_hits(&mut sorted);
        assert_eq!(cutoff(&sorted, EPS, Passes::AllOnly), 3.0 + EPS);
        assert_eq!(cutoff(&sorted, EPS, Passes::AllAndOpaque), f32::INFINITY);
    }

    #[test]
    fn cutoff_is_infinite_until_both_passes_are_decided() {
        let mut hits = vec![alpha(1.0, 5)];
        assert_eq!(cutoff(&hits, EPS, Passes::AllAndOpaque), f32::INFINITY);
        hits.push(caster(3.0, 6));
        sort_hits(&mut hits);
        // All pass decided (canopy + roof), Opaque (roof alone) not yet.
        assert_eq!(cutoff(&hits, EPS, Passes::AllAndOpaque), f32::INFINITY);
        assert_eq!(cutoff(&hits, EPS, Passes::AllOnly), 3.0 + EPS);
        hits.push(caster(4.0, 6));
        sort_hits(&mut hits);
        assert_eq!(cutoff(&hits, EPS, Passes::AllAndOpaque), 4.0 + EPS);
    }

    #[test]
    fn hits_beyond_the_cutoff_never_change_the_answer() {
        // Seeded random hit lists: evaluating only the hits up to the cutoff
        // computed from any subset found so far (in random discovery order)
        // gives the same useful set as evaluating all hits.
        let mut rng = crate::rng::Rng::new(17);
        for _ in 0..5000 {
            let n = 1 + rng.below(7);
            let all: Vec<RayHit> = (0..n)
                .map(|_| {
                    // Clustered t so ties and merges happen often.
                    let t = 1.0 + rng.below(4) as f32 * 0.5 + rng.below(3) as f32 * 0.6 * EPS;
                    RayHit {
                        t,
                        caster: rng.below(3) as u32,
                        receiver_only: rng.below(5) == 0,
                        alpha_tested: rng.below(4) == 0,
                    }
                })
                .collect();
            for which in [Passes::AllOnly, Passes::AllAndOpaque] {
                let expected = useful(all.clone(), which);
                // Discover hits one by one, keeping only those within the
                // current cut-off, shrinking it as a traversal would.
                let mut found: Vec<RayHit> = Vec::new();
                let mut limit = f32::INFINITY;
                for hit in &all {
                    if hit.t <= limit {
                        found.push(*hit);
                        sort_hits(&mut found);
                        limit = limit.min(cutoff(&found, EPS, which));
                    }
                }
                found.retain(|h| h.t <= limit);
                assert_eq!(useful(found, which), expected, "{all:?} {which:?}");
            }
        }
    }
}
