//! The light-space basis. A directional or spot light needs two axes across
//! its direction to lay out its texel grid; the usual `lookAt` with a fixed
//! "up" vector breaks down when the light points along that vector (a sun
//! straight overhead is the most common light there is), so docs/contract.md §4 asks for
//! a construction that is robust for every direction.

use glam::DVec3;

/// An orthonormal basis `(u, v)` across the unit vector `d`, right-handed:
/// `u × v = d`.
///
/// This is the branchless construction of Duff et al., "Building an
/// Orthonormal Basis, Revisited" (JCGT 2017). It has no singularity, keeps
/// full f64 precision near every axis, and gives exact basis vectors (only
/// 0 and ±1) for the six axis directions. Because no tangent field on the
/// sphere is continuous everywhere, it jumps across the plane `d.z = 0`;
/// that is harmless here, as each light uses one basis for all its texels.
///
/// The sign of `d.z` decides the branch with `d.z >= 0.0`, so `-0.0` and
/// `+0.0` give the same basis (the result depends on the direction's value
/// only, not on how a zero was computed).
///
/// `d` must be unit length (the bake settings normalise light directions);
/// otherwise the result is not orthonormal.
pub fn orthonormal_basis(d: DVec3) -> (DVec3, DVec3) {
    let sign = if d.z >= 0.0 { 1.0 } else { -1.0 };
    let a = -1.0 / (sign + d.z);
    let b = d.x * d.y * a;
    let u = DVec3::new(1.0 + sign * d.x * d.x * a, sign * b, -sign * d.x);
    let v = DVec3::new(b, sign + d.y * d.y * a, -d.y);
    (u, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Orthonormal to ~1e-15 (Duff's construction is accurate to a few ulps),
    /// right-handed, and `d` itself is unit.
    fn assert_frame(d: DVec3) {
        let (u, v) = orthonormal_basis(d);
        let tol = 1e-14;
        assert!(
            (u.length() - 1.0).abs() < tol,
            "|u| = {} for d = {d}",
            u.length()
        );
        assert!(
            (v.length() - 1.0).abs() < tol,
            "|v| = {} for d = {d}",
            v.length()
        );
        assert!(u.dot(v).abs() < tol, "u·v = {} for d = {d}", u.dot(v));
        assert!(u.dot(d).abs() < tol, "u·d = {} for d = {d}", u.dot(d));
        assert!(v.dot(d).abs() < tol, "v·d = {} for d = {d}", v.dot(d));
        let w = u.cross(v);
        assert!((w - d).length() < tol, "u×v = {w} differs from d = {d}");
    }

    #[test]
    fn random_directions_give_right_handed_orthonormal_frames() {
        let mut rng = Rng::new(0x11_9417);
        for _ in 0..100_000 {
            assert_frame(rng.unit_vector());
        }
    }

    #[test]
    fn axis_directions_give_exact_axis_frames() {
        // Every component must be exactly 0 or ±1: worked out from the
        // formula (a = -1/(sign + d.z), b = d.x·d.y·a = 0 on an axis).
        let expected = [
            (DVec3::X, DVec3::new(0.0, 0.0, -1.0), DVec3::Y),
            (DVec3::NEG_X, DVec3::Z, DVec3::Y),
            (DVec3::Y, DVec3::X, DVec3::NEG_Z),
            (DVec3::NEG_Y, DVec3::X, DVec3::Z),
            (DVec3::Z, DVec3::X, DVec3::Y),
            (DVec3::NEG_Z, DVec3::X, DVec3::NEG_Y),
        ];
        for (d, eu, ev) in expected {
            let (u, v) = orthonormal_basis(d);
            assert_eq!((u, v), (eu, ev), "basis of {d}");
            assert_eq!(u.cross(v), d, "handedness of {d}");
            assert_frame(d);
        }
    }

    #[test]
    fn negative_zero_does_not_change_the_basis() {
        let plus = orthonormal_basis(DVec3::new(1.0, 0.0, 0.0));
        let minus = orthonormal_basis(DVec3::new(1.0, 0.0, -0.0));
        assert_eq!(plus, minus);
    }

    #[test]
    fn near_axis_directions_stay_orthonormal() {
        let tiny = [1e-12, -1e-12, 1e-300, 1e-17, -3e-9];
        for &e in &tiny {
            for axis in [
                DVec3::X,
                DVec3::NEG_X,
                DVec3::Y,
                DVec3::NEG_Y,
                DVec3::Z,
                DVec3::NEG_Z,
            ] {
                for off in [DVec3::X, DVec3::Y, DVec3::Z] {
                    let d = (axis + off * e).normalize();
                    assert_frame(d);
                }
            }
        }
        // The case named in the brief, and the classic failure of Frisvad's
        // original method (d.z just above -1).
        assert_frame(DVec3::new(1e-12, -1.0, 0.0).normalize());
        assert_frame(DVec3::new(1e-8, 1e-8, -1.0).normalize());
    }

    #[test]
    fn basis_is_continuous_within_a_hemisphere() {
        // Small changes of d give small changes of the basis (apart from the
        // documented jump across d.z = 0).
        let mut rng = Rng::new(7);
        for _ in 0..10_000 {
            let d = rng.unit_vector();
            if d.z.abs() < 1e-3 {
                continue;
            }
            let e = DVec3::new(
                rng.range(-1e-7, 1e-7),
                rng.range(-1e-7, 1e-7),
                rng.range(-1e-7, 1e-7),
            );
            let d2 = (d + e).normalize();
            if d2.z.signum() != d.z.signum() {
                continue;
            }
            let (u1, v1) = orthonormal_basis(d);
            let (u2, v2) = orthonormal_basis(d2);
            // The basis derivative grows like 1/(1 + |d.z|) ≤ 1 → small.
            assert!((u1 - u2).length() < 1e-5, "u jumps near {d}");
            assert!((v1 - v2).length() < 1e-5, "v jumps near {d}");
        }
    }
}
