//! The node test of a packet of rays: six planes that every ray segment of
//! the packet lies within (four sides around a central direction, a near and
//! a far cap), so a box entirely outside one of them meets none of the
//! rays. For a directional light's tile the sides are a slab around parallel
//! rays; for a spot or point light's tile, a frustum from the common origin;
//! the construction is the same for any packet whose directions lie within a
//! cone (otherwise [`Beam::new`] declines and the caller traces the rays one
//! by one).
//!
//! Conservative like the single-ray node test (`boxtree`): every box is
//! grown by the same padding (hundreds of ulps of the magnitude of the
//! boxes and the ray origins), which covers the rounding of a tree's
//! quantized boxes and of the triangle test; and the planes are built in
//! f64 with a slope margin so that rounding the normals to f32 cannot tip a
//! ray out of them, then loosened by a bound on the f32 evaluation error.
//! A beam only culls: the triangle test of each ray decides its hits, so
//! every ray gets the hits of the single-ray traversal.

use super::{ToModel, TraceRay, PAD_EPSILONS};
use glam::{DMat3, DVec3, Vec3};
use obvhs::cwbvh::node::{extract_byte64, CwBvhNode};

/// A packet whose rays spread beyond this cosine from the central
/// direction is not bundled (the side planes would bound little).
const MIN_COSINE: f64 = 0.25;

fn same_bits(a: Vec3, b: Vec3) -> bool {
    a.to_array().map(f32::to_bits) == b.to_array().map(f32::to_bits)
}

/// Relative widening of the side planes' slopes: far beyond the f64
/// rounding of the slopes and the f32 rounding of the normals (6e-8), so
/// every ray direction stays within the planes that are actually tested.
const SLOPE_MARGIN: f64 = 1e-6;

/// Six planes `n · x <= limit` that hold every point of every ray segment
/// of a packet; a box is culled when it lies entirely outside one of them.
#[derive(Clone, Debug)]
pub(crate) struct Beam {
    normals: [Vec3; 6],
    /// Plane offsets, already loosened by the padding and the evaluation
    /// error bound.
    limits: [f32; 6],
    /// Padding of the single-ray node test for these rays.
    #[cfg_attr(not(test), allow(dead_code))]
    pad: f32,
}

/// How far a packet's rays reach: the largest offset along each side
/// normal, and the nearest start and farthest end along the axis.
struct Extent {
    side_max: [f64; 4],
    near: f64,
    far: f64,
    /// The origin of the last ray added that starts at or after it (t_min
    /// ≥ 0): a ray from the same origin adds nothing to the sides (a spot
    /// or point light's packet shares one).
    last_origin: Option<[u32; 3]>,
}

impl Extent {
    fn empty() -> Extent {
        Extent {
            side_max: [f64::NEG_INFINITY; 4],
            near: f64::INFINITY,
            far: f64::NEG_INFINITY,
            last_origin: None,
        }
    }

    /// Widens the extent to hold `ray`'s segment (direction `d` in f64),
    /// given `along` = axis · d (the caller's, once per ray or once for a
    /// packet sharing one direction) and the side normals `n64`.
    fn add(
        &mut self,
        ray: &TraceRay,
        axis: DVec3,
        along: f64,
        n64: &[DVec3; 4],
        d: DVec3,
        pad: f32,
    ) {
        let o64 = ray.origin.as_dvec3();
        let o = axis.dot(o64);
        let t_min = f64::from(ray.t_min);
        self.near = self.near.min(
            o + if t_min.is_finite() {
                t_min * along
            } else {
                f64::NEG_INFINITY
            },
        );
        self.far = self
            .far
            .max(o + f64::from(node_t_max(ray.t_max, pad)) * along);
        // A segment starting behind its origin (t_min < 0) reaches back
        // past n · o by |t_min| · |n · d|.
        let back = f64::from(ray.t_min.min(0.0));
        let bits = ray.origin.to_array().map(f32::to_bits);
        if back == 0.0 && self.last_origin == Some(bits) {
            return;
        }
        self.last_origin = (back == 0.0).then_some(bits);
        for (m, n) in self.side_max.iter_mut().zip(n64) {
            let behind = if back < 0.0 {
                back * n.dot(d).min(0.0) * (1.0 + 1e-9)
            } else {
                0.0
            };
            *m = m.max(n.dot(o64) + behind);
        }
    }
}

/// The side planes' normals for the extreme slopes `slope_max` (along u,
/// −u, v, −v over the axis), widened by the slope margin and rounded to
/// f32 (kept in f64 for the offsets): n · d < 0 for every ray still (the
/// margin exceeds the rounding), so each ray's points stay at or below its
/// origin's n · o.
fn side_normals(axis: DVec3, u: DVec3, v: DVec3, slope_max: [f64; 4]) -> [DVec3; 4] {
    let sides = [u, -u, v, -v];
    std::array::from_fn(|k| {
        let slope = slope_max[k] + SLOPE_MARGIN * (1.0 + slope_max[k].abs());
        (sides[k] - axis * slope).as_vec3().as_dvec3()
    })
}

impl Beam {
    /// The beam of `rays` (each with its own `[t_min, t_max]`, t_max the
    /// running one), for boxes within `magnitude` of the origin of their
    /// frame. `None` when the packet is empty, not finite or too wide.
    pub(crate) fn new(
        rays: impl Iterator<Item = TraceRay> + Clone,
        magnitude: f32,
    ) -> Option<Beam> {
        // Any axis inside the cone of directions will do: their sum.
        let mut sum = DVec3::ZERO;
        let mut origin_max = 0.0f32;
        let mut first: Option<Vec3> = None;
        let mut parallel = true;
        for ray in rays.clone() {
            if !(ray.origin.is_finite() && ray.direction.is_finite()) || ray.t_min.is_nan() {
                return None;
            }
            sum += ray.direction.as_dvec3();
            origin_max = origin_max.max(ray.origin.abs().max_element());
            let bits = |v: Vec3| v.to_array().map(f32::to_bits);
            parallel &= first.is_none_or(|f| bits(f) == bits(ray.direction));
            first.get_or_insert(ray.direction);
        }
        let axis = sum.try_normalize()?;
        if parallel {
            return Beam::parallel(rays, axis, first?, magnitude, origin_max);
        }
        let pad = PAD_EPSILONS * f32::EPSILON * (magnitude + origin_max) + 1e-30;
        let (u, v) = perpendiculars(axis);
        // Each ray's direction in the (u, v, axis) frame: the side planes'
        // slopes are the extreme ratios u·d / axis·d.
        let mut slope_max = [f64::NEG_INFINITY; 4];
        for ray in rays.clone() {
            let d = ray.direction.as_dvec3();
            let along = axis.dot(d);
            if !(along > 0.0 && along * along > MIN_COSINE * MIN_COSINE * d.length_squared()) {
                return None;
            }
            let (su, sv) = (u.dot(d) / along, v.dot(d) / along);
            for (m, s) in slope_max.iter_mut().zip([su, -su, sv, -sv]) {
                *m = m.max(s);
            }
        }
        let n64 = side_normals(axis, u, v, slope_max);
        let mut extent = Extent::empty();
        for ray in rays {
            let d = ray.direction.as_dvec3();
            extent.add(&ray, axis, axis.dot(d), &n64, d, pad);
        }
        Some(Beam::of_planes(
            axis,
            n64,
            extent,
            pad,
            [magnitude, origin_max],
        ))
    }

    /// The beam of side normals `n64` (from [`side_normals`]) and the rays'
    /// `extent` along them and along `axis`, every plane loosened by the
    /// padding and by the f32 error of box tests with coordinates up to the
    /// sum of `magnitudes` (the boxes' and the origins').
    fn of_planes(
        axis: DVec3,
        n64: [DVec3; 4],
        extent: Extent,
        pad: f32,
        [boxes, origins]: [f32; 2],
    ) -> Beam {
        // Where the box test's f32 dot products may err: a few ulps of
        // the largest coordinate involved.
        let scale = f64::from(boxes) + f64::from(origins) + f64::from(pad);
        let mut normals = [Vec3::ZERO; 6];
        let mut limits = [0.0f32; 6];
        for k in 0..4 {
            normals[k] = n64[k].as_vec3();
            limits[k] = loosen(extent.side_max[k], n64[k], pad, scale);
        }
        // Caps along the axis: from the nearest start to the farthest end.
        let axis32 = axis.as_vec3();
        normals[4] = -axis32;
        limits[4] = loosen(-extent.near, -axis32.as_dvec3(), pad, scale);
        normals[5] = axis32;
        limits[5] = loosen(extent.far, axis32.as_dvec3(), pad, scale);
        Beam {
            normals,
            limits,
            pad,
        }
    }

    /// A beam holding every ray of a packet of a light's grid, made from
    /// only the rays through the corners of a rectangle of grid positions
    /// holding the packet's (`corners`, light-relative; the packet's rays
    /// go through texel or sub-texel centres inside it). `None` unless the
    /// corners share their span and either their direction (a directional
    /// light: parallel rays) or their origin (a spot or point light).
    ///
    /// Why it holds the packet's rays:
    /// - parallel rays: an inside ray's exact origin is a convex
    ///   combination of the corners' (the grid's origins are affine in the
    ///   texel position), so every plane offset it reaches (n · o, and
    ///   along the axis) is at most the corners' largest; each f32 origin
    ///   is rounded on its own, by at most half an ulp of the largest
    ///   coordinate per axis, which the planes are loosened by (four times
    ///   over);
    /// - rays from one origin: an inside ray's exact direction lies in the
    ///   cone of the corners' (texel positions map to directions affinely
    ///   before normalising), so its slopes against the axis are convex
    ///   combinations of theirs, and the caller keeps the rectangle half
    ///   a texel out from the rays' positions (its texels' edges), far
    ///   more than the f32 rounding of directions (`GRID_SLOPE_SLACK`);
    ///   its start along
    ///   the axis is no nearer (the cosine to an axis inside the cone is
    ///   least at a corner), but its end may be farther, so there is no far
    ///   cap.
    pub(crate) fn of_grid_corners(corners: &[TraceRay; 4], magnitude: f32) -> Option<Beam> {
        let first = corners[0];
        let alike = |f: fn(&TraceRay) -> Vec3| corners.iter().all(|r| same_bits(f(r), f(&first)));
        let span = corners.iter().all(|r| {
            r.t_min.to_bits() == first.t_min.to_bits() && r.t_max.to_bits() == first.t_max.to_bits()
        });
        let parallel = alike(|r| r.direction);
        if !(span && (parallel || alike(|r| r.origin))) {
            return None;
        }
        let mut beam = Beam::new(corners.iter().copied(), magnitude)?;
        let origin_max = corners
            .iter()
            .fold(0.0f32, |m, r| m.max(r.origin.abs().max_element()));
        let rounding = 4.0 * f64::from(f32::EPSILON) * f64::from(origin_max);
        for (limit, n) in beam.limits.iter_mut().zip(beam.normals) {
            let l1 = f64::from(n.abs().element_sum());
            let value = f64::from(*limit) + l1 * rounding;
            *limit = (value as f32).next_up();
        }
        if !parallel {
            beam.limits[5] = f32::INFINITY;
        }
        Some(beam)
    }

    /// [`Beam::new`] for rays that share their direction `direction` (a
    /// directional light's packet, in any frame): the side planes' slopes
    /// are the one direction's, so a single pass over the rays finds the
    /// planes' offsets and the caps. The same planes as the general
    /// construction, computed once instead of per ray.
    fn parallel(
        rays: impl Iterator<Item = TraceRay>,
        axis: DVec3,
        direction: Vec3,
        magnitude: f32,
        origin_max: f32,
    ) -> Option<Beam> {
        let pad = PAD_EPSILONS * f32::EPSILON * (magnitude + origin_max) + 1e-30;
        let (u, v) = perpendiculars(axis);
        let d = direction.as_dvec3();
        let along = axis.dot(d);
        if !(along > 0.0 && along * along > MIN_COSINE * MIN_COSINE * d.length_squared()) {
            return None;
        }
        let (su, sv) = (u.dot(d) / along, v.dot(d) / along);
        let n64 = side_normals(axis, u, v, [su, -su, sv, -sv]);
        let mut extent = Extent::empty();
        for ray in rays {
            extent.add(&ray, axis, along, &n64, d, pad);
        }
        Some(Beam::of_planes(
            axis,
            n64,
            extent,
            pad,
            [magnitude, origin_max],
        ))
    }

    /// This beam mapped into an instance's model space, for rays mapped by
    /// `to_model` (and rounded to f32 there; `world` is
    /// [`ToModel::world_linear`]) and boxes within `magnitude`
    /// of the model's origin; `origin_max` bounds the mapped origins. A
    /// plane n · x <= c becomes (Wᵀn) · y <= c + (Wᵀn) · offset for the
    /// world-linear map W (y = L x + offset, W = L⁻¹). The model-space
    /// padding covers the rounding of the mapped rays (a few ulps of the
    /// model-space coordinates), as it does for the single-ray test;
    /// `None` if the map is not finite.
    pub(crate) fn to_model(
        &self,
        to_model: &ToModel,
        world: DMat3,
        magnitude: f32,
        origin_max: f32,
    ) -> Option<Beam> {
        let (_, offset) = to_model.parts();
        if !world.is_finite() {
            return None;
        }
        let pad = PAD_EPSILONS * f32::EPSILON * (magnitude + origin_max) + 1e-30;
        let scale = f64::from(magnitude) + f64::from(origin_max) + f64::from(pad);
        let mut normals = [Vec3::ZERO; 6];
        let mut limits = [0.0f32; 6];
        for k in 0..6 {
            let n = world.transpose() * self.normals[k].as_dvec3();
            let n32 = n.as_vec3();
            let limit = f64::from(self.limits[k]) + n.dot(offset);
            if !n32.is_finite() {
                return None;
            }
            normals[k] = n32;
            // The error of the inverse, relative to the terms involved.
            let l1 = n.abs().element_sum();
            let inverse_error = 1e-12 * (limit.abs() + l1 * (scale + offset.abs().max_element()));
            limits[k] = loosen(limit + inverse_error, n32.as_dvec3(), 2.0 * pad, scale);
        }
        Some(Beam {
            normals,
            limits,
            pad,
        })
    }

    /// Whether any ray of the packet may touch the box (grown by the
    /// padding). NaN counts as a touch.
    #[inline(always)]
    pub(crate) fn touches(&self, min: Vec3, max: Vec3) -> bool {
        for k in 0..6 {
            let n = self.normals[k];
            let x = if n.x > 0.0 { min.x } else { max.x };
            let y = if n.y > 0.0 { min.y } else { max.y };
            let z = if n.z > 0.0 { min.z } else { max.z };
            if n.x * x + n.y * y + n.z * z > self.limits[k] {
                return false;
            }
        }
        true
    }

    /// obvhs's hit mask for the children of `node` the beam may touch;
    /// with AVX2 when the processor has it (the same arithmetic).
    #[inline]
    pub(crate) fn hitmask(&self, node: &CwBvhNode, oct_inv4: u32) -> u32 {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the processor has AVX2 (checked just above).
            return unsafe { self.hitmask_avx2(node, oct_inv4) };
        }
        self.hitmask_inline(node, oct_inv4)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn hitmask_avx2(&self, node: &CwBvhNode, oct_inv4: u32) -> u32 {
        self.hitmask_inline(node, oct_inv4)
    }

    /// The eight children's boxes decoded as obvhs does (`q · extent + p`)
    /// and tested against the six planes, child by child in lanes.
    // Children index several arrays in lockstep: the form that vectorizes.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn hitmask_inline(&self, node: &CwBvhNode, oct_inv4: u32) -> u32 {
        let e = node.compute_extent();
        let decode = |q: &[u8; 8], e: f32, p: f32| q.map(|v| v as f32 * e + p);
        let lo = [
            decode(&node.child_min_x, e.x, node.p.x),
            decode(&node.child_min_y, e.y, node.p.y),
            decode(&node.child_min_z, e.z, node.p.z),
        ];
        let hi = [
            decode(&node.child_max_x, e.x, node.p.x),
            decode(&node.child_max_y, e.y, node.p.y),
            decode(&node.child_max_z, e.z, node.p.z),
        ];
        let mut outside = [false; 8];
        for k in 0..6 {
            let n = self.normals[k].to_array();
            let pick = |i: usize| if n[i] > 0.0 { &lo[i] } else { &hi[i] };
            let (x, y, z) = (pick(0), pick(1), pick(2));
            let limit = self.limits[k];
            for c in 0..8 {
                outside[c] |= n[0] * x[c] + n[1] * y[c] + n[2] * z[c] > limit;
            }
        }
        let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
        let mut hit_mask = 0;
        for (c, &out) in outside.iter().enumerate() {
            if !out {
                hit_mask |= extract_byte64(child_bits8, c) << extract_byte64(bit_index8, c);
            }
        }
        hit_mask
    }

    #[cfg(test)]
    pub(crate) fn pad(&self) -> f32 {
        self.pad
    }
}

/// `BoxRay::node_t_max` for padding `pad`: t_max plus slack for hits whose
/// computed t lies within t_max while the exact point lies beyond.
#[inline]
fn node_t_max(t_max: f32, pad: f32) -> f32 {
    t_max + 4.0 * pad + t_max.abs() * (1.0 / 65536.0)
}

/// Plane offset `limit` for normal `n` (its f32 value, exactly in f64),
/// loosened by the box padding (a box grown by `pad` reaches `pad·|n|₁`
/// further along n) and by a bound on the error of the f32 dot product of
/// n with coordinates up to `scale`, rounded up to f32.
fn loosen(limit: f64, n: DVec3, pad: f32, scale: f64) -> f32 {
    let l1 = n.x.abs() + n.y.abs() + n.z.abs();
    let slack = l1 * (f64::from(pad) + 8.0 * f64::from(f32::EPSILON) * scale);
    let value = limit + slack + 1e-12 * limit.abs();
    if value.is_nan() {
        return f32::INFINITY;
    }
    let f = value as f32;
    if f64::from(f) < value {
        f.next_up()
    } else {
        f
    }
}

/// Two unit vectors perpendicular to `axis` and to each other.
fn perpendiculars(axis: DVec3) -> (DVec3, DVec3) {
    let helper = if axis.x.abs() < 0.6 {
        DVec3::X
    } else {
        DVec3::Y
    };
    let u = axis.cross(helper).normalize();
    (u, axis.cross(u))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::vec3;

    fn ray(o: Vec3, d: Vec3, t_max: f32) -> TraceRay {
        TraceRay {
            origin: o,
            direction: d.normalize(),
            t_min: 0.0,
            t_max,
        }
    }

    /// A box just outside the packet's extreme ray, by less than the
    /// padding, is still touched; one farther out is not. Taking the
    /// padding out of the beam fails this.
    #[test]
    fn boxes_within_the_padding_of_the_extreme_ray_are_touched() {
        let rays: Vec<TraceRay> = (0..4)
            .flat_map(|i| (0..4).map(move |j| (i, j)))
            .map(|(i, j)| ray(vec3(i as f32, 50.0, j as f32), Vec3::NEG_Y, f32::INFINITY))
            .collect();
        let beam = Beam::new(rays.iter().copied(), 100.0).unwrap();
        let pad = beam.pad();
        assert!(pad > 1e-3, "{pad}");
        // The rays' largest x is 3 (and z 3): boxes beside them.
        for (x, touched) in [(3.0 + 0.5 * pad, true), (3.0 + 2.0 * pad, false)] {
            let reach = beam.touches(vec3(x, -1.0, 1.0), vec3(x + 1.0, 1.0, 2.0));
            assert_eq!(reach, touched, "x {x}");
            let reach = beam.touches(vec3(1.0, -1.0, x), vec3(2.0, 1.0, x + 1.0));
            assert_eq!(reach, touched, "z {x}");
            let reach = beam.touches(vec3(-1.0, -1.0, 1.0), vec3(3.0 - x, 1.0, 2.0));
            assert_eq!(reach, touched, "-x {x}");
        }
        // Above the origins: only the padding reaches it.
        assert!(beam.touches(vec3(1.0, 50.0 + 0.5 * pad, 1.0), vec3(2.0, 51.0, 2.0)));
        assert!(!beam.touches(vec3(1.0, 50.0 + 2.0 * pad, 1.0), vec3(2.0, 51.0, 2.0)));
        assert!(beam.touches(vec3(1.0, -80.0, 1.0), vec3(2.0, -79.0, 2.0)));
    }

    /// A light's packet of `side`² texels at `(x0, y0)`, `samples`² rays
    /// a texel, as the grid makes them (f64, then rounded to f32), and the
    /// rays through its rectangle's corners (`inset`: texels in from the
    /// edges, 0 for the real corners). `frame`: the light's axes.
    struct GridPacket {
        perspective: bool,
        frame: [DVec3; 3],
        /// Directional: texel size and first origin; perspective: the
        /// face's half extent and resolution.
        scale: f64,
        base: DVec3,
        resolution: f64,
    }

    impl GridPacket {
        fn ray_at(&self, cx: f64, cy: f64) -> TraceRay {
            let [forward, u, v] = self.frame;
            if self.perspective {
                let s = self.scale * (cx / self.resolution * 2.0 - 1.0);
                let t = self.scale * (cy / self.resolution * 2.0 - 1.0);
                let d = (forward + u * s + v * t).normalize();
                TraceRay {
                    origin: Vec3::ZERO,
                    direction: d.as_vec3(),
                    t_min: 0.1,
                    t_max: 80.0,
                }
            } else {
                let o = self.base + u * (cx * self.scale) + v * (cy * self.scale);
                TraceRay {
                    origin: o.as_vec3(),
                    direction: forward.as_vec3(),
                    t_min: 0.0,
                    t_max: 900.0,
                }
            }
        }
    }

    /// Every ray of a grid packet (through texel or sub-texel centres)
    /// lies in the beam of the rays through the packet's corners, out to
    /// its far end: parallel rays (far from the origin; corners at the
    /// outermost ray positions) and rays from one point (up to 45° off
    /// their face's axis; corners at the texels' edges). Keeping a far cap
    /// for rays from one point fails this (the middle rays reach farther
    /// along the axis than the corners), and so does taking their corners
    /// at the texels' centres, or a directional light's a sample further
    /// in.
    #[test]
    fn a_grid_packets_rays_lie_in_the_beam_of_its_corners() {
        let mut rng = crate::rng::Rng::new(41);
        for case in 0..400 {
            let perspective = case % 2 == 1;
            let forward = rng.unit_vector();
            let u = forward.any_orthonormal_vector();
            let frame = [forward, u, forward.cross(u)];
            let resolution = [16.0, 64.0, 256.0][rng.below(3)];
            let grid = GridPacket {
                perspective,
                frame,
                scale: if perspective {
                    rng.range(0.2, 1.0)
                } else {
                    rng.range(0.5, 2.0)
                },
                base: DVec3::new(
                    rng.range(-300.0, 300.0),
                    rng.range(-300.0, 300.0),
                    rng.range(-300.0, 300.0),
                ),
                resolution,
            };
            let side = [1, 3, 8][rng.below(3)];
            let samples = 1 + rng.below(2);
            let x0 = rng.below(resolution as usize - side) as f64;
            let y0 = rng.below(resolution as usize - side) as f64;
            let (x1, y1) = (x0 + side as f64, y0 + side as f64);
            // As the bake takes them: a directional light's through the
            // outermost ray positions, a perspective light's through the
            // texels' edges.
            let inset = if perspective {
                0.0
            } else {
                0.5 / samples as f64
            };
            let (lo, hi) = ((x0 + inset, y0 + inset), (x1 - inset, y1 - inset));
            let corners = [(lo.0, lo.1), (hi.0, lo.1), (lo.0, hi.1), (hi.0, hi.1)]
                .map(|(x, y)| grid.ray_at(x, y));
            let beam = Beam::of_grid_corners(&corners, 100.0).expect("a grid packet's beam");
            let step = 1.0 / samples as f64;
            for j in 0..side * samples {
                for i in 0..side * samples {
                    let cx = x0 + (i as f64 + 0.5) * step;
                    let cy = y0 + (j as f64 + 0.5) * step;
                    let r = grid.ray_at(cx, cy);
                    for t in [r.t_min, 0.5 * (r.t_min + r.t_max), r.t_max] {
                        let p = r.origin + r.direction * t;
                        assert!(beam.touches(p, p), "case {case}: {p} at t {t} of {r:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn frusta_cull_beside_and_behind_and_keep_what_rays_reach() {
        let o = vec3(5.0, 20.0, -3.0);
        let rays: Vec<TraceRay> = (0..8)
            .flat_map(|i| (0..8).map(move |j| (i, j)))
            .map(|(i, j)| ray(o, vec3(i as f32 * 0.02 - 0.07, -1.0, j as f32 * 0.02), 30.0))
            .collect();
        let beam = Beam::new(rays.iter().copied(), 100.0).unwrap();
        for r in &rays {
            for t in [0.5f32, 7.0, 29.0] {
                let p = r.origin + r.direction * t;
                let e = Vec3::splat(1e-3);
                assert!(beam.touches(p - e, p + e), "{p} of {r:?}");
            }
        }
        // Behind the origin, beside the frustum, beyond t_max.
        assert!(!beam.touches(o + vec3(-1.0, 1.0, -1.0), o + vec3(1.0, 2.0, 1.0)));
        assert!(!beam.touches(o + vec3(5.0, -10.0, 0.0), o + vec3(6.0, -9.0, 1.0)));
        assert!(!beam.touches(o + vec3(-1.0, -40.0, -1.0), o + vec3(1.0, -35.0, 1.0)));
    }

    #[test]
    fn wide_empty_and_nan_packets_are_declined() {
        let up = ray(Vec3::ZERO, Vec3::Y, 1.0);
        let down = ray(Vec3::ZERO, Vec3::NEG_Y, 1.0);
        assert!(Beam::new([up, down].into_iter(), 10.0).is_none());
        assert!(Beam::new(std::iter::empty(), 10.0).is_none());
        let mut nan = up;
        nan.origin.x = f32::NAN;
        assert!(Beam::new([up, nan].into_iter(), 10.0).is_none());
    }
}
