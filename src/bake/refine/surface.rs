//! A caster's surface points: area-weighted random points of its own
//! triangles, one ray toward each, so a caster thinner than the lattice's
//! step still gets rays that cross it. Seeded per (light, caster), so the
//! rays are the same run to run and whatever the threads.

use super::sampler::{Sampler, BATCH};
use crate::light::TexelRay;
use crate::rng::{mix, Rng};
use crate::trace::TraceTriangle;
use glam::DVec3;

/// Barycentric coordinates stay this far from the edges, so a sample lies
/// inside its triangle and its ray crosses that triangle, not a neighbour.
const EDGE_MARGIN: f64 = 0.02;

/// Surface points traced before the others: once they prove the caster,
/// the others are deferred. Few, as tracing more before deferring the rest
/// was slower (see docs/performance.md).
const FIRST_POINTS: usize = 2;

/// The area-weighted surface points of `run` (the caster's triangles) that
/// may prove it, traced until one does; returns whether one did, and the
/// rays of the points deferred: those that cannot prove it (after a
/// proof, and before one those its occluders so far surely hide from it),
/// which may still prove others.
///
/// Every point is traced, even once one proves the caster: the others may
/// prove other casters, which their own rays can miss (leaving them out
/// loses casters a denser grid keeps). The deferred ones go after the
/// caster's chunk of candidates, only where they may meet a caster not
/// proven by then ([`Sampler::trace_batch_for_others`]).
pub(super) fn surface_points(
    sampler: &mut Sampler<'_, '_>,
    run: &[TraceTriangle],
    light: usize,
    samples: u32,
) -> (bool, Vec<TexelRay>) {
    // The running sums of the triangles' areas, so a pick is a binary
    // search, not a walk of every triangle (a tree's canopy has hundreds).
    let running = running_sums(run.iter().map(area));
    let total = running.last().copied().unwrap_or(0.0);
    if samples == 0 || run.is_empty() || total.is_nan() || total <= 0.0 {
        return (false, Vec::new());
    }
    let grid = sampler.rays.grid;
    let reference = grid.reference_point();
    let mut rng = Rng::new(mix(((light as u64) << 32) | sampler.caster as u64));
    let mut points = Vec::with_capacity(samples as usize);
    let mut at = Vec::with_capacity(samples as usize);
    for _ in 0..samples {
        let chosen = pick_triangle(&running, rng.unit() * total);
        let p = reference + sample_point(&run[chosen], &mut rng);
        if let Some(ray) = grid.ray_toward(p) {
            points.push(ray);
            at.push(p);
        }
    }
    let first = points.len().min(FIRST_POINTS);
    if sampler.trace_surface_points(&points[..first]) {
        points.drain(..first);
        return (true, points);
    }
    let (open, mut deferred) = sampler.split_hidden(&points[first..], &at[first..], run);
    for (k, batch) in open.chunks(BATCH).enumerate() {
        if sampler.trace_surface_points(batch) {
            deferred.extend_from_slice(&open[k * BATCH + batch.len()..]);
            return (true, deferred);
        }
    }
    (false, deferred)
}

/// The triangle an area-weighted `pick` in `[0, total)` falls on, from
/// the running sums of the areas: the first whose sum exceeds it (the last
/// when none does, as for a NaN pick).
fn pick_triangle(running: &[f64], pick: f64) -> usize {
    running
        .partition_point(|&s| pick.partial_cmp(&s) != Some(std::cmp::Ordering::Less))
        .min(running.len().saturating_sub(1))
}

/// Each value's sum with those before it, added in order.
fn running_sums(values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut sum = 0.0;
    values
        .map(|v| {
            sum += v;
            sum
        })
        .collect()
}

fn area(triangle: &TraceTriangle) -> f64 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    0.5 * (b - a).cross(c - a).length()
}

/// A uniform point of the triangle (light-relative), away from its edges.
fn sample_point(triangle: &TraceTriangle, rng: &mut Rng) -> DVec3 {
    let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
    let squeeze = |r: f64| EDGE_MARGIN + (1.0 - 2.0 * EDGE_MARGIN) * r;
    let (r1, r2) = (squeeze(rng.unit()).sqrt(), squeeze(rng.unit()));
    a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain walk over the areas: the first triangle whose running sum
    /// exceeds the pick, else the last.
    fn pick_by_walk(areas: &[f64], pick: f64) -> usize {
        let mut sum = 0.0;
        for (i, a) in areas.iter().enumerate() {
            sum += a;
            if pick < sum {
                return i;
            }
        }
        areas.len() - 1
    }

    #[test]
    fn a_pick_falls_on_the_triangle_the_walk_over_areas_finds() {
        let mut rng = Rng::new(17);
        for round in 0..2000 {
            let n = 1 + rng.below(40);
            // Some zero areas (degenerate triangles), which no pick may land on
            // unless it is the last.
            let areas: Vec<f64> = (0..n)
                .map(|_| {
                    if rng.below(4) == 0 {
                        0.0
                    } else {
                        rng.range(0.0, 3.0)
                    }
                })
                .collect();
            let running = running_sums(areas.iter().copied());
            let sum = running[n - 1];
            let pick = match round % 50 {
                0 => f64::NAN,
                1 => sum,
                _ => rng.unit() * sum,
            };
            assert_eq!(
                pick_triangle(&running, pick),
                pick_by_walk(&areas, pick),
                "{areas:?} {pick}"
            );
        }
    }
}
