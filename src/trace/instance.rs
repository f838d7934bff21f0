//! Entering a placed instance: a light-relative ray mapped into the model's
//! own space by the inverse of the instance's affine world transform.
//!
//! The direction is mapped by the linear part and not renormalised, so the
//! ray parameter t is the same on both sides: a hit at model-space t lies
//! t metres along the world ray. The inverse is computed in f64 from the
//! f64 world transform, and the reference point is folded into its
//! translation in f64 too, so a world far from the origin loses nothing
//! (only the final model-space ray is rounded to f32).
//!
//! Facing needs no flip for mirrored instances: the engine flips the cull
//! mode of a model whose transform mirrors it, which is the same as judging
//! facing by the model-space normal against the model-space direction —
//! what the triangle test does here. (Flattening to world space instead has
//! to swap two vertices of every mirrored triangle to get this.)

use super::TraceRay;
use glam::{DMat3, DMat4, DVec3, Vec3};

/// The map from the light-relative frame (world minus the light's
/// reference point) into one instance's model space.
#[derive(Clone, Copy, Debug)]
pub struct ToModel {
    linear: DMat3,
    /// The model-space position of the reference point.
    offset: DVec3,
}

impl ToModel {
    /// `None` when `world` is not an invertible finite affine map (a
    /// damaged transform: such an instance cannot be entered).
    pub fn new(world: &DMat4, reference: DVec3) -> Option<ToModel> {
        let det = world.determinant();
        if !(det.is_finite() && det != 0.0) {
            return None;
        }
        let inverse = world.inverse();
        if !inverse.is_finite() {
            return None;
        }
        Some(ToModel {
            linear: DMat3::from_mat4(inverse),
            offset: inverse.transform_point3(reference),
        })
    }

    /// The map's linear part and offset: y = linear · x + offset.
    pub(crate) fn parts(&self) -> (DMat3, DVec3) {
        (self.linear, self.offset)
    }

    /// The inverse of the linear part: model space back to the light's
    /// frame (computed on demand: an entry does not hold it).
    pub(crate) fn world_linear(&self) -> DMat3 {
        self.linear.inverse()
    }

    /// A light-relative point in model space (a ray's origin).
    #[inline]
    pub(crate) fn origin(&self, origin: Vec3) -> Vec3 {
        (self.linear * origin.as_dvec3() + self.offset).as_vec3()
    }

    /// A bound on the coordinates of light-relative points within
    /// `origin_max` of 0 once mapped into model space (and rounded to f32):
    /// the map's row-sum norm times `origin_max`, plus the offset, with a
    /// relative margin far beyond the f64 evaluation's and the f32
    /// rounding's.
    pub(crate) fn origin_bound(&self, origin_max: f32) -> f32 {
        let norm = row_sum_norm(&self.linear);
        let bound = (norm * f64::from(origin_max) + self.offset.abs().max_element()) * (1.0 + 1e-6);
        let f = bound as f32;
        if f64::from(f) < bound {
            f.next_up()
        } else {
            f
        }
    }

    /// The ray in model space, same t range.
    #[inline]
    pub fn ray(&self, ray: &TraceRay) -> TraceRay {
        self.ray_with(ray, self.direction(ray.direction))
    }

    /// The direction part of [`Self::ray`] (parallel rays share it).
    #[inline]
    pub(crate) fn direction(&self, direction: Vec3) -> Vec3 {
        (self.linear * direction.as_dvec3()).as_vec3()
    }

    /// [`Self::ray`] given the mapped direction.
    #[inline]
    pub(crate) fn ray_with(&self, ray: &TraceRay, direction: Vec3) -> TraceRay {
        TraceRay {
            origin: self.origin(ray.origin),
            direction,
            t_min: ray.t_min,
            t_max: ray.t_max,
        }
    }
}

/// The ∞-norm of `m` (its largest row sum of absolute values): how much
/// it can grow a vector's largest coordinate.
pub(crate) fn row_sum_norm(m: &DMat3) -> f64 {
    let rows = m.transpose();
    [rows.x_axis, rows.y_axis, rows.z_axis]
        .iter()
        .fold(0.0f64, |n, r| n.max(r.abs().element_sum()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DQuat, Vec3};

    #[test]
    fn t_is_kept_through_scale_rotation_and_far_translation() {
        let world = DMat4::from_scale_rotation_translation(
            DVec3::new(2.0, 0.5, 3.0),
            DQuat::from_rotation_y(0.7),
            DVec3::new(1e6, 20.0, -1e6),
        );
        let reference = DVec3::new(1e6 + 10.0, 0.0, -1e6 - 5.0);
        let to_model = ToModel::new(&world, reference).unwrap();
        let ray = TraceRay {
            origin: Vec3::new(-3.0, 40.0, 2.0),
            direction: Vec3::new(0.3, -0.9, 0.1).normalize(),
            t_min: 0.0,
            t_max: 100.0,
        };
        let m = to_model.ray(&ray);
        for t in [0.0f32, 7.5, 33.0] {
            let world_point = reference + (ray.origin + ray.direction * t).as_dvec3();
            let model_point = world.inverse().transform_point3(world_point);
            let ours = (m.origin + m.direction * t).as_dvec3();
            assert!(
                (ours - model_point).length() < 1e-4,
                "{ours} vs {model_point}"
            );
        }
        assert_eq!((m.t_min, m.t_max), (0.0, 100.0));
    }

    #[test]
    fn origin_bound_holds_every_mapped_origin() {
        // Scaled, rotated, sheared and far-translated instances; points
        // anywhere within origin_max, corners included (where a loose
        // norm would show).
        let mut rng = crate::rng::Rng::new(21);
        for _ in 0..200 {
            let world = DMat4::from_scale_rotation_translation(
                DVec3::new(
                    rng.range(0.05, 20.0),
                    rng.range(0.05, 20.0),
                    rng.range(0.05, 20.0),
                ),
                DQuat::from_euler(
                    glam::EulerRot::YXZ,
                    rng.range(-3.0, 3.0),
                    rng.range(-3.0, 3.0),
                    rng.range(-3.0, 3.0),
                ),
                DVec3::new(
                    rng.range(-1e5, 1e5),
                    rng.range(-100.0, 100.0),
                    rng.range(-1e5, 1e5),
                ),
            ) * DMat4::from_cols_array(&[
                1.0,
                0.0,
                0.0,
                0.0,
                rng.range(-0.5, 0.5),
                1.0,
                0.0,
                0.0,
                0.0,
                0.0,
                1.0,
                0.0,
                0.0,
                0.0,
                0.0,
                1.0,
            ]);
            let reference = DVec3::new(rng.range(-1e5, 1e5), 0.0, rng.range(-1e5, 1e5));
            let to_model = ToModel::new(&world, reference).unwrap();
            let origin_max = rng.range(1.0, 5000.0) as f32;
            let bound = to_model.origin_bound(origin_max);
            let mut largest = 0.0f32;
            for i in 0..64 {
                let mut pick = |bit: usize| {
                    if i < 8 {
                        if i & bit == 0 {
                            -origin_max
                        } else {
                            origin_max
                        }
                    } else {
                        (rng.range(-1.0, 1.0) * f64::from(origin_max)) as f32
                    }
                };
                let o = Vec3::new(pick(1), pick(2), pick(4));
                largest = largest.max(to_model.origin(o).abs().max_element());
            }
            assert!(largest <= bound, "{largest} > {bound}");
            // Tight: within the norm's slack of the largest corner.
            assert!(bound <= 2.0 * largest + 1.0, "{bound} for {largest}");
        }
    }

    #[test]
    fn singular_and_non_finite_transforms_cannot_be_entered() {
        assert!(ToModel::new(&DMat4::from_scale(DVec3::new(1.0, 0.0, 1.0)), DVec3::ZERO).is_none());
        let mut nan = DMat4::IDENTITY;
        nan.w_axis.x = f64::NAN;
        assert!(ToModel::new(&nan, DVec3::ZERO).is_none());
    }
}
