//! The camera view: the whole world in perspective, each surface coloured
//! by its caster's verdict for one light and lit by that light, so an
//! artist sees which objects the light would skip. One primary ray per
//! pixel centre through the bake's own bottom levels under a top level
//! over every placed part and terrain block (a camera reaches everything),
//! so the view holds a box and an inverse transform per placement, never
//! the placed world's triangles. A part's triangles are placed in world
//! space as the ray meets them and tested there, so each pixel is what a
//! flat list of the world's triangles gives it. The nearest triangle wins
//! whatever its facing (a picture of the world, not of the light's
//! filter), equal distances to the lowest caster id, then the lowest
//! triangle number (the order of that flat list). Shade: `AMBIENT + (1 − AMBIENT)·max(0, n·l)` with `n`
//! the triangle's normal turned towards the camera and `l` towards the
//! light (directional: against its direction; spot and point: from the
//! point to the light); no shadows. Sky: dark blue.

use super::{check_size, shaded, verdicts, Class, Picture, RenderError, Source};
use crate::bake::casters::Owner;
use crate::bake::geometry::{placed_triangle, world_bounds};
use crate::bake::setup::BakeWorld;
use crate::bake::BakeConfig;
use crate::formats::bake_settings::LightKind;
use crate::scene::Scene;
use crate::trace::{Hit, PartsFrom, PlacedBlock, PlacedPart, TopLevel, TraceRay, TraceTriangle};
use glam::{DVec3, Vec3};
use rayon::prelude::*;

/// Light reaching surfaces that face away from the light, so their shape
/// and colour still read.
const AMBIENT: f64 = 0.3;
const SKY: [u8; 3] = [18, 24, 48];
/// Direction from the world's centre to the default camera: above, from
/// the −z side and a little +x, so the default picture looks north-east
/// and down at about 40°.
const OVERVIEW_FROM: DVec3 = DVec3::new(0.45, 0.85, -0.9);

/// Where the camera is and what it draws. `position` / `look_at` `None`:
/// the overview (see [`CameraSpec::resolve`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSpec {
    pub position: Option<DVec3>,
    pub look_at: Option<DVec3>,
    /// Vertical field of view, degrees, in (0, 180).
    pub fov_degrees: f64,
    pub width: u32,
    pub height: u32,
}

impl Default for CameraSpec {
    fn default() -> Self {
        CameraSpec {
            position: None,
            look_at: None,
            fov_degrees: 60.0,
            width: 800,
            height: 600,
        }
    }
}

impl CameraSpec {
    /// The camera position and target for a world of `bounds`: the target
    /// defaults to the bounds' centre; the position to the nearest point in
    /// direction [`OVERVIEW_FROM`] from the target from which all eight
    /// corners of the bounds are in the picture, moved 5 % further out.
    pub fn resolve(&self, (min, max): (DVec3, DVec3)) -> (DVec3, DVec3) {
        let centre = (min + max) * 0.5;
        let target = self.look_at.unwrap_or(centre);
        let position = self.position.unwrap_or_else(|| {
            let from = OVERVIEW_FROM.normalize();
            let corners: Vec<DVec3> = (0..8)
                .map(|i| {
                    DVec3::new(
                        if i & 1 == 0 { min.x } else { max.x },
                        if i & 2 == 0 { min.y } else { max.y },
                        if i & 4 == 0 { min.z } else { max.z },
                    )
                })
                .collect();
            let frame = Frame::new(-from, self.fov_degrees, self.width, self.height);
            let sees_all = |distance: f64| {
                let eye = target + from * distance;
                corners.iter().all(|c| frame.contains(*c - eye))
            };
            // Far enough to see every corner: past the farthest corner by
            // the distance at which a sphere around them fits the view.
            let radius = corners
                .iter()
                .map(|c| (*c - target).length())
                .fold(1.0, f64::max);
            let (mut near, mut far) = (0.0, radius * 2.0 / frame.half_min().sin() + radius);
            if !sees_all(far) {
                return target + from * far;
            }
            for _ in 0..60 {
                let mid = (near + far) * 0.5;
                if sees_all(mid) {
                    far = mid;
                } else {
                    near = mid;
                }
            }
            target + from * far * 1.05
        });
        (position, target)
    }
}

/// The camera's axes and image-plane half extents at distance 1.
struct Frame {
    forward: DVec3,
    right: DVec3,
    up: DVec3,
    half_w: f64,
    half_h: f64,
}

impl Frame {
    /// `forward` must be unit length; the picture's up is as near world +Y
    /// as `forward` allows (+Z when looking straight up or down).
    fn new(forward: DVec3, fov_degrees: f64, width: u32, height: u32) -> Frame {
        let up_hint = if forward.y.abs() > 0.999 {
            DVec3::Z
        } else {
            DVec3::Y
        };
        let right = forward.cross(up_hint).normalize();
        let up = right.cross(forward);
        let half_h = (fov_degrees.to_radians() * 0.5).tan();
        let half_w = half_h * width as f64 / height.max(1) as f64;
        Frame {
            forward,
            right,
            up,
            half_w,
            half_h,
        }
    }

    /// Half of the narrower field of view, radians.
    fn half_min(&self) -> f64 {
        self.half_w.min(self.half_h).atan()
    }

    /// Whether a point at `offset` from the camera is in front of it and
    /// inside the picture.
    fn contains(&self, offset: DVec3) -> bool {
        let depth = offset.dot(self.forward);
        depth > 0.0
            && offset.dot(self.right).abs() <= self.half_w * depth
            && offset.dot(self.up).abs() <= self.half_h * depth
    }

    /// The unit direction through picture point `(sx, sy)` in [-1, 1]²
    /// (x right, y up).
    fn direction(&self, sx: f64, sy: f64) -> DVec3 {
        (self.forward + self.right * (sx * self.half_w) + self.up * (sy * self.half_h)).normalize()
    }
}

/// Draws the world seen by `camera`, coloured by light `light`'s verdicts.
pub fn camera_view(
    scene: &Scene,
    config: &BakeConfig,
    light: usize,
    camera: &CameraSpec,
) -> Result<Picture, RenderError> {
    camera_view_from(scene, config, light, camera, Source::Bake)
}

/// [`camera_view`] with the verdicts from `source`.
pub fn camera_view_from(
    scene: &Scene,
    config: &BakeConfig,
    light: usize,
    camera: &CameraSpec,
    source: Source,
) -> Result<Picture, RenderError> {
    check_camera(camera)?;
    let world = BakeWorld::new(scene);
    let (verdicts, _) = verdicts(&world, config, light, source)?;
    let bounds = world_bounds(scene).ok_or(RenderError::EmptyWorld)?;
    let (position, target) = camera.resolve(bounds);
    let forward = (target - position).normalize_or_zero();
    if forward == DVec3::ZERO || !forward.is_finite() {
        return Err(RenderError::BadCamera(format!(
            "camera {position} and look-at {target} are the same point: no direction to look in"
        )));
    }
    let reference = (bounds.0 + bounds.1) * 0.5;
    let view = View {
        frame: Frame::new(forward, camera.fov_degrees, camera.width, camera.height),
        position,
        origin: (position - reference).as_vec3(),
        world: CameraWorld::new(&world, reference),
        classes: &verdicts.classes,
        light_kind: &config.lights[light].kind,
    };
    let (classes, rgb) = view.draw(camera.width, camera.height);
    Ok(Picture {
        width: camera.width,
        height: camera.height,
        rgb,
        classes,
        light: verdicts.light,
        notes: notes(position, target, camera.fov_degrees),
    })
}

/// Refuses a picture size, field of view or points a camera cannot use.
fn check_camera(camera: &CameraSpec) -> Result<(), RenderError> {
    check_size(camera.width, camera.height)?;
    if !(camera.fov_degrees > 0.0 && camera.fov_degrees < 180.0) {
        return Err(RenderError::BadCamera(format!(
            "field of view must be in (0, 180) degrees, got {}",
            camera.fov_degrees
        )));
    }
    for (name, v) in [("camera", camera.position), ("look-at", camera.look_at)] {
        if v.is_some_and(|v| !v.is_finite()) {
            return Err(RenderError::BadCamera(format!(
                "{name} point must be finite"
            )));
        }
    }
    Ok(())
}

/// What the camera traces: a top level over every placed part and
/// terrain block on the bake's bottom levels, relative to `reference`.
struct CameraWorld<'w> {
    world: &'w BakeWorld<'w>,
    top: TopLevel,
    reference: DVec3,
}

impl<'w> CameraWorld<'w> {
    fn new(world: &'w BakeWorld<'w>, reference: DVec3) -> CameraWorld<'w> {
        let scene = world.scene;
        let parts = PartsFrom {
            count: world.parts.len(),
            part: |i| {
                let part = &world.parts[i];
                PlacedPart {
                    model: part.model as u32,
                    world: scene.instances[part.instance].world,
                    first_caster: part.first_caster,
                }
            },
        };
        let blocks = (0..scene.terrain.len()).map(|block| PlacedBlock {
            block: block as u32,
            caster: world.casters.of_block[block],
        });
        CameraWorld {
            world,
            top: TopLevel::build(&world.bottom, &parts, blocks, reference),
            reference,
        }
    }

    /// Heap bytes the view adds to the bake's world: its top level.
    #[cfg(test)]
    fn heap_bytes(&self) -> usize {
        self.top.heap_bytes()
    }

    /// The nearest hit along `ray` and its triangle (relative to
    /// `reference`); equal t: the lowest (caster, triangle).
    fn nearest(&self, ray: &TraceRay) -> Option<(Hit, TraceTriangle)> {
        let mut best: Option<(Hit, TraceTriangle)> = None;
        let place =
            |first_caster: u32, triangle: &TraceTriangle| self.place(first_caster, triangle);
        self.top
            .for_each_placed_hit(&self.world.bottom, ray, place, |hit, triangle| {
                let key = |h: &Hit| (h.t, h.caster, h.triangle);
                if best.is_none_or(|(b, _)| key(&hit) < key(&b)) {
                    best = Some((hit, *triangle));
                }
                best.map_or(hit.t, |(b, _)| b.t)
            });
        best
    }

    /// A model-space triangle of the part whose group 0 is `first_caster`,
    /// placed as the raster's flat list places it (NaN, never hit, if the
    /// id names no part).
    fn place(&self, first_caster: u32, triangle: &TraceTriangle) -> TraceTriangle {
        let casters = &self.world.casters.casters;
        let caster = first_caster + triangle.caster;
        match casters.get(first_caster as usize).map(|c| c.owner) {
            Some(Owner::Group { instance, .. }) => placed_triangle(
                &self.world.scene.instances[instance as usize],
                triangle.vertices,
                caster,
                self.reference,
            ),
            _ => TraceTriangle {
                vertices: [Vec3::NAN; 3],
                caster,
            },
        }
    }
}

/// What one pixel's ray needs: the camera, the world it traces (relative
/// to a reference point, as `origin` is) and the verdicts and light that
/// colour it.
struct View<'a> {
    frame: Frame,
    /// The camera in world coordinates, for the light's direction at a hit.
    position: DVec3,
    /// The camera relative to the world's reference point.
    origin: Vec3,
    world: CameraWorld<'a>,
    classes: &'a [Class],
    light_kind: &'a LightKind,
}

impl View<'_> {
    /// Every pixel's class and colour, row by row from the top, written
    /// in place (the picture is the largest thing the view holds).
    fn draw(&self, width: u32, height: u32) -> (Vec<Class>, Vec<u8>) {
        let pixels = width as usize * height as usize;
        let mut rgb = vec![0u8; pixels * 3];
        let mut classes = vec![Class::Nothing; pixels];
        rgb.par_chunks_mut(width as usize * 3)
            .zip(classes.par_chunks_mut(width as usize))
            .enumerate()
            .for_each(|(row, (rgb, classes))| {
                let sy = 1.0 - (row as f64 + 0.5) / height as f64 * 2.0;
                for (column, (colour, class)) in
                    rgb.chunks_exact_mut(3).zip(classes.iter_mut()).enumerate()
                {
                    let sx = (column as f64 + 0.5) / width as f64 * 2.0 - 1.0;
                    let (pixel_class, pixel_colour) = self.pixel(self.frame.direction(sx, sy));
                    *class = pixel_class;
                    colour.copy_from_slice(&pixel_colour);
                }
            });
        (classes, rgb)
    }

    /// The nearest surface along `direction`: its caster's class, lit by
    /// the light (Lambert with ambient); the sky when nothing is hit.
    fn pixel(&self, direction: DVec3) -> (Class, [u8; 3]) {
        let ray = TraceRay {
            origin: self.origin,
            direction: direction.as_vec3(),
            t_min: 0.0,
            t_max: f32::INFINITY,
        };
        let Some((hit, triangle)) = self.world.nearest(&ray) else {
            return (Class::Nothing, SKY);
        };
        let class = self
            .classes
            .get(hit.caster as usize)
            .copied()
            .unwrap_or(Class::Nothing);
        let [a, b, c] = triangle.vertices.map(|v| v.as_dvec3());
        let mut normal = (b - a).cross(c - a).normalize_or_zero();
        if normal.dot(direction) > 0.0 {
            normal = -normal;
        }
        let point = self.position + direction * hit.t as f64;
        let to_light = match self.light_kind {
            LightKind::Directional { direction, .. } => -*direction,
            LightKind::Spot { position, .. } | LightKind::Point { position, .. } => {
                *position - point
            }
        }
        .normalize_or_zero();
        let lambert = normal.dot(to_light).max(0.0);
        (class, shaded(class, AMBIENT + (1.0 - AMBIENT) * lambert))
    }
}

/// The legend's account of the camera and the lighting.
fn notes(position: DVec3, target: DVec3, fov_degrees: f64) -> Vec<String> {
    vec![
        format!(
            "camera view: from ({:.2}, {:.2}, {:.2}) looking at ({:.2}, {:.2}, {:.2}), vertical field of view {}°",
            position.x, position.y, position.z, target.x, target.y, target.z, fov_degrees
        ),
        format!(
            "surfaces lit by the light's direction (Lambert, {:.0} % ambient, no shadows); sky dark blue",
            AMBIENT * 100.0
        ),
        "casters outside the light's reach are never useful for it, so they show as culled".to_string(),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bake::geometry::parts_geometry;
    use crate::files::ResPaths;
    use crate::scene::{load_scene, LoadConfig};
    use crate::trace::Bvh;

    /// Heap bytes the view may hold per placed part or terrain block: a
    /// top-level entry (an f64 inverse transform and ids) and its share of
    /// the box tree, whatever the part's or the block's triangle count.
    const MOST_BYTES_PER_PLACEMENT: usize = 192;

    fn village() -> Scene {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/worlds/village");
        load_scene(&LoadConfig {
            res_paths: ResPaths::new(vec![root]),
            space: "spaces/village".into(),
            speedtrees: Default::default(),
        })
        .expect("the village fixture loads")
    }

    #[test]
    fn the_view_holds_placements_not_placed_triangles() {
        let scene = village();
        let world = BakeWorld::new(&scene);
        let (min, max) = world.bounds.unwrap();
        let view = CameraWorld::new(&world, (min + max) * 0.5);
        let placements = world.parts.len() + scene.terrain.len();
        let bytes = view.heap_bytes();
        assert!(
            bytes <= MOST_BYTES_PER_PLACEMENT * placements,
            "{bytes} bytes for {placements} parts and blocks"
        );
        // What a flat list of the placed world would hold: every placed
        // triangle and two a terrain cell, far more than the bound.
        let placed: usize = world
            .parts
            .iter()
            .map(|p| world.bottom.model_triangles(p.model))
            .sum();
        let cells: usize = scene
            .terrain
            .iter()
            .map(|b| b.cells().0 * b.cells().1)
            .sum();
        let flat = (placed + 2 * cells) * std::mem::size_of::<TraceTriangle>();
        assert!(flat > 20 * MOST_BYTES_PER_PLACEMENT * placements, "{flat}");
    }

    #[test]
    fn each_pixel_is_the_flat_placed_worlds_nearest_triangle() {
        // The reference the view replaces: a BVH over every placed
        // triangle and terrain cell in caster id order, the nearest hit and
        // on equal t the lowest index.
        let scene = village();
        let world = BakeWorld::new(&scene);
        let (min, max) = world.bounds.unwrap();
        let reference = (min + max) * 0.5;
        let parts: Vec<u32> = (0..world.parts.len() as u32).collect();
        let blocks: Vec<u32> = (0..scene.terrain.len() as u32).collect();
        let flat = parts_geometry(
            &scene,
            &world.casters,
            &world.parts,
            &parts,
            &blocks,
            reference,
        );
        let bvh = Bvh::build(&flat.triangles);
        let view = CameraWorld::new(&world, reference);
        let spec = CameraSpec {
            width: 160,
            height: 120,
            ..CameraSpec::default()
        };
        let mut hit_pixels = 0;
        for (position, target) in [
            spec.resolve((min, max)),
            (min + DVec3::new(-5.0, 12.0, -5.0), reference),
            (reference + DVec3::new(3.0, 2.5, 1.0), max),
        ] {
            let frame = Frame::new(
                (target - position).normalize(),
                60.0,
                spec.width,
                spec.height,
            );
            for row in 0..spec.height {
                for column in 0..spec.width {
                    let sx = (column as f64 + 0.5) / spec.width as f64 * 2.0 - 1.0;
                    let sy = 1.0 - (row as f64 + 0.5) / spec.height as f64 * 2.0;
                    let ray = TraceRay {
                        origin: (position - reference).as_vec3(),
                        direction: frame.direction(sx, sy).as_vec3(),
                        t_min: 0.0,
                        t_max: f32::INFINITY,
                    };
                    let ours = view.nearest(&ray).map(|(h, t)| (h.t, h.caster, t.vertices));
                    let expected = bvh
                        .closest_hit(&ray)
                        .map(|h| (h.t, h.caster, flat.triangles[h.triangle as usize].vertices));
                    assert_eq!(ours, expected, "pixel ({column}, {row}) from {position}");
                    hit_pixels += usize::from(ours.is_some());
                }
            }
        }
        assert!(hit_pixels > 20_000, "{hit_pixels}");
    }

    #[test]
    fn overview_frames_the_bounds() {
        let spec = CameraSpec::default();
        let bounds = (DVec3::new(0.0, 0.0, 0.0), DVec3::new(100.0, 10.0, 100.0));
        let (position, target) = spec.resolve(bounds);
        assert_eq!(target, DVec3::new(50.0, 5.0, 50.0));
        // Every corner in the picture, and (the 5 % margin) not all of them
        // from 10 % nearer.
        let frame = Frame::new((target - position).normalize(), 60.0, 800, 600);
        let corners =
            [0.0, 100.0].map(|x| [0.0, 10.0].map(|y| [0.0, 100.0].map(|z| DVec3::new(x, y, z))));
        let corners: Vec<DVec3> = corners.into_iter().flatten().flatten().collect();
        assert!(corners.iter().all(|c| frame.contains(*c - position)));
        let nearer = target + (position - target) * 0.9;
        assert!(!corners.iter().all(|c| frame.contains(*c - nearer)));
        assert!(position.y > bounds.1.y);
        let given = CameraSpec {
            position: Some(DVec3::ONE),
            look_at: Some(DVec3::ZERO),
            ..spec
        };
        assert_eq!(given.resolve(bounds), (DVec3::ONE, DVec3::ZERO));
    }
}
