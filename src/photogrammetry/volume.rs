//! The observation volume: the box in object space where particles are sought.

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

/// An axis-aligned box in object space (mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Volume {
    /// Smallest corner.
    pub min: Point3<f64>,
    /// Largest corner.
    pub max: Point3<f64>,
}

impl Volume {
    /// The centre of the box.
    pub fn centre(&self) -> Point3<f64> {
        nalgebra::center(&self.min, &self.max)
    }

    /// Half the length of the box's diagonal.
    pub fn radius(&self) -> f64 {
        (self.max - self.min).norm() / 2.0
    }

    /// Whether `point` lies inside.
    pub fn contains(&self, point: &Point3<f64>) -> bool {
        (0..3).all(|i| point[i] >= self.min[i] && point[i] <= self.max[i])
    }

    /// The eight corners.
    pub fn corners(&self) -> [Point3<f64>; 8] {
        std::array::from_fn(|i| {
            Point3::new(
                if i & 1 == 0 { self.min.x } else { self.max.x },
                if i & 2 == 0 { self.min.y } else { self.max.y },
                if i & 4 == 0 { self.min.z } else { self.max.z },
            )
        })
    }
}
