//! Shadow-map texel grids of the three light kinds (docs/contract.md §3–§4).
//!
//! The bake casts one ray through the centre of every texel of every light's
//! shadow map. This module decides where those texels are: it turns a
//! validated `LightSettings` (plus, for a directional light, the bounds of the
//! world it must cover) into a [`TexelGrid`] that hands out the ray of any
//! texel as a pure function of `(face, x, y)`, so any thread computes the same
//! ray and the bake is deterministic whatever the thread count. It also
//! answers whether a box can be reached by the light at all, so geometry
//! outside a light's frustum can be left out of that light's BVH (docs/contract.md §7).
//!
//! Conventions (fixed; the report and the rasterized cross-check rely on
//! them):
//! - Texel `(x, y)` of a face lies at image coordinates
//!   `s = k·((x + 0.5)/w·2 − 1)`, `t = k·((y + 0.5)/h·2 − 1)` along the face's
//!   basis vectors `u` (x grows with `u`) and `v` (y grows with `v`), where `k`
//!   is `tan(fov/2)` for a spot light and 1 for a cube face. `(u, v)` come
//!   from [`orthonormal_basis`], so `u × v` is the face's forward axis.
//! - A point light has six faces in the order +X, −X, +Y, −Y, +Z, −Z, each
//!   the 90° frustum around its axis with the basis `orthonormal_basis(axis)`:
//!
//!   | face | axis | u | v |
//!   |---|---|---|---|
//!   | 0 | +X | −Z | +Y |
//!   | 1 | −X | +Z | +Y |
//!   | 2 | +Y | +X | −Z |
//!   | 3 | −Y | +X | +Z |
//!   | 4 | +Z | +X | +Y |
//!   | 5 | −Z | +X | −Y |
//!
//! - A directional light's texel `(x, y)` is centred at light-plane
//!   coordinates `(u_min + (x + 0.5)·texelSize, v_min + (y + 0.5)·texelSize)`
//!   where `u_min`, `v_min` are the smallest projections of the world bounds'
//!   corners on `u`, `v`.
//! - Linear texel indices ([`TexelGrid::texel_at`]) run over faces, then
//!   rows (`y`), then columns (`x`).
//!
//! Rays are unit length, so `t` is a distance in metres; spot and point rays
//! keep hits with `near <= t <= far` (distance along the ray, not depth).

mod basis;

pub use basis::orthonormal_basis;

use crate::formats::bake_settings::{LightKind, LightSettings};
use glam::DVec3;

/// Largest shadow map side, in texels: a 0.1 m sun over a 10 km world
/// (96×96 chunks, 116 870 × 111 968 texels) fits with room to spare.
/// Texel coordinates are `u32` and linear indices `u64`, so both limits are
/// far from any overflow.
pub const MAX_SIDE: u64 = 1 << 18;
/// Largest number of texels of one light (all faces together): 68.7 G rays,
/// a distributed bake's size. What a grid allocates grows with its 32×32
/// tiles, not its texels (a shard's plan keeps 8 bytes per tile: 537 MB at
/// this limit).
pub const MAX_TEXELS: u64 = 1 << 36;

/// Cube faces of a point light, as `(axis, u, v)`; see the module docs.
/// `u` and `v` are what `orthonormal_basis(axis)` returns (a test checks it),
/// written out so the table is documentation too.
const CUBE_FACES: [(DVec3, DVec3, DVec3); 6] = [
    (DVec3::X, DVec3::NEG_Z, DVec3::Y),
    (DVec3::NEG_X, DVec3::Z, DVec3::Y),
    (DVec3::Y, DVec3::X, DVec3::NEG_Z),
    (DVec3::NEG_Y, DVec3::X, DVec3::Z),
    (DVec3::Z, DVec3::X, DVec3::Y),
    (DVec3::NEG_Z, DVec3::X, DVec3::NEG_Y),
];

/// Short names of the cube faces, for messages and reports.
pub const CUBE_FACE_NAMES: [&str; 6] = ["+X", "-X", "+Y", "-Y", "+Z", "-Z"];

/// Distance (metres) by which a directional light's ray origins sit in front
/// of the nearest point of the world, before the relative part is added.
const DIRECTIONAL_MARGIN: f64 = 1.0;
/// Relative part of that margin (times the world's coordinate magnitude), so
/// the origins stay clear of the geometry in worlds far from the origin.
const RELATIVE_MARGIN: f64 = 1e-6;
/// Relative slack of [`TexelGrid::reaches`], far larger than the rounding of
/// its f64 arithmetic, so it never rejects a box a ray can enter.
const REACH_SLACK: f64 = 1e-9;

/// One texel's ray: hits count for `t_min <= t <= t_max`, with the hit point
/// `origin + t·direction` (world coordinates, metres).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TexelRay {
    pub origin: DVec3,
    /// Unit length.
    pub direction: DVec3,
    pub t_min: f64,
    pub t_max: f64,
}

impl TexelRay {
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + self.direction * t
    }
}

/// Why a light's grid cannot be built. Each names the light.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GridError {
    #[error(
        "light `{light}`: the world has no extent to cover (bounds min {min}, max {max}); \
         a directional light's grid covers the world's geometry and terrain, so the space \
         needs at least one loaded model or terrain block"
    )]
    EmptyWorld {
        light: String,
        min: DVec3,
        max: DVec3,
    },
    #[error(
        "light `{light}`: the shadow map would be {faces} × {width} × {height} texels, more than \
         the limit of {MAX_SIDE} per side and {MAX_TEXELS} in total; {}",
        too_large_fix(.light_type)
    )]
    TooLarge {
        light: String,
        light_type: &'static str,
        faces: u64,
        width: u64,
        height: u64,
    },
    #[error("light `{light}`: {message}")]
    BadLight { light: String, message: String },
}

fn too_large_fix(light_type: &str) -> &'static str {
    if light_type == "directional" {
        "raise <texelSize> (metres per texel)"
    } else {
        "lower <resolution>"
    }
}

/// A triangle projected on a face (texel units and depth per vertex): three
/// points, or four where a perspective face's near plane cuts a corner off.
/// Held inline: refinement and the conservative bake project every triangle
/// they look at.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProjectedPolygon {
    points: [(f64, f64, f64); 4],
    len: usize,
}

impl std::ops::Deref for ProjectedPolygon {
    type Target = [(f64, f64, f64)];

    fn deref(&self) -> &Self::Target {
        &self.points[..self.len]
    }
}

impl ProjectedPolygon {
    fn push(&mut self, point: (f64, f64, f64)) {
        self.points[self.len] = point;
        self.len += 1;
    }

    /// The polygon without its depths.
    pub fn flat(&self) -> FacePolygon {
        let mut points = [(0.0, 0.0); 4];
        for (point, &(x, y, _)) in points.iter_mut().zip(self.iter()) {
            *point = (x, y);
        }
        FacePolygon {
            points,
            len: self.len,
        }
    }
}

/// A [`ProjectedPolygon`] without its depths (texel units), also inline.
#[derive(Debug, Clone, Copy)]
pub struct FacePolygon {
    points: [(f64, f64); 4],
    len: usize,
}

impl std::ops::Deref for FacePolygon {
    type Target = [(f64, f64)];

    fn deref(&self) -> &Self::Target {
        &self.points[..self.len]
    }
}

/// Where a box projects on one face of a grid ([`TexelGrid::box_image`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum BoxImage {
    /// No ray of the face can reach it (or it is not a finite box).
    Nowhere,
    /// It reaches behind the face's plane: anywhere on the face.
    WholeFace,
    /// Within `(x0, y0, x1, y1)` (texel units, not clipped to the face).
    Rect(f64, f64, f64, f64),
}

/// A light's shadow map: `faces × height × width` texels, each with one ray
/// through its centre.
#[derive(Debug, Clone)]
pub struct TexelGrid {
    projection: Projection,
    faces: usize,
    width: u32,
    height: u32,
    reference: DVec3,
    /// Every ray position moved by this much (texel units, each in
    /// [−½, ½)); see [`TexelGrid::with_offset`].
    offset: (f64, f64),
}

#[derive(Debug, Clone)]
enum Projection {
    Orthographic {
        direction: DVec3,
        u: DVec3,
        v: DVec3,
        /// Light-plane coordinates of the grid's lower edges.
        u_min: f64,
        v_min: f64,
        texel_size: f64,
        /// `p·direction` of every ray origin.
        w_origin: f64,
        t_max: f64,
    },
    Perspective {
        position: DVec3,
        near: f64,
        far: f64,
        /// Half-width of the image plane at distance 1.
        half_extent: f64,
        /// `(forward, u, v)` of a spot light's only face.
        frame: (DVec3, DVec3, DVec3),
        /// A point light: the faces are [`CUBE_FACES`] and cover every
        /// direction, so `reaches` need not test a pyramid.
        cube: bool,
    },
}

impl TexelGrid {
    /// Builds the grid of `light`. `world_bounds` are the min and max corners
    /// of everything that can be hit (every chunk's geometry and terrain); only
    /// a directional light uses them, and it fails with
    /// [`GridError::EmptyWorld`] when they are empty or not finite. A world of
    /// zero size (one flat plane, or a point) still gets at least one texel
    /// per side.
    pub fn new(
        light: &LightSettings,
        world_bounds: (DVec3, DVec3),
    ) -> Result<TexelGrid, GridError> {
        let bad = |message: String| GridError::BadLight {
            light: light.name.clone(),
            message,
        };
        match light.kind {
            LightKind::Directional {
                direction,
                texel_size,
            } => {
                let direction = unit(direction).ok_or_else(|| {
                    bad(format!(
                        "direction {direction} has no length; give a non-zero finite <direction>"
                    ))
                })?;
                if !(texel_size.is_finite() && texel_size > 0.0) {
                    return Err(bad(format!(
                        "<texelSize> must be a finite number > 0, found {texel_size}"
                    )));
                }
                Self::directional(light, direction, texel_size, world_bounds)
            }
            LightKind::Spot {
                position,
                direction,
                fov_degrees,
                near,
                far,
                resolution,
            } => {
                let direction = unit(direction).ok_or_else(|| {
                    bad(format!(
                        "direction {direction} has no length; give a non-zero finite <direction>"
                    ))
                })?;
                if !(fov_degrees > 0.0 && fov_degrees < 180.0) {
                    return Err(bad(format!(
                        "spot light <fov> must be in (0, 180) degrees, found {fov_degrees}"
                    )));
                }
                check_perspective(&light.name, position, near, far, resolution, 1)?;
                let (u, v) = orthonormal_basis(direction);
                Ok(TexelGrid {
                    projection: Projection::Perspective {
                        position,
                        near,
                        far,
                        half_extent: (fov_degrees.to_radians() * 0.5).tan(),
                        frame: (direction, u, v),
                        cube: false,
                    },
                    faces: 1,
                    width: resolution,
                    height: resolution,
                    reference: position,
                    offset: (0.0, 0.0),
                })
            }
            LightKind::Point {
                position,
                near,
                far,
                resolution,
            } => {
                check_perspective(&light.name, position, near, far, resolution, 6)?;
                Ok(TexelGrid {
                    projection: Projection::Perspective {
                        position,
                        near,
                        far,
                        // tan(45°) is 1; written exactly rather than computed.
                        half_extent: 1.0,
                        frame: CUBE_FACES[0],
                        cube: true,
                    },
                    faces: 6,
                    width: resolution,
                    height: resolution,
                    reference: position,
                    offset: (0.0, 0.0),
                })
            }
        }
    }

    fn directional(
        light: &LightSettings,
        direction: DVec3,
        texel_size: f64,
        (min, max): (DVec3, DVec3),
    ) -> Result<TexelGrid, GridError> {
        // `!(min <= max)` also catches NaN.
        if !(min.is_finite() && max.is_finite() && min.cmple(max).all()) {
            return Err(GridError::EmptyWorld {
                light: light.name.clone(),
                min,
                max,
            });
        }
        let (u, v) = orthonormal_basis(direction);
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for corner in corners(min, max) {
            let p = DVec3::new(corner.dot(u), corner.dot(v), corner.dot(direction));
            lo = lo.min(p);
            hi = hi.max(p);
        }
        let side = |lo: f64, hi: f64| -> u64 {
            // Float division can land a hair under the true quotient; grow the
            // count until the grid's far edge really reaches `hi`. Saturating
            // casts keep absurd sizes finite for the error message.
            let mut n = ((hi - lo) / texel_size).ceil().max(1.0) as u64;
            while n <= MAX_SIDE && lo + n as f64 * texel_size < hi {
                n += 1;
            }
            n
        };
        let width = side(lo.x, hi.x);
        let height = side(lo.y, hi.y);
        check_size(light, 1, width, height)?;

        let scale = min.abs().max(max.abs()).max_element().max(hi.z - lo.z);
        let margin = DIRECTIONAL_MARGIN + RELATIVE_MARGIN * scale;
        let w_origin = lo.z - margin;
        Ok(TexelGrid {
            projection: Projection::Orthographic {
                direction,
                u,
                v,
                u_min: lo.x,
                v_min: lo.y,
                texel_size,
                w_origin,
                t_max: (hi.z - w_origin) + margin,
            },
            faces: 1,
            width: width as u32,
            height: height as u32,
            reference: (min + max) * 0.5,
            offset: (0.0, 0.0),
        })
    }

    /// The same light's grid moved by a sub-texel `offset` (texel units,
    /// each coordinate wrapped into [−½, ½)): where the game's shadow map
    /// may sample instead, since cascades snap to their own texel grid.
    /// Every ray position `(cx, cy)` of [`Self::ray_through`] moves to
    /// `(cx + offset)`, so texel `(x, y)`'s centre ray passes anywhere
    /// within its own square: the texels (and a directional grid's cover of
    /// the world) stay where they are, only the sample points move.
    /// Deterministic: the sweep's offset references and the tests choose
    /// offsets from a seed.
    pub fn with_offset(mut self, offset: (f64, f64)) -> TexelGrid {
        let wrap = |o: f64| {
            if o.is_finite() {
                (o + 0.5).rem_euclid(1.0) - 0.5
            } else {
                0.0
            }
        };
        self.offset = (wrap(offset.0), wrap(offset.1));
        self
    }

    /// 1, or 6 for a point light.
    pub fn faces(&self) -> usize {
        self.faces
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// `faces × width × height`; at most [`MAX_TEXELS`].
    pub fn texel_count(&self) -> u64 {
        self.faces as u64 * self.width as u64 * self.height as u64
    }

    /// The texel with linear index `index` (faces, then rows, then columns),
    /// or `None` past the end. Lets a parallel bake split `0..texel_count()`
    /// into ranges.
    pub fn texel_at(&self, index: u64) -> Option<(usize, u32, u32)> {
        if index >= self.texel_count() {
            return None;
        }
        let per_face = self.width as u64 * self.height as u64;
        let face = index / per_face;
        let rest = index % per_face;
        let y = rest / self.width as u64;
        let x = rest % self.width as u64;
        Some((face as usize, x as u32, y as u32))
    }

    /// The ray through the centre `(x + 0.5, y + 0.5)` of texel `(x, y)` of
    /// `face`; a pure function of its arguments.
    ///
    /// The arguments should be in range (debug builds assert it). Out of
    /// range, `x` and `y` extrapolate the grid and `face` is taken modulo
    /// [`faces`](Self::faces), so a caller's mistake gives a wrong ray, never
    /// a panic.
    pub fn ray(&self, face: usize, x: u32, y: u32) -> TexelRay {
        debug_assert!(
            face < self.faces && x < self.width && y < self.height,
            "texel ({face}, {x}, {y}) outside a {}×{}×{} grid",
            self.faces,
            self.width,
            self.height
        );
        self.ray_through(face, x as f64 + 0.5, y as f64 + 0.5)
    }

    /// The `samples`² rays of texel `(face, x, y)`: 1 gives its centre, k a
    /// k×k pattern of sub-texel centres (the same rays as a k× denser grid).
    pub fn texel_rays(
        &self,
        face: usize,
        x: u32,
        y: u32,
        samples: u32,
    ) -> impl ExactSizeIterator<Item = TexelRay> + '_ {
        let samples = samples.max(1);
        let step = 1.0 / samples as f64;
        // One flat range (rows of samples, x fastest): its exact length lets
        // a packet's rays be written straight into place.
        (0..samples * samples).map(move |i| {
            let (sx, sy) = (i % samples, i / samples);
            self.ray_through(
                face,
                x as f64 + (sx as f64 + 0.5) * step,
                y as f64 + (sy as f64 + 0.5) * step,
            )
        })
    }

    /// The ray through grid position (`cx`, `cy`) of `face`, in texel units
    /// (texel (x, y) spans [x, x+1) × [y, y+1); its centre is (x+0.5,
    /// y+0.5)): supersampling traces several per texel.
    pub fn ray_through(&self, face: usize, cx: f64, cy: f64) -> TexelRay {
        let direction = self.unit_depth_direction(face, cx, cy);
        let (cx, cy) = (cx + self.offset.0, cy + self.offset.1);
        match &self.projection {
            Projection::Orthographic {
                direction,
                u,
                v,
                u_min,
                v_min,
                texel_size,
                w_origin,
                t_max,
            } => {
                let pu = u_min + cx * texel_size;
                let pv = v_min + cy * texel_size;
                TexelRay {
                    origin: *u * pu + *v * pv + *direction * *w_origin,
                    direction: *direction,
                    t_min: 0.0,
                    t_max: *t_max,
                }
            }
            Projection::Perspective {
                position,
                near,
                far,
                ..
            } => TexelRay {
                origin: *position,
                direction: direction.normalize(),
                t_min: *near,
                t_max: *far,
            },
        }
    }

    /// The light's ray through world point `p` (for refinement rays aimed at
    /// a caster's own surface), or `None` when the shadow map does not cover
    /// `p`: outside a directional grid's extent, outside a spot light's
    /// pyramid, or not between `near` and `far`. The ray starts where the
    /// texel rays start (the origin plane, or the light position), so it is
    /// filtered and classified exactly like them.
    pub fn ray_toward(&self, p: DVec3) -> Option<TexelRay> {
        if !p.is_finite() {
            return None;
        }
        match &self.projection {
            Projection::Orthographic {
                direction,
                u,
                v,
                u_min,
                v_min,
                texel_size,
                w_origin,
                t_max,
            } => {
                let (pu, pv) = (p.dot(*u), p.dot(*v));
                let inside = |value: f64, min: f64, count: u32| {
                    value >= min && value <= min + count as f64 * texel_size
                };
                if !inside(pu, *u_min, self.width) || !inside(pv, *v_min, self.height) {
                    return None;
                }
                let origin = *u * pu + *v * pv + *direction * *w_origin;
                Some(TexelRay {
                    origin,
                    direction: *direction,
                    t_min: 0.0,
                    t_max: *t_max,
                })
            }
            Projection::Perspective {
                position,
                near,
                far,
                half_extent,
                frame,
                cube,
            } => {
                let offset = p - *position;
                let distance = offset.length();
                if !(distance >= *near && distance <= *far) {
                    return None;
                }
                let direction = offset / distance;
                if !*cube {
                    let (forward, u, v) = *frame;
                    let depth = direction.dot(forward);
                    if depth <= 0.0
                        || direction.dot(u).abs() > half_extent * depth
                        || direction.dot(v).abs() > half_extent * depth
                    {
                        return None;
                    }
                }
                Some(TexelRay {
                    origin: *position,
                    direction,
                    t_min: *near,
                    t_max: *far,
                })
            }
        }
    }

    /// A directional light's unit direction; `None` for spot and point
    /// lights (their rays' directions vary).
    pub fn direction(&self) -> Option<DVec3> {
        match &self.projection {
            Projection::Orthographic { direction, .. } => Some(*direction),
            Projection::Perspective { .. } => None,
        }
    }

    /// A directional light's texel size in metres; `None` for spot and
    /// point lights.
    pub fn texel_size(&self) -> Option<f64> {
        match &self.projection {
            Projection::Orthographic { texel_size, .. } => Some(*texel_size),
            Projection::Perspective { .. } => None,
        }
    }

    /// World point `p` on `face` in texel units (see
    /// [`Self::project_triangle`]), or `None` when it lies too near the
    /// light's plane (or behind it) for any ray of the face to reach it.
    pub fn project_point(&self, face: usize, p: DVec3) -> Option<(f64, f64)> {
        if let Projection::Orthographic { .. } = self.projection {
            // What the triangle's path gives, with one projection, not three.
            return self.project_point_directional(p);
        }
        let polygon = self.project_triangle(face, [p, p, p])?;
        (polygon.len() == 3).then(|| polygon[0])
    }

    /// The ray direction through image position `(cx, cy)` of `face`
    /// (texel units, as [`Self::ray_through`] takes them), not normalised
    /// for a perspective face: unit depth along its axis, so its length is
    /// the factor from depth z to distance t. A directional light's unit
    /// direction.
    pub fn unit_depth_direction(&self, face: usize, cx: f64, cy: f64) -> DVec3 {
        let (cx, cy) = (cx + self.offset.0, cy + self.offset.1);
        match &self.projection {
            Projection::Orthographic { direction, .. } => *direction,
            Projection::Perspective {
                half_extent,
                frame,
                cube,
                ..
            } => {
                let (forward, u, v) = face_axes(*frame, *cube, face);
                let s = half_extent * (cx / self.width as f64 * 2.0 - 1.0);
                let t = half_extent * (cy / self.height as f64 * 2.0 - 1.0);
                forward + u * s + v * t
            }
        }
    }

    /// A perspective light's `near` and `far`; `None` for a directional
    /// light (its rays cover the whole world).
    pub fn near_far(&self) -> Option<(f64, f64)> {
        match &self.projection {
            Projection::Orthographic { .. } => None,
            Projection::Perspective { near, far, .. } => Some((*near, *far)),
        }
    }

    /// The part of triangle `triangle` (world points) that rays of `face`
    /// can hit, projected to the face in texel units (texel (x, y) spans
    /// [x, x+1) × [y, y+1)): a convex polygon, not clipped to the face.
    /// For a perspective face the triangle is first clipped to depths
    /// (along the face's axis) of at least `near` / (the longest unit-depth
    /// ray of the face), below which no ray reaches `near`. `None`: no part
    /// of it can be hit from this face, or a vertex is not finite.
    pub fn project_triangle(&self, face: usize, triangle: [DVec3; 3]) -> Option<Vec<(f64, f64)>> {
        let polygon = self.project_triangle_with_depth(face, triangle)?;
        Some(polygon.iter().map(|&(x, y, _)| (x, y)).collect())
    }

    /// A directional light's image position (texel units) of `p`, as
    /// [`Self::project_triangle`] gives a vertex's, without making a
    /// polygon; `None` for a spot or point light or a point not finite.
    pub fn project_point_directional(&self, p: DVec3) -> Option<(f64, f64)> {
        match &self.projection {
            Projection::Orthographic {
                u,
                v,
                u_min,
                v_min,
                texel_size,
                ..
            } if p.is_finite() => Some((
                (p.dot(*u) - u_min) / texel_size - self.offset.0,
                (p.dot(*v) - v_min) / texel_size - self.offset.1,
            )),
            _ => None,
        }
    }

    /// [`Self::project_triangle`] with each vertex's depth: `p·direction`
    /// for a directional light (t plus a constant), the depth `z` along
    /// the face's axis for a perspective face.
    pub fn project_triangle_with_depth(
        &self,
        face: usize,
        triangle: [DVec3; 3],
    ) -> Option<ProjectedPolygon> {
        if !triangle.iter().all(|p| p.is_finite()) {
            return None;
        }
        match &self.projection {
            Projection::Orthographic { direction, .. } => {
                let mut polygon = ProjectedPolygon::default();
                for p in triangle {
                    let (x, y) = self.project_point_directional(p)?;
                    polygon.push((x, y, p.dot(*direction)));
                }
                Some(polygon)
            }
            Projection::Perspective {
                position,
                near,
                half_extent,
                frame,
                cube,
                ..
            } => {
                let (forward, u, v) = face_axes(*frame, *cube, face);
                let min_depth = near / (1.0 + 2.0 * half_extent * half_extent).sqrt();
                let rel = triangle.map(|p| p - *position);
                let depth = |p: DVec3| p.dot(forward);
                // At most four: a vertex kept per side inside, and two
                // crossings when the plane cuts the triangle.
                let (mut clipped, mut n) = ([DVec3::ZERO; 4], 0);
                for i in 0..3 {
                    let (a, b) = (rel[i], rel[(i + 1) % 3]);
                    let (da, db) = (depth(a) - min_depth, depth(b) - min_depth);
                    if da >= 0.0 {
                        clipped[n] = a;
                        n += 1;
                    }
                    if (da >= 0.0) != (db >= 0.0) {
                        clipped[n] = a + (b - a) * (da / (da - db));
                        n += 1;
                    }
                }
                if n == 0 {
                    return None;
                }
                let (w, h) = (self.width as f64, self.height as f64);
                let mut polygon = ProjectedPolygon::default();
                for &p in &clipped[..n] {
                    let z = depth(p).max(min_depth);
                    polygon.push((
                        (p.dot(u) / z / half_extent + 1.0) * 0.5 * w - self.offset.0,
                        (p.dot(v) / z / half_extent + 1.0) * 0.5 * h - self.offset.1,
                        z,
                    ));
                }
                Some(polygon)
            }
        }
    }

    /// Whether some ray of this light may hit a point of the box `min..max`
    /// within its `[t_min, t_max]`. Conservative: `false` only when no point
    /// of the box can be hit — for a spot light, the box misses the pyramid of
    /// the full opening angle or the shell between `near` and `far` around the
    /// light; for a point light, the shell; for a directional light, the slab
    /// its grid sweeps (always `true` for boxes inside the world bounds).
    /// An empty box (`min > max` on an axis) is `false`; a box with NaN
    /// corners is `true`, so bad geometry is never silently dropped here.
    pub fn reaches(&self, min: DVec3, max: DVec3) -> bool {
        if min.is_nan() || max.is_nan() {
            return true;
        }
        if !min.cmple(max).all() {
            return false;
        }
        let centre = (min + max) * 0.5;
        let half = (max - min) * 0.5;
        // Extent of the box along unit-ish `n`, around `centre·n`.
        let radius = |n: DVec3| half.dot(n.abs());
        match &self.projection {
            Projection::Orthographic {
                direction,
                u,
                v,
                u_min,
                v_min,
                texel_size,
                w_origin,
                t_max,
            } => {
                let u_max = u_min + self.width as f64 * texel_size;
                let v_max = v_min + self.height as f64 * texel_size;
                let w_max = w_origin + t_max;
                let slack = REACH_SLACK
                    * (1.0 + centre.abs().max_element() + half.max_element() + t_max.abs());
                let overlaps = |axis: DVec3, lo: f64, hi: f64| {
                    let c = centre.dot(axis);
                    let r = radius(axis);
                    c + r >= lo - slack && c - r <= hi + slack
                };
                overlaps(*u, *u_min, u_max)
                    && overlaps(*v, *v_min, v_max)
                    && overlaps(*direction, *w_origin, w_max)
            }
            Projection::Perspective {
                position,
                near,
                far,
                half_extent,
                frame,
                cube,
            } => {
                let rel_centre = centre - *position;
                let slack =
                    REACH_SLACK * (1.0 + rel_centre.abs().max_element() + half.max_element() + far);
                // Nearest and farthest points of the box from the light.
                let nearest = (rel_centre.abs() - half).max(DVec3::ZERO).length();
                let farthest = (rel_centre.abs() + half).length();
                if nearest > far + slack || farthest < near - slack {
                    return false;
                }
                if *cube {
                    return true;
                }
                let (forward, u, v) = *frame;
                // The pyramid is the intersection of four half-spaces through
                // the apex, {p : ±(p·side) <= k·(p·forward)}; a box entirely
                // outside one of them is out of reach.
                [u, -u, v, -v].into_iter().all(|side| {
                    let n = forward * *half_extent - side;
                    rel_centre.dot(n) + radius(n) >= -slack * n.length()
                })
            }
        }
    }

    /// The rectangle `(x0, y0, x1, y1)`, in texel units of `face` and
    /// clipped to the grid, that the projection of the box `min..max`
    /// covers; `None` when it covers none of the face. Conservative (a box
    /// reaching behind a perspective face's plane covers the whole face):
    /// it feeds the cost estimate of a distributed bake's plan and the
    /// conservative pass's bins ([`Self::box_image`] unclipped).
    pub fn footprint(&self, face: usize, min: DVec3, max: DVec3) -> Option<(f64, f64, f64, f64)> {
        let (w, h) = (self.width as f64, self.height as f64);
        let (lo, hi) = match self.box_image(face, min, max) {
            BoxImage::Nowhere => return None,
            BoxImage::WholeFace => return Some((0.0, 0.0, w, h)),
            BoxImage::Rect(x0, y0, x1, y1) => ((x0, y0), (x1, y1)),
        };
        let (x0, y0) = (lo.0.max(0.0), lo.1.max(0.0));
        let (x1, y1) = (hi.0.min(w), hi.1.min(h));
        (x0 < x1 && y0 < y1).then_some((x0, y0, x1, y1))
    }

    /// Where on `face` (texel units, not clipped to the face) every point
    /// of the box `min..max` projects: the rectangle around its corners'
    /// images (a perspective projection keeps a box wholly in front of the
    /// face's plane inside the hull of its corners' images), the whole
    /// face when the box reaches behind that plane and the light reaches
    /// it, nowhere for a box that is not finite or empty. A ray's hit on
    /// something in the box projects to the ray's position up to
    /// [`Self::image_rounding`]: the bake cache's cells use it to find what
    /// a cell's rays can meet.
    pub fn box_image(&self, face: usize, min: DVec3, max: DVec3) -> BoxImage {
        if !(min.is_finite() && max.is_finite() && min.cmple(max).all()) {
            return BoxImage::Nowhere;
        }
        let (w, h) = (self.width as f64, self.height as f64);
        let mut lo = (f64::INFINITY, f64::INFINITY);
        let mut hi = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for corner in corners(min, max) {
            let (x, y) = match &self.projection {
                Projection::Orthographic {
                    u,
                    v,
                    u_min,
                    v_min,
                    texel_size,
                    ..
                } => (
                    (corner.dot(*u) - u_min) / texel_size - self.offset.0,
                    (corner.dot(*v) - v_min) / texel_size - self.offset.1,
                ),
                Projection::Perspective {
                    position,
                    half_extent,
                    frame,
                    cube,
                    ..
                } => {
                    let (forward, u, v) = face_axes(*frame, *cube, face);
                    let rel = corner - *position;
                    let depth = rel.dot(forward);
                    if depth <= 1e-9 * (1.0 + rel.length()) {
                        return match self.reaches(min, max) {
                            true => BoxImage::WholeFace,
                            false => BoxImage::Nowhere,
                        };
                    }
                    let image = |axis: DVec3, side: f64| {
                        (rel.dot(axis) / depth / half_extent + 1.0) * 0.5 * side
                    };
                    (image(u, w) - self.offset.0, image(v, h) - self.offset.1)
                }
            };
            lo = (lo.0.min(x), lo.1.min(y));
            hi = (hi.0.max(x), hi.1.max(y));
        }
        BoxImage::Rect(lo.0, lo.1, hi.0, hi.1)
    }

    /// Texels by which the image of a ray's hit may stray from the ray's
    /// own position on the grid through the `f32` rounding of the traced
    /// rays and triangles, far more than that rounding: for a directional
    /// light whose reach lies within `magnitude` metres of the reference
    /// point, 1024 ulps of its rays' light-relative origins; for a spot or
    /// point light, 64 ulps of a direction's angle in texels at the edge
    /// of the face.
    pub fn image_rounding(&self, magnitude: f64) -> f64 {
        let epsilon = f64::from(f32::EPSILON);
        match &self.projection {
            Projection::Orthographic { texel_size, .. } => {
                // The grid's own rays start within this of the reference point.
                let origins = (self.width.max(self.height) as f64 + 2.0) * texel_size;
                1024.0 * epsilon * (magnitude + origins) / texel_size
            }
            Projection::Perspective { half_extent, .. } => {
                let per_radian = self.width.max(self.height) as f64
                    * (1.0 + half_extent * half_extent)
                    / (2.0 * half_extent);
                64.0 * epsilon * per_radian
            }
        }
    }

    /// A good origin for light-relative f32 coordinates: the centre of the
    /// world bounds for a directional light, the light position otherwise.
    pub fn reference_point(&self) -> DVec3 {
        self.reference
    }
}

/// `d` normalised, or `None` when it has no usable length.
/// `(forward, u, v)` of a perspective light's face `face`: a point
/// light's cube face, else the spot light's one frame.
fn face_axes(frame: (DVec3, DVec3, DVec3), cube: bool, face: usize) -> (DVec3, DVec3, DVec3) {
    if cube {
        CUBE_FACES[face % CUBE_FACES.len()]
    } else {
        frame
    }
}

fn unit(d: DVec3) -> Option<DVec3> {
    let length = d.length();
    (d.is_finite() && length.is_finite() && length > 0.0).then(|| d / length)
}

fn corners(min: DVec3, max: DVec3) -> [DVec3; 8] {
    std::array::from_fn(|i| {
        DVec3::new(
            if i & 1 == 0 { min.x } else { max.x },
            if i & 2 == 0 { min.y } else { max.y },
            if i & 4 == 0 { min.z } else { max.z },
        )
    })
}

fn check_perspective(
    light: &str,
    position: DVec3,
    near: f64,
    far: f64,
    resolution: u32,
    faces: u64,
) -> Result<(), GridError> {
    let bad = |message: String| GridError::BadLight {
        light: light.to_string(),
        message,
    };
    if !position.is_finite() {
        return Err(bad(format!("<position> must be finite, found {position}")));
    }
    if !(near.is_finite() && near > 0.0) {
        return Err(bad(format!(
            "<near> must be a finite number > 0, found {near}"
        )));
    }
    if !(far.is_finite() && far > near) {
        return Err(bad(format!(
            "<far> must be finite and greater than <near> ({near}), found {far}"
        )));
    }
    if resolution == 0 {
        return Err(bad("<resolution> must be at least 1".to_string()));
    }
    let light_type = if faces == 6 { "point" } else { "spot" };
    let size = u64::from(resolution);
    if size > MAX_SIDE || faces * size * size > MAX_TEXELS {
        return Err(GridError::TooLarge {
            light: light.to_string(),
            light_type,
            faces,
            width: size,
            height: size,
        });
    }
    Ok(())
}

fn check_size(light: &LightSettings, faces: u64, width: u64, height: u64) -> Result<(), GridError> {
    let total = faces.checked_mul(width).and_then(|n| n.checked_mul(height));
    if width > MAX_SIDE || height > MAX_SIDE || total.is_none_or(|n| n > MAX_TEXELS) {
        return Err(GridError::TooLarge {
            light: light.name.clone(),
            light_type: light.kind.type_name(),
            faces,
            width,
            height,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests;
