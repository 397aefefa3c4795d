//! The 16 parameters of a camera (Eq. 1-5: exterior orientation, interior
//! orientation, distortion and affine terms), named as OpenPTV names them,
//! and sets of them: which are free, fixed by the user, or held.

use serde::{Deserialize, Serialize};

/// One of the 16 camera parameters, named as OpenPTV names them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Parameter {
    /// Projective centre X0 (mm).
    X0,
    /// Projective centre Y0 (mm).
    Y0,
    /// Projective centre Z0 (mm).
    Z0,
    /// Rotation about x (rad).
    Omega,
    /// Rotation about y (rad).
    Phi,
    /// Rotation about z (rad).
    Kappa,
    /// Principal point x (mm).
    Xh,
    /// Principal point y (mm).
    Yh,
    /// Principal distance (mm).
    C,
    /// Radial distortion r² term.
    K1,
    /// Radial distortion r⁴ term.
    K2,
    /// Radial distortion r⁶ term.
    K3,
    /// Decentering distortion.
    P1,
    /// Decentering distortion.
    P2,
    /// Scale of x.
    Scx,
    /// Shear (rad).
    She,
}

impl Parameter {
    /// All 16, in the order of OpenPTV's files.
    pub const ALL: [Parameter; 16] = [
        Parameter::X0,
        Parameter::Y0,
        Parameter::Z0,
        Parameter::Omega,
        Parameter::Phi,
        Parameter::Kappa,
        Parameter::Xh,
        Parameter::Yh,
        Parameter::C,
        Parameter::K1,
        Parameter::K2,
        Parameter::K3,
        Parameter::P1,
        Parameter::P2,
        Parameter::Scx,
        Parameter::She,
    ];

    /// OpenPTV's name: `x0`, `omega`, `xh`, `c`, `k1`, `scx`, `she`, ...
    pub fn name(self) -> &'static str {
        [
            "x0", "y0", "z0", "omega", "phi", "kappa", "xh", "yh", "c", "k1", "k2", "k3", "p1",
            "p2", "scx", "she",
        ][self.index()]
    }

    /// The parameter of a name (case-insensitive).
    pub fn from_name(name: &str) -> Option<Parameter> {
        let name = name.trim().to_ascii_lowercase();
        Parameter::ALL.into_iter().find(|p| p.name() == name)
    }

    /// Position in [`Parameter::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }

    /// Exterior orientation is always determinable from enough points and is
    /// never held; the others may be.
    pub(super) fn holdable(self) -> bool {
        !ParameterSet::exterior().contains(self)
    }

    /// Which of two correlated parameters to hold: the lower number goes
    /// first (higher-order and smaller effects before lower-order ones).
    pub(super) fn hold_priority(self) -> u8 {
        match self {
            Parameter::K3 => 0,
            Parameter::K2 => 1,
            Parameter::She => 2,
            Parameter::Scx => 3,
            Parameter::P2 => 4,
            Parameter::P1 => 5,
            Parameter::K1 => 6,
            Parameter::Yh => 7,
            Parameter::Xh => 8,
            Parameter::C => 9,
            _ => 10,
        }
    }

    /// The order in which parameters the observations cannot determine
    /// (their standard deviation against their plausible range) are held
    /// at the setup's values, lowest first: the distortion (higher radial
    /// terms, decentering, then k1), then the affine terms and the
    /// principal point, then the principal distance, the one that sets the
    /// rig's scale with the position.
    pub(super) fn range_order(self) -> u8 {
        match self {
            Parameter::K3 => 0,
            Parameter::K2 => 1,
            Parameter::P2 => 2,
            Parameter::P1 => 3,
            Parameter::K1 => 4,
            Parameter::She => 5,
            Parameter::Scx => 6,
            Parameter::Yh => 7,
            Parameter::Xh => 8,
            Parameter::C => 9,
            _ => 10,
        }
    }

    /// How far a real camera's value plausibly lies from a setup's nominal
    /// one (half-width of the range, the parameter's unit); `None` for the
    /// exterior orientation, which has no such range. With `r` the sensor's
    /// half-diagonal (mm), the image effect at the sensor's corner:
    ///
    /// * c: 10% of the setup's, the most a lens focused at a finite
    ///   distance `d` moves its principal distance from the focal length
    ///   `f` (`c = f d / (d - f)`, 11% at `d = 10 f`, the closest PTV
    ///   distances; refraction by a flat window is in the media model);
    /// * xh, yh: r / 10 (the sensor's centre within a tenth of its
    ///   half-diagonal: 0.98 mm, 82 px, on test_cavity's 1280 x 1024 x
    ///   12 µm sensors; real offsets are tens of pixels);
    /// * k1, k2, k3: a radial displacement of 5% of r at the corner (a
    ///   strong wide-angle lens's distortion): `0.05 / r^2`, `/ r^4`, `/ r^6`;
    /// * p1, p2: a decentering displacement (up to `3 p r^2`) of 1% of r
    ///   at the corner: `0.01 / (3 r)`;
    /// * scx, she: 1% (the pixel pitch's aspect and the sensor's shear are
    ///   manufactured far closer than that).
    pub fn plausible_range(
        self,
        setup: &crate::photogrammetry::camera::CameraParameters,
    ) -> Option<f64> {
        let s = &setup.sensor;
        let r =
            0.5 * (f64::from(s.width) * s.pixel_size_x).hypot(f64::from(s.height) * s.pixel_size_y);
        let r = r.max(1e-3);
        match self {
            Parameter::C => Some(0.1 * setup.interior.c.abs()),
            Parameter::Xh | Parameter::Yh => Some(0.1 * r),
            Parameter::K1 => Some(0.05 / r.powi(2)),
            Parameter::K2 => Some(0.05 / r.powi(4)),
            Parameter::K3 => Some(0.05 / r.powi(6)),
            Parameter::P1 | Parameter::P2 => Some(0.01 / (3.0 * r)),
            Parameter::Scx | Parameter::She => Some(0.01),
            _ => None,
        }
    }

    /// Distortion and affine terms are held at the setup's value (normally
    /// none); principal distance and point at their current estimate.
    pub(super) fn held_at_setup(self) -> bool {
        ParameterSet::distortion().contains(self)
    }
}

impl std::fmt::Display for Parameter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A set of camera parameters, one bit per parameter in
/// [`Parameter::ALL`]'s order: iteration gives its members in the order of
/// the parameter vector, the Jacobian's columns and OpenPTV's files.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct ParameterSet(u16);

impl ParameterSet {
    /// No parameter.
    pub const fn empty() -> ParameterSet {
        ParameterSet(0)
    }

    /// All 16.
    pub const fn all() -> ParameterSet {
        ParameterSet(u16::MAX)
    }

    /// The given parameters.
    pub const fn of(parameters: &[Parameter]) -> ParameterSet {
        let mut bits = 0;
        let mut i = 0;
        while i < parameters.len() {
            bits |= 1 << parameters[i] as u16;
            i += 1;
        }
        ParameterSet(bits)
    }

    /// The projective centre: X0, Y0, Z0.
    pub const fn position() -> ParameterSet {
        ParameterSet::of(&[Parameter::X0, Parameter::Y0, Parameter::Z0])
    }

    /// The rotation of Eq. 1: omega, phi, kappa.
    pub const fn rotation() -> ParameterSet {
        ParameterSet::of(&[Parameter::Omega, Parameter::Phi, Parameter::Kappa])
    }

    /// The exterior orientation: position and rotation.
    pub const fn exterior() -> ParameterSet {
        ParameterSet(ParameterSet::position().0 | ParameterSet::rotation().0)
    }

    /// The interior orientation: principal point and distance.
    pub const fn interior() -> ParameterSet {
        ParameterSet::of(&[Parameter::Xh, Parameter::Yh, Parameter::C])
    }

    /// The distortion and affine terms (Eq. 3, 5; OpenPTV's `.addpar`):
    /// k1, k2, k3, p1, p2, scx, she.
    pub const fn distortion() -> ParameterSet {
        ParameterSet(!(ParameterSet::exterior().0 | ParameterSet::interior().0))
    }

    /// Whether `parameter` is a member.
    pub const fn contains(self, parameter: Parameter) -> bool {
        self.0 & (1 << parameter as u16) != 0
    }

    /// Adds `parameter`.
    pub fn insert(&mut self, parameter: Parameter) {
        self.0 |= 1 << parameter as u16;
    }

    /// Removes `parameter`.
    pub fn remove(&mut self, parameter: Parameter) {
        self.0 &= !(1 << parameter as u16);
    }

    /// The parameters not in this set.
    pub const fn complement(self) -> ParameterSet {
        ParameterSet(!self.0)
    }

    /// How many parameters are members.
    pub const fn len(self) -> usize {
        self.0.count_ones() as usize
    }

    /// Whether there are none.
    pub const fn is_empty(self) -> bool {
        self.0 == 0
    }

    /// The members, in [`Parameter::ALL`]'s order.
    pub fn iter(self) -> impl Iterator<Item = Parameter> {
        Parameter::ALL
            .into_iter()
            .filter(move |&p| self.contains(p))
    }
}

impl std::ops::BitOr for ParameterSet {
    type Output = ParameterSet;

    /// The union.
    fn bitor(self, other: ParameterSet) -> ParameterSet {
        ParameterSet(self.0 | other.0)
    }
}

impl std::ops::Sub for ParameterSet {
    type Output = ParameterSet;

    /// The members of `self` that are not in `other`.
    fn sub(self, other: ParameterSet) -> ParameterSet {
        ParameterSet(self.0 & !other.0)
    }
}

impl FromIterator<Parameter> for ParameterSet {
    fn from_iter<I: IntoIterator<Item = Parameter>>(parameters: I) -> ParameterSet {
        let mut set = ParameterSet::empty();
        for p in parameters {
            set.insert(p);
        }
        set
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parameter_names_round_trip() {
        for p in Parameter::ALL {
            assert_eq!(Parameter::from_name(p.name()), Some(p));
            assert_eq!(Parameter::ALL[p.index()], p);
            assert_eq!(
                serde_json::to_string(&p).unwrap(),
                format!("\"{}\"", p.name())
            );
        }
        assert_eq!(Parameter::from_name(" K1 "), Some(Parameter::K1));
        assert_eq!(Parameter::from_name("k4"), None);
    }

    #[test]
    fn the_named_sets_split_the_parameters_as_the_files_do() {
        let names = |set: ParameterSet| set.iter().map(Parameter::name).collect::<Vec<_>>();
        assert_eq!(
            names(ParameterSet::exterior()),
            ["x0", "y0", "z0", "omega", "phi", "kappa"]
        );
        assert_eq!(names(ParameterSet::interior()), ["xh", "yh", "c"]);
        assert_eq!(
            names(ParameterSet::distortion()),
            ["k1", "k2", "k3", "p1", "p2", "scx", "she"]
        );
        assert_eq!(
            ParameterSet::exterior() | ParameterSet::interior() | ParameterSet::distortion(),
            ParameterSet::all()
        );
        assert_eq!(
            ParameterSet::position() | ParameterSet::rotation(),
            ParameterSet::exterior()
        );
        assert_eq!(ParameterSet::all().len(), 16);
        assert_eq!(ParameterSet::distortion().complement().len(), 9);
    }

    #[test]
    fn members_come_in_parameter_order() {
        let mut set: ParameterSet = [Parameter::She, Parameter::X0, Parameter::C]
            .into_iter()
            .collect();
        assert_eq!(
            set.iter().collect::<Vec<_>>(),
            [Parameter::X0, Parameter::C, Parameter::She]
        );
        set.remove(Parameter::C);
        set.insert(Parameter::K1);
        assert!(set.contains(Parameter::K1) && !set.contains(Parameter::C));
        assert_eq!(
            set - ParameterSet::exterior(),
            ParameterSet::of(&[Parameter::K1, Parameter::She])
        );
        assert!(ParameterSet::empty().is_empty() && ParameterSet::empty().iter().next().is_none());
    }
}
