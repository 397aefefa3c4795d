//! Iterative particle reconstruction (IPR) of one frame set: the particles
//! of a dense field (0.01..0.15 particles per pixel) from the images of
//! 2..16 cameras, after Wieneke (2013, Meas. Sci. Technol. 24 024008,
//! "Iterative reconstruction of volumetric particle distribution") and
//! Jahn, Schanz and Schröder (2021, Exp. Fluids 62:179, "Advanced
//! iterative particle reconstruction"), with the outer loops of OpenLPT
//! (Tan et al. 2020, Exp. Fluids 61:47) read for comparison, not copied.
//!
//! The method, per frame set:
//!
//! 1. **Particle image model** ([`otf`]): per camera an elliptic Gaussian
//!    estimated from the recording's isolated particle images (or stated).
//! 2. **Residual images** ([`image`]): each camera's recording minus a
//!    smooth background, minus the image of every particle found so far
//!    (Wieneke's Eq. 3, `I_res = I_rec - I_proj`).
//! 3. **Outer loop** k: the 2D peaks of every residual image (local maxima
//!    above a threshold, a fraction of the model's typical peak) are the
//!    targets of the existing correspondence search ([`Matcher`], epipolar
//!    bands through the walls, a band widened to [`IprParameters::tolerance`]).
//!    Every group of peaks whose rays meet is a candidate
//!    ([`Matcher::candidates`]), a peak in as many as it fits, as in
//!    Wieneke's triangulation of all possible matches (section 2.2): the
//!    1993 method's best-first choice, one particle per peak, lets a ghost
//!    hold the peaks of four true particles, which then never become
//!    candidates while it stands. The candidates, intersected by least
//!    squares, are painted (their images subtracted from the residuals with
//!    the residual's height at their centre) best-meeting rays first: a true
//!    particle's rays meet within the image noise, a ghost's only within the
//!    band, so the true one takes the light it shares with a ghost.
//! 4. **Shaking** (Wieneke section 2.3): every particle's position and
//!    per-camera intensities are fitted to its image patches in all
//!    cameras, the others' images subtracted (the "augmented" image
//!    `I_res + I_part`, Wieneke's Eq. 4): the cost `sum_c sum_px (I_aug -
//!    a_c G_c(x))²` is minimised by a Gauss-Newton step in the position
//!    (the intensities eliminated by their Schur complement, a step limited
//!    to half a pixel in every camera and halved while the cost rises), in
//!    place of the papers' ±0.1 px line search per axis: the same minimum,
//!    one projection with its Jacobian per camera instead of six
//!    projections. The particles are shaken one after the other, each
//!    against the residual the others left (Gauss-Seidel).
//! 5. **Ghosts** (Wieneke section 2.4): a candidate made of other
//!    particles' images loses its intensity to them while they are shaken;
//!    particles whose mean intensity falls below
//!    [`IprParameters::ghost_fraction`] of the model's typical peak, or
//!    whose image reaches that fraction of its camera's typical peak in
//!    fewer cameras than the loop requires, are removed, and so is the
//!    weaker of two particles closer than a pixel (overlaps resolved by
//!    shaking leave them apart). The test is per camera because the
//!    intensities are: a ghost loses its light in each camera to the one
//!    true particle whose image it borrowed there, and keeps a mean
//!    intensity from the cameras where that particle is not yet found.
//! 6. The last [`IprParameters::reduced_loops`] outer loops accept
//!    candidates seen in one camera less (Jahn et al. 2021, section 2.2:
//!    particles hidden behind brighter ones in one view).
//!
//! Per particle the result holds the position, its standard deviation
//! from the shaking's normal equations (`sigma0² (H')^-1`, `H'` the
//! position block's Schur complement and `sigma0²` the residual variance
//! of the patches), the mean intensity over the cameras that see it, and
//! `rms_px`: the RMS over those cameras of the shift by which each
//! camera's own image would move the particle's image (a 2D Gauss-Newton
//! step on that camera alone), the counterpart of the intersection's
//! reprojection residual.
//!
//! Memory: one float residual per pixel and camera, the particles (at most
//! one per 2x2 pixels of the first camera, [`max_targets`]), and the
//! matcher's index of the targets (linear in them).
//!
//! Not here (issue 32's later parts): the model's variation over
//! sub-volumes, Shake-the-Box over time.

pub mod image;
pub mod otf;

use nalgebra::{Matrix3, Point2, Point3, Vector2, Vector3};

use self::image::View;
pub use self::otf::Otf;
use super::camera::Camera;
use super::correspond::{max_targets, MatchError, Matcher, MatchingParameters, Particle};
use super::detect::{PreprocessError, Preprocessing};
use super::image::{GreyImage, SensorMismatch};
use super::volume::Volume;

/// How to reconstruct.
#[derive(Clone, Debug, PartialEq)]
pub struct IprParameters {
    /// The observation volume; `None` for the region all cameras look at.
    pub volume: Option<Volume>,
    /// Half-width (px) of the correspondence search's epipolar band (an
    /// upper bound, narrowed by the matcher to the frame's noise).
    pub tolerance: f64,
    /// Outer loops with candidates seen in every camera.
    pub loops: usize,
    /// Further outer loops with candidates seen in one camera less.
    pub reduced_loops: usize,
    /// Shaking passes over all particles per outer loop.
    pub shakes: usize,
    /// Peaks of the residual below this fraction of the model's typical
    /// peak are not candidates' images.
    pub peak_fraction: f64,
    /// Particles whose mean intensity is below this fraction of the
    /// model's typical peak are ghosts.
    pub ghost_fraction: f64,
    /// The particle image model per camera; `None` to estimate it.
    pub otf: Option<Vec<Otf>>,
}

impl Default for IprParameters {
    fn default() -> Self {
        IprParameters {
            volume: None,
            tolerance: 2.0,
            loops: 8,
            reduced_loops: 3,
            shakes: 3,
            peak_fraction: 0.25,
            ghost_fraction: 0.3,
            otf: None,
        }
    }
}

/// A reconstructed particle.
#[derive(Clone, Debug, PartialEq)]
pub struct ReconstructedParticle {
    /// Position (mm).
    pub position: Point3<f64>,
    /// Standard deviations of X, Y, Z (mm).
    pub sigma: Vector3<f64>,
    /// Mean peak intensity over the cameras that see it (grey levels).
    pub intensity: f64,
    /// RMS over its cameras of each camera's own image shift (px).
    pub rms_px: f64,
    /// How many cameras see it.
    pub cameras: usize,
}

/// What one outer loop did.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopReport {
    /// The loop (from 1).
    pub index: usize,
    /// The cameras a candidate had to be seen in.
    pub min_cameras: usize,
    /// Residual peaks per camera.
    pub peaks: Vec<usize>,
    /// Candidates from the correspondence search.
    pub candidates: usize,
    /// Particles removed as ghosts or duplicates.
    pub removed: usize,
    /// Particles after the loop.
    pub particles: usize,
    /// RMS of the residual images over all usable pixels (grey levels).
    pub residual_rms: f64,
}

/// The result.
#[derive(Clone, Debug, PartialEq)]
pub struct Reconstruction {
    /// The particles.
    pub particles: Vec<ReconstructedParticle>,
    /// The particle image model used, per camera.
    pub otf: Vec<Otf>,
    /// The outer loops.
    pub loops: Vec<LoopReport>,
}

/// Why a frame set cannot be reconstructed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IprError {
    /// Not one image per camera.
    #[error(
        "got {images} images for {cameras} cameras; give one image per camera, in camera order"
    )]
    ImageCount {
        /// Images given.
        images: usize,
        /// Cameras.
        cameras: usize,
    },
    /// A background or mask per camera, or none.
    #[error("got {given} backgrounds/masks for {cameras} cameras; give one per camera or none")]
    PreprocessingCount {
        /// Given.
        given: usize,
        /// Cameras.
        cameras: usize,
    },
    /// An image is not of its camera's sensor.
    #[error("the image of camera {camera} does not fit its sensor")]
    Sensor {
        /// The camera (0-based).
        camera: usize,
        /// The sizes that differ.
        #[source]
        source: SensorMismatch,
    },
    /// A background or mask does not fit the image.
    #[error("the background or mask of camera {camera} does not fit its image")]
    Preprocess {
        /// The camera (0-based).
        camera: usize,
        /// What does not fit.
        #[source]
        source: PreprocessError,
    },
    /// A stated model per camera is expected.
    #[error("got a particle image model for {given} cameras, but there are {cameras}")]
    OtfCount {
        /// Given.
        given: usize,
        /// Cameras.
        cameras: usize,
    },
    /// A stated model is not a spot.
    #[error("the particle image model of camera {camera} is not a spot: sigmas must be 0.3..4 px, |rho| < 0.95, the peak positive")]
    InvalidOtf {
        /// The camera (0-based).
        camera: usize,
    },
    /// Too few isolated particle images to estimate the model.
    #[error(
        "camera {camera}'s image has fewer than {} isolated particle images, too few to \
         estimate the particle image model; check that the image holds particles (brighter \
         than the background) and that the mask leaves them",
        otf::MIN_SAMPLES
    )]
    NoParticleImages {
        /// The camera (0-based).
        camera: usize,
    },
    /// The parameters or the volume do not suit the correspondence search.
    #[error("cannot search correspondences")]
    Matching(#[from] MatchError),
    /// A parameter is out of range.
    #[error("{0}")]
    Parameter(String),
}

/// One particle while it is being reconstructed.
#[derive(Clone, Debug)]
struct State {
    position: Point3<f64>,
    /// Per camera: the centre and intensity of its image as subtracted
    /// from the residual (`None`: not in that camera's image).
    images: Vec<Option<(Point2<f64>, f64)>>,
    sigma: Vector3<f64>,
    rms_px: f64,
}

impl State {
    /// In how many cameras the particle's image is at least `fraction` of
    /// that camera's typical peak. A ghost sits where the rays of other
    /// particles' images cross; once those particles are found, each takes
    /// its light back in its own camera, and the ghost keeps a faint image
    /// there while it may keep its mean intensity from the others.
    fn bright_in(&self, views: &[View], fraction: f64) -> usize {
        self.images
            .iter()
            .zip(views)
            .filter(|(image, view)| image.is_some_and(|(_, a)| a >= fraction * view.otf.peak))
            .count()
    }

    fn intensity(&self) -> (f64, usize) {
        let seen: Vec<f64> = self.images.iter().flatten().map(|&(_, a)| a).collect();
        let n = seen.len();
        (
            if n == 0 {
                0.0
            } else {
                seen.iter().sum::<f64>() / n as f64
            },
            n,
        )
    }
}

/// One camera's normal-equation terms at a position.
struct CameraTerms {
    centre: Point2<f64>,
    /// d(pixel)/d(position), 2x3.
    jacobian: nalgebra::Matrix2x3<f64>,
    gg: f64,
    gr: f64,
    /// Sums over the patch with `d = a (dG/du, dG/dv)`: `d dᵀ`, `d e`, `G d`.
    dd: nalgebra::Matrix2<f64>,
    de: Vector2<f64>,
    gd: Vector2<f64>,
    ge: f64,
    ee: f64,
    pixels: usize,
}

/// The terms of camera `view` for a particle at `position` with intensity
/// `amplitude` against the residual plus its own image (the caller has
/// added it back).
fn camera_terms(
    camera: &Camera,
    view: &View,
    position: &Point3<f64>,
    amplitude: f64,
) -> Option<CameraTerms> {
    let (centre, jacobian) = camera.project_with_jacobian(position).ok()?;
    let (x0, x1, y0, y1) = view.patch(centre)?;
    let mut t = CameraTerms {
        centre,
        jacobian,
        gg: 0.0,
        gr: 0.0,
        dd: nalgebra::Matrix2::zeros(),
        de: Vector2::zeros(),
        gd: Vector2::zeros(),
        ge: 0.0,
        ee: 0.0,
        pixels: 0,
    };
    for y in y0..y1 {
        for x in x0..x1 {
            let index = y * view.width + x;
            if !view.usable(index) {
                continue;
            }
            let r = f64::from(view.residual[index]);
            let (g, gu, gv) = view.spot(x, y, centre);
            let d = Vector2::new(amplitude * gu, amplitude * gv);
            let e = r - amplitude * g;
            t.gg += g * g;
            t.gr += g * r;
            t.dd += d * d.transpose();
            t.de += d * e;
            t.gd += d * g;
            t.ge += g * e;
            t.ee += e * e;
            t.pixels += 1;
        }
    }
    (t.pixels > 0 && t.gg > 1e-6).then_some(t)
}

/// The shared context of a reconstruction.
struct Context<'a> {
    cameras: &'a [Camera],
    volume: Volume,
    /// Object-space size of a pixel at the volume's centre (mm).
    mm_per_px: f64,
}

impl Context<'_> {
    /// The volume widened by two pixels: particles beyond it are lost.
    fn holds(&self, p: &Point3<f64>) -> bool {
        let m = 2.0 * self.mm_per_px;
        (0..3).all(|i| p[i] >= self.volume.min[i] - m && p[i] <= self.volume.max[i] + m)
    }
}

/// Shakes one particle: its image is added back to the residuals, its
/// position and intensities fitted (`iterations` Gauss-Newton steps), and
/// its new image subtracted. False if it left the volume or every image.
fn shake(state: &mut State, views: &mut [View], context: &Context<'_>, iterations: usize) -> bool {
    for (view, image) in views.iter_mut().zip(&state.images) {
        if let Some((centre, amplitude)) = image {
            view.paint(*centre, *amplitude);
        }
    }
    let n = views.len();
    let mut position = state.position;
    let mut amplitudes: Vec<f64> = (0..n)
        .map(|c| match state.images[c] {
            Some((_, a)) => a,
            None => context.cameras[c]
                .project(&position)
                .map_or(0.0, |centre| views[c].amplitude(centre)),
        })
        .collect();
    let evaluate = |position: &Point3<f64>, amplitudes: &[f64]| -> Vec<Option<CameraTerms>> {
        (0..n)
            .map(|c| camera_terms(&context.cameras[c], &views[c], position, amplitudes[c]))
            .collect()
    };
    let cost = |terms: &[Option<CameraTerms>]| terms.iter().flatten().map(|t| t.ee).sum::<f64>();
    let mut terms = evaluate(&position, &amplitudes);
    for _ in 0..iterations {
        // Normal equations in (X, a_c), the intensities eliminated.
        let mut h = Matrix3::<f64>::zeros();
        let mut g = Vector3::<f64>::zeros();
        let mut eliminated = Vec::with_capacity(n);
        for t in terms.iter() {
            let Some(t) = t else {
                eliminated.push(None);
                continue;
            };
            let jt = t.jacobian.transpose();
            let h_xx = jt * t.dd * t.jacobian;
            let g_x = jt * t.de;
            let h_xa = jt * t.gd;
            h += h_xx - h_xa * h_xa.transpose() / t.gg;
            g += g_x - h_xa * (t.ge / t.gg);
            eliminated.push(Some((h_xa, t.ge, t.gg)));
        }
        let Some(step) = h.try_inverse().map(|inverse| inverse * g) else {
            break;
        };
        // At most half a pixel in any camera.
        let longest = terms
            .iter()
            .flatten()
            .map(|t| (t.jacobian * step).norm())
            .fold(0.0, f64::max);
        let mut scale = if longest > 0.5 { 0.5 / longest } else { 1.0 };
        let before = cost(&terms);
        let mut accepted = false;
        for _ in 0..3 {
            let trial = position + step * scale;
            let trial_amplitudes: Vec<f64> = (0..n)
                .map(|c| match &eliminated[c] {
                    Some((h_xa, ge, gg)) => {
                        (amplitudes[c] + (ge - h_xa.dot(&(step * scale))) / gg).max(0.0)
                    }
                    None => amplitudes[c],
                })
                .collect();
            let trial_terms = evaluate(&trial, &trial_amplitudes);
            if cost(&trial_terms) <= before {
                position = trial;
                amplitudes = trial_amplitudes;
                terms = trial_terms;
                accepted = true;
                break;
            }
            scale *= 0.5;
        }
        if !accepted || step.norm() * scale < 1e-4 * context.mm_per_px {
            break;
        }
    }
    // The intensities at the final position, by linear least squares, and
    // the uncertainties there.
    let mut images = Vec::with_capacity(n);
    let mut h = Matrix3::<f64>::zeros();
    let (mut ssr, mut pixels, mut seen) = (0.0, 0usize, 0usize);
    let mut shifts = 0.0;
    for (c, t) in terms.iter().enumerate() {
        let Some(t) = t else {
            images.push(None);
            continue;
        };
        let a = (t.gr / t.gg).max(0.0);
        if a <= 0.0 {
            images.push(None);
            continue;
        }
        // Rescale the terms computed with the iteration's intensity to `a`.
        let ratio = if amplitudes[c] > 0.0 {
            a / amplitudes[c]
        } else {
            0.0
        };
        let dd = t.dd * ratio * ratio;
        let gd = t.gd * ratio;
        let jt = t.jacobian.transpose();
        let h_xa = jt * gd;
        h += jt * dd * t.jacobian - h_xa * h_xa.transpose() / t.gg;
        // The residual sum at intensity `a`: e = r - a g.
        let residual = (t.ee + 2.0 * amplitudes[c] * t.ge + amplitudes[c].powi(2) * t.gg)
            - 2.0 * a * t.gr
            + a * a * t.gg;
        ssr += residual.max(0.0);
        pixels += t.pixels;
        seen += 1;
        // This camera's own shift: the 3x3 system in (du, dv, da).
        let de = t.de * ratio + t.gd * ratio * (amplitudes[c] - a);
        let mut m = Matrix3::zeros();
        m.fixed_view_mut::<2, 2>(0, 0).copy_from(&dd);
        m.fixed_view_mut::<2, 1>(0, 2).copy_from(&gd);
        m.fixed_view_mut::<1, 2>(2, 0).copy_from(&gd.transpose());
        m[(2, 2)] = t.gg;
        let rhs = Vector3::new(de.x, de.y, 0.0);
        if let Some(solution) = m.try_inverse().map(|inverse| inverse * rhs) {
            shifts += solution.x * solution.x + solution.y * solution.y;
        }
        images.push(Some((t.centre, a)));
    }
    let dof = pixels as f64 - 3.0 - seen as f64;
    state.sigma = match h.try_inverse() {
        Some(inverse) if dof > 0.0 => (inverse * (ssr / dof))
            .diagonal()
            .map(|v| v.max(0.0).sqrt()),
        _ => Vector3::repeat(f64::NAN),
    };
    state.rms_px = if seen > 0 {
        (shifts / seen as f64).sqrt()
    } else {
        f64::NAN
    };
    state.position = position;
    state.images = images;
    for (view, image) in views.iter_mut().zip(&state.images) {
        if let Some((centre, amplitude)) = image {
            view.paint(*centre, -amplitude);
        }
    }
    seen > 0 && context.holds(&position)
}

/// Removes a particle's image from the residuals (adds its light back).
fn restore(state: &State, views: &mut [View]) {
    for (view, image) in views.iter_mut().zip(&state.images) {
        if let Some((centre, amplitude)) = image {
            view.paint(*centre, *amplitude);
        }
    }
}

/// Indices of particles closer than `distance` (mm) to an earlier, stronger
/// one, by a grid of cells `distance` wide.
fn duplicates(states: &[State], distance: f64) -> Vec<bool> {
    use std::collections::HashMap;
    let cell = |p: &Point3<f64>| {
        (
            (p.x / distance).floor() as i64,
            (p.y / distance).floor() as i64,
            (p.z / distance).floor() as i64,
        )
    };
    let mut order: Vec<usize> = (0..states.len()).collect();
    order.sort_by(|&a, &b| states[b].intensity().0.total_cmp(&states[a].intensity().0));
    let mut grid: HashMap<(i64, i64, i64), Vec<usize>> = HashMap::new();
    let mut duplicate = vec![false; states.len()];
    for i in order {
        let p = &states[i].position;
        let (cx, cy, cz) = cell(p);
        let mut near = false;
        'search: for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = grid.get(&(cx + dx, cy + dy, cz + dz)) {
                        if list
                            .iter()
                            .any(|&j| (states[j].position - p).norm() < distance)
                        {
                            near = true;
                            break 'search;
                        }
                    }
                }
            }
        }
        if near {
            duplicate[i] = true;
        } else {
            grid.entry((cx, cy, cz)).or_default().push(i);
        }
    }
    duplicate
}

/// Reconstructs the particles of one frame set.
///
/// `images` one per camera (each its sensor's size), `preprocessing` one
/// per camera or none; `progress` is called after every outer loop.
pub fn reconstruct(
    cameras: &[Camera],
    images: &[GreyImage],
    preprocessing: &[Preprocessing],
    parameters: &IprParameters,
    progress: &mut dyn FnMut(&LoopReport),
) -> Result<Reconstruction, IprError> {
    check_request(cameras, images, preprocessing, parameters)?;
    let n = cameras.len();
    let matching = |min_cameras: usize| MatchingParameters {
        tolerance: parameters.tolerance,
        volume: parameters.volume,
        min_cameras,
        similarity: None,
    };
    let full = Matcher::new(cameras, &matching(n))?;
    let reduced = if n > 2 && parameters.reduced_loops > 0 {
        Some(Matcher::new(cameras, &matching(n - 1))?)
    } else {
        None
    };
    let cameras = full.cameras();
    let volume = *full.volume();

    let mut views = residual_views(images, preprocessing, parameters)?;
    let typical_peak = {
        let mut peaks: Vec<f64> = views.iter().map(|v| v.otf.peak).collect();
        peaks.sort_by(f64::total_cmp);
        peaks[peaks.len() / 2]
    };
    let mm_per_px = mm_per_px(cameras, &volume);
    if !mm_per_px.is_finite() {
        return Err(IprError::Matching(MatchError::NoDefaultVolume));
    }
    let context = Context {
        cameras,
        volume,
        mm_per_px,
    };
    let limit = max_targets(cameras[0].sensor());
    let threshold = (parameters.peak_fraction * typical_peak) as f32;

    let mut states: Vec<State> = Vec::new();
    let mut reports = Vec::new();
    let total = parameters.loops
        + if reduced.is_some() {
            parameters.reduced_loops
        } else {
            0
        };
    for index in 1..=total {
        let (matcher, min_cameras) = if index <= parameters.loops {
            (&full, n)
        } else {
            (reduced.as_ref().unwrap_or(&full), n - 1)
        };
        let peaks: Vec<_> = views
            .iter()
            .map(|v| {
                let mut p = v.peaks(threshold);
                // The matcher's bound: the brightest peaks first.
                if p.len() > limit {
                    p.sort_by_key(|b| std::cmp::Reverse(b.sumg));
                    p.truncate(limit);
                }
                p
            })
            .collect();
        // Every candidate, a peak in several (Wieneke 2013, section 2.2),
        // best-meeting rays first: the first to be painted take the light,
        // and a true particle's rays meet within the image noise where a
        // ghost's meet only within the band. (Two cameras have no
        // candidates beyond the unambiguous pairs.)
        let mut candidates = if n >= 3 {
            matcher.candidates(&peaks)?
        } else {
            matcher.match_frame(&peaks)?
        };
        candidates.sort_by(|a, b| a.rms_px.total_cmp(&b.rms_px));
        let candidate_count = candidates.len();
        let first_new = states.len();
        add_candidates(candidates, &mut states, &mut views, &context);
        let keep = shake_all(
            &mut states,
            &mut views,
            &context,
            parameters.shakes,
            first_new,
        );
        let removed = remove_ghosts(
            &mut states,
            &mut views,
            keep,
            mm_per_px,
            parameters.ghost_fraction,
            typical_peak,
            min_cameras,
        );
        let report = LoopReport {
            index,
            min_cameras,
            peaks: peaks.iter().map(Vec::len).collect(),
            candidates: candidate_count,
            removed,
            particles: states.len(),
            residual_rms: residual_rms(&views),
        };
        progress(&report);
        reports.push(report);
    }
    // A last pass settles the uncertainties at the final positions.
    let mut keep = vec![true; states.len()];
    for (i, state) in states.iter_mut().enumerate() {
        if !shake(state, &mut views, &context, 1) {
            restore(state, &mut views);
            keep[i] = false;
        }
    }
    let particles = states
        .iter()
        .zip(keep)
        .filter(|(_, keep)| *keep)
        .map(|(s, _)| {
            let (intensity, seen) = s.intensity();
            ReconstructedParticle {
                position: s.position,
                sigma: s.sigma,
                intensity,
                rms_px: s.rms_px,
                cameras: seen,
            }
        })
        .collect();
    Ok(Reconstruction {
        particles,
        otf: views.iter().map(|v| v.otf).collect(),
        loops: reports,
    })
}

/// An outer loop's new particles: each candidate inside the volume with
/// its image amplitude per camera, painted out of the residual images.
fn add_candidates(
    candidates: Vec<Particle>,
    states: &mut Vec<State>,
    views: &mut [View],
    context: &Context<'_>,
) {
    for particle in candidates {
        if !context.holds(&particle.position) {
            continue;
        }
        let images = context
            .cameras
            .iter()
            .zip(views.iter())
            .map(|(camera, view)| {
                camera.project(&particle.position).ok().and_then(|centre| {
                    let a = view.amplitude(centre);
                    (a > 0.0).then_some((centre, a))
                })
            })
            .collect();
        let state = State {
            position: particle.position,
            images,
            sigma: particle.sigma,
            rms_px: particle.rms_px,
        };
        for (view, image) in views.iter_mut().zip(&state.images) {
            if let Some((centre, amplitude)) = image {
                view.paint(*centre, -amplitude);
            }
        }
        states.push(state);
    }
}

/// `shakes` passes of shaking, the particles from `first_new` on (this
/// loop's) twice as often as the settled ones; per particle whether it is
/// kept (one that no longer images is restored to the residual images).
fn shake_all(
    states: &mut [State],
    views: &mut [View],
    context: &Context<'_>,
    shakes: usize,
    first_new: usize,
) -> Vec<bool> {
    let mut keep = vec![true; states.len()];
    for pass in 0..2 * shakes {
        for (i, state) in states.iter_mut().enumerate() {
            if !keep[i] || (i < first_new && pass % 2 == 1) {
                continue;
            }
            if !shake(state, views, context, 1) {
                restore(state, views);
                state.images.iter_mut().for_each(|image| *image = None);
                keep[i] = false;
            }
        }
    }
    keep
}

/// Ghosts (mean intensity below `ghost_fraction` of `typical_peak`, or an
/// image of that fraction of its camera's typical peak in fewer than
/// `min_cameras` cameras, [`State::bright_in`]) and duplicates restored to
/// the residual images and removed with those `keep` already drops; how
/// many were removed.
fn remove_ghosts(
    states: &mut Vec<State>,
    views: &mut [View],
    mut keep: Vec<bool>,
    mm_per_px: f64,
    ghost_fraction: f64,
    typical_peak: f64,
    min_cameras: usize,
) -> usize {
    let duplicate = duplicates(states, mm_per_px);
    let mut removed = 0;
    for (i, state) in states.iter().enumerate() {
        let intensity = state.intensity().0;
        let ghost = intensity < ghost_fraction * typical_peak
            || state.bright_in(views, ghost_fraction) < min_cameras;
        if keep[i] && (ghost || duplicate[i]) {
            restore(state, views);
            keep[i] = false;
        }
        if !keep[i] {
            removed += 1;
        }
    }
    let mut flags = keep.into_iter();
    states.retain(|_| flags.next().unwrap_or(false));
    removed
}

/// The request's inputs against each other: one image (and preprocessing,
/// if any) per camera, of the camera's sensor; the parameters in range; a
/// stated model per camera, of a plausible shape.
fn check_request(
    cameras: &[Camera],
    images: &[GreyImage],
    preprocessing: &[Preprocessing],
    parameters: &IprParameters,
) -> Result<(), IprError> {
    let n = cameras.len();
    if images.len() != n {
        return Err(IprError::ImageCount {
            images: images.len(),
            cameras: n,
        });
    }
    if !preprocessing.is_empty() && preprocessing.len() != n {
        return Err(IprError::PreprocessingCount {
            given: preprocessing.len(),
            cameras: n,
        });
    }
    let fraction = |v: f64, low: f64| v >= low && v < 1.0;
    if !fraction(parameters.peak_fraction, f64::MIN_POSITIVE)
        || !fraction(parameters.ghost_fraction, 0.0)
        || parameters.loops == 0
        || parameters.loops + parameters.reduced_loops > 50
        || parameters.shakes > 50
    {
        return Err(IprError::Parameter(format!(
            "the peak and ghost fractions must be within 0..1, the loops 1..50 and the shaking \
             passes at most 50; got {parameters:?}"
        )));
    }
    for (camera, (model, image)) in cameras.iter().zip(images).enumerate() {
        image
            .check_sensor(model.sensor())
            .map_err(|source| IprError::Sensor { camera, source })?;
        if let Some(p) = preprocessing.get(camera) {
            p.check(image)
                .map_err(|source| IprError::Preprocess { camera, source })?;
        }
    }
    if let Some(stated) = &parameters.otf {
        if stated.len() != n {
            return Err(IprError::OtfCount {
                given: stated.len(),
                cameras: n,
            });
        }
        if let Some(camera) = stated.iter().position(|o| {
            !((0.3..=4.0).contains(&o.sigma_x)
                && (0.3..=4.0).contains(&o.sigma_y)
                && o.rho.abs() < 0.95
                && o.peak > 0.0
                && o.peak.is_finite())
        }) {
            return Err(IprError::InvalidOtf { camera });
        }
    }
    Ok(())
}

/// Each camera's residual image (the recording less its background) and
/// its particle image model, stated or estimated from its brightest
/// isolated particle images.
fn residual_views(
    images: &[GreyImage],
    preprocessing: &[Preprocessing],
    parameters: &IprParameters,
) -> Result<Vec<View>, IprError> {
    let no_preprocessing = Preprocessing::default();
    let mut views = Vec::with_capacity(images.len());
    for (camera, image) in images.iter().enumerate() {
        let p = preprocessing.get(camera).unwrap_or(&no_preprocessing);
        let residual = image::background_free(image, p);
        let (width, height) = (image.width() as usize, image.height() as usize);
        let otf = match &parameters.otf {
            Some(stated) => stated[camera],
            None => {
                // The brightest particles set the scale: maxima above a
                // tenth of the 99.9th percentile.
                let mut sample: Vec<f32> = residual.iter().step_by(7).copied().collect();
                let k = ((sample.len() as f64 * 0.999) as usize).min(sample.len() - 1);
                let top = *sample.select_nth_unstable_by(k, f32::total_cmp).1;
                let mask = p.mask.clone();
                let usable = move |index: usize| mask.as_ref().map_or(true, |m| m.uses(index));
                otf::estimate(&residual, width, height, 0.1 * top, &usable)
                    .ok_or(IprError::NoParticleImages { camera })?
            }
        };
        views.push(View {
            width,
            height,
            residual,
            mask: p.mask.clone(),
            otf,
            precision: otf.precision(),
            radius: otf.radius(),
        });
    }
    Ok(views)
}

/// Object-space size of a pixel at the volume's centre (mm): the smallest
/// over the cameras of the inverse of the projection's largest singular
/// value; infinite if no camera sees the centre.
fn mm_per_px(cameras: &[Camera], volume: &Volume) -> f64 {
    let centre = volume_centre(volume);
    cameras
        .iter()
        .filter_map(|c| c.project_with_jacobian(&centre).ok())
        .map(|(_, j)| {
            // The largest singular value of J: pixels per mm.
            let jj = j * j.transpose();
            let (a, b, d) = (jj[(0, 0)], jj[(0, 1)], jj[(1, 1)]);
            let largest = 0.5 * (a + d) + (0.25 * (a - d).powi(2) + b * b).sqrt();
            1.0 / largest.sqrt()
        })
        .fold(f64::INFINITY, f64::min)
}

fn volume_centre(volume: &Volume) -> Point3<f64> {
    let clamp = |v: f64| if v.is_finite() { v } else { 0.0 };
    Point3::new(
        clamp(0.5 * (volume.min.x + volume.max.x)),
        clamp(0.5 * (volume.min.y + volume.max.y)),
        clamp(0.5 * (volume.min.z + volume.max.z)),
    )
}

fn residual_rms(views: &[View]) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for view in views {
        for (index, value) in view.residual.iter().enumerate() {
            if view.usable(index) {
                sum += f64::from(*value).powi(2);
                count += 1;
            }
        }
    }
    if count == 0 {
        0.0
    } else {
        (sum / count as f64).sqrt()
    }
}
