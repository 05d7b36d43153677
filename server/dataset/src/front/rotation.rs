//! Quaternions: rotating points and the yaw of a child's `rot`.

use super::json::identity_quaternion;

/// Rotates `v` by the unit quaternion `q = [x, y, z, w]`.
pub(super) fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let [x, y, z, w] = q;
    // v' = v + 2w (q × v) + 2 q × (q × v)
    let t = [2.0 * (y * v[2] - z * v[1]), 2.0 * (z * v[0] - x * v[2]), 2.0 * (x * v[1] - y * v[0])];
    [
        v[0] + w * t[0] + (y * t[2] - z * t[1]),
        v[1] + w * t[1] + (z * t[0] - x * t[2]),
        v[2] + w * t[2] + (x * t[1] - y * t[0]),
    ]
}

pub(super) fn normalized(q: [f64; 4]) -> [f64; 4] {
    let norm = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    if norm.is_finite() && norm > 1e-12 { q.map(|c| c / norm) } else { identity_quaternion() }
}

/// The yaw (SPEC §1: right-handed about +y, local `+x` to `(cos yaw, 0, −sin yaw)`) of a
/// 3D-FRONT rotation `[x, y, z, w]`, normalised first: the heading of the rotated local `+x`
/// projected on the plan (of the rotated `+z` when `+x` points straight up or down). In
/// `(−π, π]`; a zero quaternion is the identity.
pub fn yaw_from_quaternion(rot: [f64; 4]) -> f64 {
    let q = normalized(rot);
    let x_axis = rotate(q, [1.0, 0.0, 0.0]);
    if x_axis[0].hypot(x_axis[2]) > 1e-6 {
        (-x_axis[2]).atan2(x_axis[0])
    } else {
        // Local +z goes to (sin yaw, 0, cos yaw).
        let z_axis = rotate(q, [0.0, 0.0, 1.0]);
        z_axis[0].atan2(z_axis[2])
    }
}
