//! Closed-form starting values for the resection: no operator
//! pre-orientation.
//!
//! For control points spread in depth, the direct linear transformation
//! (Abdel-Aziz and Karara 1971): the 11 parameters of the 3x4 projective
//! matrix `P ~ K0 D Rᵀ [I | -X0]` from at least 6 points (Hartley's
//! normalisation, smallest eigenvector of `AᵀA`), decomposed by an RQ split
//! into the principal distance and point and the rotation of Eq. (1) in
//! OpenPTV's conventions. For control points in one plane the DLT is
//! singular; then the plane-to-image homography, with the principal distance
//! and point taken as known, gives the exterior orientation.
//!
//! Both ignore refraction and lens distortion (the image points are
//! corrected only by the setup's distortion, usually none): they only have to
//! land in the adjustment's region of convergence, which the strict model of
//! [`super::adjustment`] then refines.

use nalgebra::{DMatrix, Matrix3, Point2, Point3, SMatrix, SymmetricEigen, Vector2, Vector3};

use crate::photogrammetry::camera::{rotation_angles, CameraParameters};

/// A projective matrix from world to homogeneous metric image coordinates.
type Projective = SMatrix<f64, 3, 4>;

/// The eigendecomposition of a symmetric matrix, `None` for non-finite
/// entries or no convergence (nalgebra's `new` would iterate forever).
pub(crate) fn symmetric_eigen<D>(m: nalgebra::OMatrix<f64, D, D>) -> Option<SymmetricEigen<f64, D>>
where
    D: nalgebra::Dim + nalgebra::DimSub<nalgebra::U1>,
    nalgebra::DefaultAllocator: nalgebra::allocator::Allocator<D, D>
        + nalgebra::allocator::Allocator<D>
        + nalgebra::allocator::Allocator<nalgebra::DimDiff<D, nalgebra::U1>>,
{
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    SymmetricEigen::try_new(m, f64::EPSILON, 10_000)
}

/// How far from a plane the control points are: the smallest singular value
/// of their centred coordinates relative to the largest.
pub(crate) fn flatness(points: &[Point3<f64>]) -> f64 {
    if points.len() < 3 {
        return 0.0;
    }
    let n = points.len() as f64;
    let centre = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut scatter = Matrix3::zeros();
    for p in points {
        let d = p.coords - centre;
        scatter += d * d.transpose();
    }
    let Some(eigen) = symmetric_eigen(scatter) else {
        return 0.0;
    };
    let mut values: Vec<f64> = eigen
        .eigenvalues
        .iter()
        .map(|v| v.max(0.0).sqrt())
        .collect();
    values.sort_by(f64::total_cmp);
    if values[2] > 0.0 {
        values[0] / values[2]
    } else {
        0.0
    }
}

/// Similarity that moves points to their centroid and scales their mean
/// distance to `sqrt(dim)` (Hartley's normalisation); `(centre, scale)`.
fn normalisation<const D: usize>(
    points: impl Iterator<Item = SMatrix<f64, D, 1>> + Clone,
) -> (SMatrix<f64, D, 1>, f64) {
    let n = points.clone().count().max(1) as f64;
    let centre = points
        .clone()
        .fold(SMatrix::<f64, D, 1>::zeros(), |a, p| a + p)
        / n;
    let mean = points.map(|p| (p - centre).norm()).sum::<f64>() / n;
    let scale = if mean > 0.0 {
        (D as f64).sqrt() / mean
    } else {
        1.0
    };
    (centre, scale)
}

/// The null vector of `AᵀA`: the eigenvector of its smallest eigenvalue.
fn null_vector(a: &DMatrix<f64>) -> Option<nalgebra::DVector<f64>> {
    let ata = a.transpose() * a;
    let eigen = symmetric_eigen(ata)?;
    let (index, _) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let v = eigen.eigenvectors.column(index).into_owned();
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// The DLT: the projective matrix mapping world points to metric image
/// coordinates (mm, y up, relative to the sensor centre).
fn dlt(points: &[(Point3<f64>, Vector2<f64>)]) -> Option<Projective> {
    let (c3, s3) = normalisation(points.iter().map(|(p, _)| p.coords));
    let (c2, s2) = normalisation(points.iter().map(|(_, m)| *m));
    let mut a = DMatrix::zeros(2 * points.len(), 12);
    for (i, (p, m)) in points.iter().enumerate() {
        let x = (p.coords - c3) * s3;
        let u = (m - c2) * s2;
        let xh = [x.x, x.y, x.z, 1.0];
        for k in 0..4 {
            a[(2 * i, k)] = xh[k];
            a[(2 * i, 8 + k)] = -u.x * xh[k];
            a[(2 * i + 1, 4 + k)] = xh[k];
            a[(2 * i + 1, 8 + k)] = -u.y * xh[k];
        }
    }
    let v = null_vector(&a)?;
    let normalised = Projective::from_row_slice(v.as_slice());
    // Undo the normalisations: P = T2⁻¹ P̃ T3.
    let t3 = SMatrix::<f64, 4, 4>::new(
        s3,
        0.0,
        0.0,
        -s3 * c3.x,
        0.0,
        s3,
        0.0,
        -s3 * c3.y,
        0.0,
        0.0,
        s3,
        -s3 * c3.z,
        0.0,
        0.0,
        0.0,
        1.0,
    );
    let t2_inv = Matrix3::new(1.0 / s2, 0.0, c2.x, 0.0, 1.0 / s2, c2.y, 0.0, 0.0, 1.0);
    Some(t2_inv * normalised * t3)
}

/// RQ decomposition of a 3x3 matrix by Gram-Schmidt from the bottom row:
/// `M = K Q` with `K` upper triangular (positive diagonal), `Q` orthonormal.
fn rq(m: &Matrix3<f64>) -> Option<(Matrix3<f64>, Matrix3<f64>)> {
    let rows: [Vector3<f64>; 3] = [
        m.row(0).transpose(),
        m.row(1).transpose(),
        m.row(2).transpose(),
    ];
    let k22 = rows[2].norm();
    if k22 == 0.0 {
        return None;
    }
    let q2 = rows[2] / k22;
    let k12 = rows[1].dot(&q2);
    let r1 = rows[1] - q2 * k12;
    let k11 = r1.norm();
    if k11 == 0.0 {
        return None;
    }
    let q1 = r1 / k11;
    let k02 = rows[0].dot(&q2);
    let k01 = rows[0].dot(&q1);
    let r0 = rows[0] - q2 * k02 - q1 * k01;
    let k00 = r0.norm();
    if k00 == 0.0 {
        return None;
    }
    let q0 = r0 / k00;
    let k = Matrix3::new(k00, k01, k02, 0.0, k11, k12, 0.0, 0.0, k22);
    let q = Matrix3::from_rows(&[q0.transpose(), q1.transpose(), q2.transpose()]);
    Some((k, q))
}

/// The pose and interior orientation from a DLT on at least 6 points not in
/// one plane. `metric` are the observations in metric image coordinates
/// with the setup's distortion removed. Returns a copy of `setup` with
/// exterior and interior replaced; `None` if the points do not determine
/// them (too few, coplanar, or all on a line).
pub(crate) fn start_from_dlt(
    setup: &CameraParameters,
    points: &[(Point3<f64>, Vector2<f64>)],
) -> Option<CameraParameters> {
    if points.len() < 6 {
        return None;
    }
    let p = dlt(points)?;
    let mut m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
    let mut p4: Vector3<f64> = p.column(3).into_owned();
    // P ~ K0 D Rᵀ [I | -X0] with det(K0 D Rᵀ) = -c² < 0 fixes the sign.
    let det = m.determinant();
    if !det.is_finite() || det == 0.0 {
        return None;
    }
    if det > 0.0 {
        m = -m;
        p4 = -p4;
    }
    let position = -(m.try_inverse()? * p4);
    let (k, q) = rq(&m)?;
    let k = k / k[(2, 2)];
    let d = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
    let rotation = q.transpose() * d;
    let (omega, phi, kappa) = rotation_angles(&rotation);
    let mut camera = setup.clone();
    camera.exterior.position = position;
    camera.exterior.omega = omega;
    camera.exterior.phi = phi;
    camera.exterior.kappa = kappa;
    camera.interior.c = 0.5 * (k[(0, 0)] + k[(1, 1)]);
    camera.interior.xh = k[(0, 2)];
    camera.interior.yh = k[(1, 2)];
    let finite = camera.exterior.position.iter().all(|v| v.is_finite())
        && [omega, phi, kappa, camera.interior.c]
            .iter()
            .all(|v| v.is_finite());
    (finite && camera.interior.c > 0.0).then_some(camera)
}

/// The pose from control points in one plane, with the setup's principal
/// distance and point taken as known: the plane-to-image homography
/// `H ~ D [r1 r2 t]` of normalised image coordinates, orthonormalised.
pub(crate) fn start_from_plane(
    setup: &CameraParameters,
    points: &[(Point3<f64>, Vector2<f64>)],
) -> Option<CameraParameters> {
    if points.len() < 4 {
        return None;
    }
    let n = points.len() as f64;
    let origin = points
        .iter()
        .fold(Vector3::zeros(), |a, (p, _)| a + p.coords)
        / n;
    let mut scatter = Matrix3::zeros();
    for (p, _) in points {
        let d = p.coords - origin;
        scatter += d * d.transpose();
    }
    let eigen = symmetric_eigen(scatter)?;
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[b].total_cmp(&eigen.eigenvalues[a]));
    let e1: Vector3<f64> = eigen.eigenvectors.column(order[0]).into_owned();
    let e2: Vector3<f64> = eigen.eigenvectors.column(order[1]).into_owned();
    let e3 = e1.cross(&e2);
    let interior = &setup.interior;
    // Normalised image coordinates (x/c, y/c) of the flat image point.
    let planar: Vec<(Vector2<f64>, Vector2<f64>)> = points
        .iter()
        .map(|(p, m)| {
            let d = p.coords - origin;
            (
                Vector2::new(d.dot(&e1), d.dot(&e2)),
                Vector2::new(
                    (m.x - interior.xh) / interior.c,
                    (m.y - interior.yh) / interior.c,
                ),
            )
        })
        .collect();
    let (cp, sp) = normalisation(planar.iter().map(|(u, _)| *u));
    let (ci, si) = normalisation(planar.iter().map(|(_, x)| *x));
    let mut a = DMatrix::zeros(2 * planar.len(), 9);
    for (i, (u, x)) in planar.iter().enumerate() {
        let u = (u - cp) * sp;
        let x = (x - ci) * si;
        let uh = [u.x, u.y, 1.0];
        for k in 0..3 {
            a[(2 * i, k)] = uh[k];
            a[(2 * i, 6 + k)] = -x.x * uh[k];
            a[(2 * i + 1, 3 + k)] = uh[k];
            a[(2 * i + 1, 6 + k)] = -x.y * uh[k];
        }
    }
    let v = null_vector(&a)?;
    let hn = Matrix3::from_row_slice(v.as_slice());
    let tp = Matrix3::new(sp, 0.0, -sp * cp.x, 0.0, sp, -sp * cp.y, 0.0, 0.0, 1.0);
    let ti_inv = Matrix3::new(1.0 / si, 0.0, ci.x, 0.0, 1.0 / si, ci.y, 0.0, 0.0, 1.0);
    let h = ti_inv * hn * tp;
    // (x/c, y/c, 1) ~ D (v / -v_z)... with v = Rᵀ(P - X0) = [r1 r2 t](u, w, 1):
    // (x, y, -c) ∝ v, so D h ∝ [r1 r2 t] with D = diag(1, 1, -1).
    let d = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0));
    let mut g = d * h;
    let scale = 2.0 / (g.column(0).norm() + g.column(1).norm());
    g *= scale;
    // The plane's origin must lie in front of the camera: v_z < 0.
    if g[(2, 2)] > 0.0 {
        g = -g;
    }
    let r1: Vector3<f64> = g.column(0).into_owned();
    let r2: Vector3<f64> = g.column(1).into_owned();
    let t: Vector3<f64> = g.column(2).into_owned();
    let approx = Matrix3::from_columns(&[r1, r2, r1.cross(&r2)]);
    if !approx.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = nalgebra::SVD::try_new(approx, true, true, f64::EPSILON, 10_000)?;
    let mut rt = svd.u? * svd.v_t?;
    if rt.determinant() < 0.0 {
        return None;
    }
    // rt = Rᵀ [e1 e2 e3], so Rᵀ = rt [e1 e2 e3]ᵀ.
    let basis = Matrix3::from_columns(&[e1, e2, e3]);
    rt *= basis.transpose();
    let rotation = rt.transpose();
    let position = origin - rotation * t;
    let (omega, phi, kappa) = rotation_angles(&rotation);
    let mut camera = setup.clone();
    camera.exterior.position = position;
    camera.exterior.omega = omega;
    camera.exterior.phi = phi;
    camera.exterior.kappa = kappa;
    camera
        .exterior
        .position
        .iter()
        .chain([omega, phi, kappa].iter())
        .all(|v| v.is_finite())
        .then_some(camera)
}

/// Metric image coordinates of a pixel with the setup's distortion removed
/// (`None` where it cannot be inverted).
pub(crate) fn ideal_metric(setup: &CameraParameters, pixel: Point2<f64>) -> Option<Vector2<f64>> {
    setup.distortion.remove(setup.sensor.pixel_to_metric(pixel))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photogrammetry::camera::rotation_matrix;
    use crate::photogrammetry::simulate::{self, RigSpec, TargetShape};

    /// A pinhole rig in air, points in a box: the DLT start is exact to
    /// rounding on noise-free images, and the plane start (with the true
    /// interior) is exact on a plane.
    #[test]
    fn closed_form_starts_are_exact_without_noise() {
        let mut spec = RigSpec::convergent(3);
        spec.tank = None;
        spec.principal_point = nalgebra::Vector2::new(0.05, -0.08);
        let mut rng = simulate::rng(1);
        let target = simulate::calibration_target(TargetShape::Volume, &spec.volume, 30, &mut rng);
        for camera in spec.build().unwrap() {
            let pairs: Vec<_> = target
                .iter()
                .map(|p| {
                    let pixel = camera.project(&p.position).unwrap();
                    (
                        p.position,
                        ideal_metric(camera.parameters(), pixel).unwrap(),
                    )
                })
                .collect();
            let start = start_from_dlt(camera.parameters(), &pairs).unwrap();
            let truth = camera.parameters();
            assert!((start.exterior.position - truth.exterior.position).norm() < 1e-6);
            assert!((start.interior.c - truth.interior.c).abs() < 1e-7);
            assert!((start.interior.xh - truth.interior.xh).abs() < 1e-7);
            let r = rotation_matrix(
                start.exterior.omega,
                start.exterior.phi,
                start.exterior.kappa,
            );
            assert!((r - camera.rotation()).abs().max() < 1e-9);
            let plane: Vec<_> = pairs
                .iter()
                .map(|(p, _)| Point3::new(p.x, p.y, 0.0))
                .map(|p| {
                    let pixel = camera.project(&p).unwrap();
                    (p, ideal_metric(truth, pixel).unwrap())
                })
                .collect();
            assert!(flatness(&plane.iter().map(|p| p.0).collect::<Vec<_>>()) < 1e-12);
            let start = start_from_plane(truth, &plane).unwrap();
            assert!((start.exterior.position - truth.exterior.position).norm() < 1e-6);
        }
    }
}
