//! The little rotation algebra the BVH solver needs, in `f64`: 3x3 matrices,
//! axis-angle rotations, the swing between two directions, and Euler angles
//! in any of the six Tait-Bryan orders BVH channels can name.
//!
//! Written out here rather than borrowed from a linear-algebra crate because
//! the solver needs exactly these few operations and two details a general
//! library does not give: Euler angles for an arbitrary channel order, and
//! the choice, among the equivalent angle triples, of the one nearest the
//! previous frame (so the channels do not jump by 360 degrees).

/// A 3-vector.
pub type Vec3 = [f64; 3];
/// A 3x3 matrix, row-major: `m[row][col]`. Rotations act on column vectors.
pub type Mat3 = [[f64; 3]; 3];

/// The identity rotation.
pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// `a / |a|`, or `None` when `|a|` is below `eps`.
pub fn unit(a: Vec3, eps: f64) -> Option<Vec3> {
    let n = norm(a);
    (n > eps && n.is_finite()).then(|| scale(a, 1.0 / n))
}

/// The part of `a` perpendicular to the unit vector `d`.
pub fn perp(a: Vec3, d: Vec3) -> Vec3 {
    sub(a, scale(d, dot(a, d)))
}

pub fn mul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

pub fn mul_vec(m: &Mat3, v: Vec3) -> Vec3 {
    std::array::from_fn(|r| dot(m[r], v))
}

pub fn transpose(m: &Mat3) -> Mat3 {
    std::array::from_fn(|r| std::array::from_fn(|c| m[c][r]))
}

/// The matrix whose columns are `a`, `b`, `c`.
pub fn from_cols(a: Vec3, b: Vec3, c: Vec3) -> Mat3 {
    [[a[0], b[0], c[0]], [a[1], b[1], c[1]], [a[2], b[2], c[2]]]
}

/// Rotation by `angle` radians about the unit `axis` (Rodrigues).
pub fn axis_angle(axis: Vec3, angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    let [x, y, z] = axis;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// Rotation by `angle` radians about coordinate axis `axis` (0 = x, 1 = y, 2 = z).
pub fn about(axis: usize, angle: f64) -> Mat3 {
    let mut e = [0.0; 3];
    e[axis] = 1.0;
    axis_angle(e, angle)
}

/// The smallest rotation taking unit `from` to unit `to`. When they are
/// opposite, the half turn is about `fallback_axis` (made perpendicular to
/// `from`), so the result is still defined.
pub fn swing(from: Vec3, to: Vec3, fallback_axis: Vec3) -> Mat3 {
    let c = dot(from, to).clamp(-1.0, 1.0);
    let axis = cross(from, to);
    match unit(axis, 1e-12) {
        Some(a) => axis_angle(a, norm(axis).atan2(c)),
        None if c > 0.0 => IDENTITY,
        None => {
            let a = unit(perp(fallback_axis, from), 1e-12)
                .or_else(|| unit(perp([1.0, 0.0, 0.0], from), 1e-6))
                .unwrap_or([0.0, 1.0, 0.0]);
            axis_angle(a, std::f64::consts::PI)
        }
    }
}

/// The angle of rotation `a⁻¹ b`, radians (0 ..= π): how far apart two
/// orientations are.
pub fn angle_between(a: &Mat3, b: &Mat3) -> f64 {
    let m = mul(&transpose(a), b);
    let tr = m[0][0] + m[1][1] + m[2][2];
    // acos is ill-conditioned near 0; use the skew part as well.
    let s = norm([m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]]) / 2.0;
    s.atan2((tr - 1.0) / 2.0)
}

/// An Euler order as BVH channels name it: `[i, j, k]` means the channels
/// `i`, `j`, `k` rotation in that order and the matrix `R_i(a) R_j(b) R_k(c)`
/// (the first channel is the outermost rotation).
pub type Order = [usize; 3];

const AXIS_NAMES: [&str; 3] = ["X", "Y", "Z"];

/// `"Zrotation Yrotation Xrotation"` for `[2, 1, 0]`.
pub fn channel_names(order: Order) -> String {
    order
        .iter()
        .map(|&a| format!("{}rotation", AXIS_NAMES[a]))
        .collect::<Vec<_>>()
        .join(" ")
}

/// The matrix of Euler angles (radians) in `order`.
pub fn from_euler(order: Order, angles: Vec3) -> Mat3 {
    let m = mul(&about(order[0], angles[0]), &about(order[1], angles[1]));
    mul(&m, &about(order[2], angles[2]))
}

fn wrap_near(angle: f64, near: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    angle - tau * ((angle - near) / tau).round()
}

/// Euler angles (radians) of rotation `m` in `order`, chosen among the
/// equivalent triples (the two Tait-Bryan solutions, each up to whole turns)
/// as the one nearest `prev`. In gimbal lock the last angle keeps its
/// previous value.
pub fn to_euler(order: Order, m: &Mat3, prev: Vec3) -> Vec3 {
    let [i, j, k] = order;
    let even = matches!(order, [0, 1, 2] | [1, 2, 0] | [2, 0, 1]);
    let s = if even { 1.0 } else { -1.0 };
    let sb = (s * m[i][k]).clamp(-1.0, 1.0);
    let b = sb.asin();
    let c = if sb.abs() < 1.0 - 1e-12 {
        (-s * m[i][j]).atan2(m[i][i])
    } else {
        prev[2]
    };
    // The first angle from what is left: R_i(a) = m R_k(-c) R_j(-b).
    let n = mul(&mul(m, &about(k, -c)), &about(j, -b));
    let (p, q) = ((i + 1) % 3, (i + 2) % 3);
    let a = n[q][p].atan2(n[p][p]);
    let pi = std::f64::consts::PI;
    let candidates = [[a, b, c], [a + pi, pi - b, c + pi]];
    let mut best = [0.0; 3];
    let mut best_cost = f64::INFINITY;
    for cand in candidates {
        let w: Vec3 = std::array::from_fn(|t| wrap_near(cand[t], prev[t]));
        let cost: f64 = (0..3).map(|t| (w[t] - prev[t]).abs()).sum();
        if cost < best_cost {
            best_cost = cost;
            best = w;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    const ORDERS: [Order; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];

    fn close(a: &Mat3, b: &Mat3, tol: f64) -> bool {
        (0..3).all(|r| (0..3).all(|c| (a[r][c] - b[r][c]).abs() < tol))
    }

    fn pseudo_random(n: usize) -> Vec<Vec3> {
        let mut x = 0.123_456_789f64;
        (0..n)
            .map(|_| {
                std::array::from_fn(|_| {
                    x = (x * 9301.0 + 49297.0) % 233280.0 / 233280.0 * 1000.0;
                    (x.fract() - 0.5) * 6.0
                })
            })
            .collect()
    }

    #[test]
    fn euler_round_trips_in_every_order() {
        for order in ORDERS {
            for angles in pseudo_random(200) {
                let m = from_euler(order, angles);
                let back = to_euler(order, &m, [0.0; 3]);
                assert!(
                    close(&from_euler(order, back), &m, 1e-9),
                    "{order:?} {angles:?}"
                );
            }
        }
    }

    #[test]
    fn euler_in_gimbal_lock_still_round_trips() {
        for order in ORDERS {
            for b in [std::f64::consts::FRAC_PI_2, -std::f64::consts::FRAC_PI_2] {
                let m = from_euler(order, [0.4, b, -1.1]);
                let back = to_euler(order, &m, [0.0, 0.0, 0.3]);
                assert!(close(&from_euler(order, back), &m, 1e-9), "{order:?}");
            }
        }
    }

    #[test]
    fn euler_picks_the_triple_nearest_the_previous_one() {
        let order = [2, 1, 0];
        let prev = [3.0, 0.1, -3.0];
        let m = from_euler(order, [3.2, 0.12, -3.1]);
        let got = to_euler(order, &m, prev);
        assert!(
            (got[0] - 3.2).abs() < 1e-9 && (got[2] + 3.1).abs() < 1e-9,
            "{got:?}"
        );
    }

    #[test]
    fn swing_maps_from_to_to() {
        for v in pseudo_random(50).chunks(2) {
            let (a, b) = (unit(v[0], 1e-9).unwrap(), unit(v[1], 1e-9).unwrap());
            let got = mul_vec(&swing(a, b, [0.0, 0.0, 1.0]), a);
            assert!(norm(sub(got, b)) < 1e-12);
        }
        let x = [1.0, 0.0, 0.0];
        let got = mul_vec(&swing(x, scale(x, -1.0), [0.0, 1.0, 0.0]), x);
        assert!(norm(sub(got, scale(x, -1.0))) < 1e-12);
    }

    #[test]
    fn angle_between_is_the_rotation_angle() {
        let a = about(1, 0.3);
        let b = mul(&a, &axis_angle(unit([1.0, 2.0, 3.0], 0.0).unwrap(), 0.25));
        assert!((angle_between(&a, &b) - 0.25).abs() < 1e-12);
        assert!(angle_between(&a, &a).abs() < 1e-12);
        assert_eq!(channel_names([2, 0, 1]), "Zrotation Xrotation Yrotation");
    }
}
