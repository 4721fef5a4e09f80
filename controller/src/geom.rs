//! Ground-plane and rotation helpers.
//!
//! Conventions (the PFNN capture's): `y` is up, a facing is a unit vector
//! `(x, z)` in the ground plane, and the yaw angle of a facing `f` is
//! `atan2(f.x, f.z)` (0 faces `+z`, positive turns toward `+x`, which is the
//! character's left). A yaw is carried as its unit facing `(sin, cos)`
//! rather than as an angle: applying it needs no trigonometry, and the
//! demo's `rotate(atan2(d.x, d.z), y)` matrix is exactly this.
//! Quaternions are `[x, y, z, w]`, scalar last.

use crate::real::Real;

/// A ground-plane vector `(x, z)`.
pub type Vec2<R> = [R; 2];
/// A 3-D vector `(x, y, z)`.
pub type Vec3<R> = [R; 3];
/// A quaternion `[x, y, z, w]`.
pub type Quat<R> = [R; 4];

/// The facing of yaw 0: `+z`.
pub fn forward<R: Real>() -> Vec2<R> {
    [R::ZERO, R::ONE]
}

/// Euclidean length of a ground-plane vector.
pub fn len2<R: Real>(v: Vec2<R>) -> R {
    (v[0] * v[0] + v[1] * v[1]).sqrt()
}

/// `v / |v|`; a zero or non-finite vector gives `+z`, the facing whose yaw
/// `atan2(0, 0) = 0` the demo would give it.
pub fn normalise2<R: Real>(v: Vec2<R>) -> Vec2<R> {
    let n = len2(v);
    if n > R::ZERO && n.is_finite() {
        [v[0] / n, v[1] / n]
    } else {
        forward()
    }
}

/// `v` turned by the yaw whose facing is `f = (sin, cos)`.
pub fn yaw2<R: Real>(f: Vec2<R>, v: Vec2<R>) -> Vec2<R> {
    let (s, c) = (f[0], f[1]);
    [c * v[0] + s * v[1], c * v[1] - s * v[0]]
}

/// `v` turned by the inverse of the yaw whose facing is `f`.
pub fn unyaw2<R: Real>(f: Vec2<R>, v: Vec2<R>) -> Vec2<R> {
    let (s, c) = (f[0], f[1]);
    [c * v[0] - s * v[1], c * v[1] + s * v[0]]
}

/// `v` turned by `angle` radians of yaw.
pub fn turn2<R: Real>(v: Vec2<R>, angle: R) -> Vec2<R> {
    let (s, c) = angle.sin_cos();
    yaw2([s, c], v)
}

/// 3-D `v` turned by the yaw whose facing is `f`.
pub fn yaw3<R: Real>(f: Vec2<R>, v: Vec3<R>) -> Vec3<R> {
    let [x, z] = yaw2(f, [v[0], v[2]]);
    [x, v[1], z]
}

/// 3-D `v` turned by the inverse of the yaw whose facing is `f`.
pub fn unyaw3<R: Real>(f: Vec2<R>, v: Vec3<R>) -> Vec3<R> {
    let [x, z] = unyaw2(f, [v[0], v[2]]);
    [x, v[1], z]
}

/// The demo's `mix_directions`: turns `from` toward `to` by the fraction `a`
/// of the (shortest) yaw angle between them; the result is a unit facing.
/// Written with one `atan2` of the relative angle instead of two absolute
/// angles and a quaternion slerp: the same rotation, fewer roundings.
#[inline(never)] // three call sites in the loop: one copy in flash
pub fn mix_directions<R: Real>(from: Vec2<R>, to: Vec2<R>, a: R) -> Vec2<R> {
    let u = normalise2(from);
    let v = normalise2(to);
    let sin = v[0] * u[1] - v[1] * u[0];
    let cos = v[0] * u[0] + v[1] * u[1];
    turn2(u, a * sin.atan2(cos))
}

/// The rotation of PFNN's exponential-map output `l`, as the demo reads it:
/// the quaternion `(l sin|l| / |l|, cos|l|)` (so the rotation angle is
/// `2|l|`). Unlike the demo, which returns the identity below `|l| = 0.01`,
/// this is continuous: `sin|l| / |l|` tends to 1.
#[inline(never)] // two call sites (reset, every joint): one copy in flash
pub fn quat_exp<R: Real>(l: Vec3<R>) -> Quat<R> {
    let w = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
    let (sin, cos) = w.sin_cos();
    let k = if w > R::ZERO { sin / w } else { R::ONE };
    normalise_quat([l[0] * k, l[1] * k, l[2] * k, cos])
}

/// `q / |q|`; a zero or non-finite quaternion gives the identity.
pub fn normalise_quat<R: Real>(q: Quat<R>) -> Quat<R> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n > R::ZERO && n.is_finite() {
        [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
    } else {
        [R::ZERO, R::ZERO, R::ZERO, R::ONE]
    }
}

/// The quaternion of the yaw whose unit facing is `f = (sin t, cos t)`:
/// `(0, sin t/2, 0, cos t/2)`, from half-angle identities (no `atan2`),
/// each branch used where it does not cancel.
pub fn yaw_quat<R: Real>(f: Vec2<R>) -> Quat<R> {
    let half = R::lit(0.5);
    let (s, c) = (f[0], f[1]);
    let (sh, ch) = if c >= R::ZERO {
        let ch = ((R::ONE + c) * half).sqrt();
        (s * half / ch, ch)
    } else {
        let sh = ((R::ONE - c) * half).sqrt();
        let sh = if s < R::ZERO { -sh } else { sh };
        (sh, s * half / sh)
    };
    normalise_quat([R::ZERO, sh, R::ZERO, ch])
}

/// Hamilton product `a b` (apply `b`, then `a`).
pub fn quat_mul<R: Real>(a: Quat<R>, b: Quat<R>) -> Quat<R> {
    let [ax, ay, az, aw] = a;
    let [bx, by, bz, bw] = b;
    [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]
}

/// The representative with `w >= 0` (q and -q are the same rotation; one
/// sign makes recorded rotations comparable component by component).
pub fn canonical<R: Real>(q: Quat<R>) -> Quat<R> {
    if q[3] < R::ZERO {
        [-q[0], -q[1], -q[2], -q[3]]
    } else {
        q
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64]) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-12)
    }

    /// Rotates `v` by `q` (q v q*), for checks only.
    fn rotate(q: Quat<f64>, v: Vec3<f64>) -> Vec3<f64> {
        let p = quat_mul(
            quat_mul(q, [v[0], v[1], v[2], 0.0]),
            [-q[0], -q[1], -q[2], q[3]],
        );
        [p[0], p[1], p[2]]
    }

    #[test]
    fn yaw_turns_forward_onto_the_facing() {
        for i in 0..64 {
            let t = -3.1 + 0.1 * f64::from(i);
            let f = [t.sin(), t.cos()];
            assert!(close(&yaw2(f, forward()), &f));
            assert!(close(&unyaw2(f, f), &forward()));
            assert!(close(&turn2(forward(), t), &f));
            // The yaw quaternion is the same rotation as the yaw matrix.
            let v = [0.3, -1.2, 2.0];
            assert!(close(&rotate(yaw_quat(f), v), &yaw3(f, v)));
        }
    }

    #[test]
    fn mix_directions_takes_the_short_way() {
        let a = [0.0f64, 1.0];
        let b = [1.0f64, 0.0];
        let m = mix_directions(a, b, 0.5);
        let h = core::f64::consts::FRAC_1_SQRT_2;
        assert!(close(&m, &[h, h]));
        // Across the +-pi seam the short way goes through -z.
        let from = [(-3.0f64).sin(), (-3.0f64).cos()];
        let to = [3.0f64.sin(), 3.0f64.cos()];
        let mid = mix_directions(from, to, 0.5);
        assert!(close(&mid, &[0.0, -1.0]) || close(&mid, &[-0.0, -1.0]));
        assert!(close(&mix_directions(a, b, 0.0), &a));
        assert!(close(&mix_directions(a, b, 1.0), &b));
        // Zero vectors act as +z, as atan2(0, 0) = 0 in the demo.
        assert!(close(&mix_directions([0.0, 0.0], b, 0.0), &a));
    }

    #[test]
    fn quat_exp_is_continuous_and_unit() {
        let q0 = quat_exp([0.0f64, 0.0, 0.0]);
        assert_eq!(q0, [0.0, 0.0, 0.0, 1.0]);
        let q = quat_exp([0.001f64, 0.0, 0.0]);
        assert!((q[0] - 0.001f64.sin()).abs() < 1e-15);
        let q = quat_exp([0.3f64, -0.4, 0.5]);
        let n: f64 = q.iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-15);
        // Angle 2|l| about l / |l|.
        let w = (0.5f64).sqrt();
        assert!((q[3] - w.cos()).abs() < 1e-15);
    }

    #[test]
    fn canonical_flips_to_non_negative_w() {
        assert_eq!(canonical([1.0f32, 2.0, 3.0, -0.5]), [-1.0, -2.0, -3.0, 0.5]);
        assert_eq!(canonical([1.0f32, 2.0, 3.0, 0.5]), [1.0, 2.0, 3.0, 0.5]);
    }
}
