//! The LiDAR keyframe decision: a scan becomes a keyframe when the robot has moved farther than
//! a distance, or turned more than an angle, from the last keyframe (the paper's distance
//! condition, with an angle added so turning on the spot also refreshes the map).

use crate::geom::{wrap_angle, Se2};

/// Keyframe thresholds.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct KeyframeConfig {
    /// Distance from the last keyframe, metres.
    pub distance: f64,
    /// Heading change from the last keyframe, radians.
    pub angle: f64,
}

impl Default for KeyframeConfig {
    fn default() -> Self {
        KeyframeConfig {
            distance: 0.2,
            angle: 0.35,
        }
    }
}

/// Remembers the last keyframe pose and decides on new ones.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeyframeSelector {
    config: KeyframeConfig,
    last: Option<Se2>,
}

impl KeyframeSelector {
    /// No keyframe yet: the first pose offered becomes one.
    pub const fn new(config: KeyframeConfig) -> Self {
        KeyframeSelector { config, last: None }
    }

    /// The last keyframe pose.
    pub fn last(&self) -> Option<Se2> {
        self.last
    }

    /// True when `pose` is far enough from the last keyframe (always for the first one).
    /// Does not record it; call [`KeyframeSelector::accept`] once the keyframe is made.
    pub fn is_keyframe(&self, pose: &Se2) -> bool {
        match &self.last {
            None => true,
            Some(k) => {
                let (dx, dy) = (pose.x - k.x, pose.y - k.y);
                libm::sqrt(dx * dx + dy * dy) > self.config.distance
                    || libm::fabs(wrap_angle(pose.theta - k.theta)) > self.config.angle
            }
        }
    }

    /// Records `pose` as the last keyframe.
    pub fn accept(&mut self, pose: Se2) {
        self.last = Some(pose);
    }

    /// Decides and records in one step; returns whether `pose` became a keyframe.
    pub fn offer(&mut self, pose: &Se2) -> bool {
        let new = self.is_keyframe(pose);
        if new {
            self.last = Some(*pose);
        }
        new
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_and_angle_thresholds() {
        let mut k = KeyframeSelector::new(KeyframeConfig {
            distance: 0.5,
            angle: 0.3,
        });
        assert!(k.offer(&Se2::IDENTITY));
        assert!(!k.offer(&Se2::new(0.3, 0.3, 0.2)));
        assert!(k.offer(&Se2::new(0.4, 0.4, 0.0)));
        assert!(!k.offer(&Se2::new(0.4, 0.4, -0.29)));
        assert!(k.offer(&Se2::new(0.4, 0.4, -0.31)));
        // Across the angle wrap.
        k.accept(Se2::new(0.0, 0.0, 3.1));
        assert!(!k.is_keyframe(&Se2::new(0.0, 0.0, -3.1)));
        assert_eq!(k.last(), Some(Se2::new(0.0, 0.0, 3.1)));
    }
}
