//! Reference generator: a point moving at constant speed along a polyline of waypoints, with
//! its desired velocity and acceleration.

use nalgebra::Vector2;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceSample {
    pub position_m: Vector2<f64>,
    pub velocity_mps: Vector2<f64>,
    /// Zero along straight segments; corners are taken as instantaneous turns.
    pub acceleration_mps2: Vector2<f64>,
    /// True once the reference has reached the last waypoint.
    pub finished: bool,
}

#[derive(Debug, Clone)]
pub struct Reference {
    waypoints: Vec<Vector2<f64>>,
    /// Arc length at each waypoint.
    cumulative_m: Vec<f64>,
    speed_mps: f64,
    start_time_s: f64,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReferenceError {
    #[error("a reference needs at least two waypoints, got {0}")]
    TooFewWaypoints(usize),
    #[error("waypoint {0} is not finite")]
    NonFinite(usize),
    #[error("speed must be positive and finite, got {0}")]
    BadSpeed(f64),
    #[error("all waypoints coincide: the path has zero length")]
    ZeroLength,
}

impl Reference {
    pub fn new(
        waypoints: &[[f64; 2]],
        speed_mps: f64,
        start_time_s: f64,
    ) -> Result<Self, ReferenceError> {
        if waypoints.len() < 2 {
            return Err(ReferenceError::TooFewWaypoints(waypoints.len()));
        }
        if !(speed_mps.is_finite() && speed_mps > 0.0) {
            return Err(ReferenceError::BadSpeed(speed_mps));
        }
        let mut points: Vec<Vector2<f64>> = Vec::with_capacity(waypoints.len());
        for (i, w) in waypoints.iter().enumerate() {
            if !(w[0].is_finite() && w[1].is_finite()) {
                return Err(ReferenceError::NonFinite(i));
            }
            let p = Vector2::new(w[0], w[1]);
            // Repeated points carry no direction: drop them.
            if points.last().is_none_or(|last| (p - last).norm() > 1e-12) {
                points.push(p);
            }
        }
        if points.len() < 2 {
            return Err(ReferenceError::ZeroLength);
        }
        let mut cumulative_m = vec![0.0];
        for pair in points.windows(2) {
            let last = *cumulative_m.last().unwrap_or(&0.0);
            cumulative_m.push(last + (pair[1] - pair[0]).norm());
        }
        Ok(Self {
            waypoints: points,
            cumulative_m,
            speed_mps,
            start_time_s,
        })
    }

    /// A reference that stays at `position_m` (a hold): a 1 nm path, finished at once.
    pub fn hold(position_m: Vector2<f64>, speed_mps: f64) -> Self {
        const HOLD_PATH_M: f64 = 1e-9;
        Self {
            waypoints: vec![position_m, position_m + Vector2::new(HOLD_PATH_M, 0.0)],
            cumulative_m: vec![0.0, HOLD_PATH_M],
            speed_mps,
            start_time_s: 0.0,
        }
    }

    /// The same path started `by_s` later (resuming after a pause of that long).
    pub fn delayed(&self, by_s: f64) -> Self {
        Self {
            start_time_s: self.start_time_s + by_s,
            ..self.clone()
        }
    }

    pub fn speed_mps(&self) -> f64 {
        self.speed_mps
    }

    pub fn length_m(&self) -> f64 {
        *self.cumulative_m.last().unwrap_or(&0.0)
    }

    pub fn duration_s(&self) -> f64 {
        self.length_m() / self.speed_mps
    }

    pub fn end_time_s(&self) -> f64 {
        self.start_time_s + self.duration_s()
    }

    pub fn waypoints(&self) -> &[Vector2<f64>] {
        &self.waypoints
    }

    /// The reference at run time `t`: holds the first waypoint before the start time and the
    /// last one after the end.
    pub fn sample(&self, t: f64) -> ReferenceSample {
        let s = ((t - self.start_time_s) * self.speed_mps).clamp(0.0, self.length_m());
        let moving = t >= self.start_time_s && s < self.length_m();
        let segment = match self.cumulative_m.iter().position(|&c| c > s) {
            Some(i) => i.saturating_sub(1).min(self.waypoints.len() - 2),
            None => self.waypoints.len() - 2,
        };
        let a = self.waypoints[segment];
        let b = self.waypoints[segment + 1];
        let seg_len = self.cumulative_m[segment + 1] - self.cumulative_m[segment];
        let direction = (b - a) / seg_len;
        let along = (s - self.cumulative_m[segment]).clamp(0.0, seg_len);
        ReferenceSample {
            position_m: a + direction * along,
            velocity_mps: if moving {
                direction * self.speed_mps
            } else {
                Vector2::zeros()
            },
            acceleration_mps2: Vector2::zeros(),
            finished: s >= self.length_m(),
        }
    }

    /// Distance from `p` to the polyline (for cross-track error).
    pub fn distance_to_path(&self, p: &Vector2<f64>) -> f64 {
        self.waypoints
            .windows(2)
            .map(|w| {
                let d = w[1] - w[0];
                let t = ((p - w[0]).dot(&d) / d.norm_squared()).clamp(0.0, 1.0);
                (p - (w[0] + d * t)).norm()
            })
            .fold(f64::INFINITY, f64::min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moves_at_constant_speed_through_corners() {
        let r = Reference::new(&[[0.0, 0.0], [0.01, 0.0], [0.01, 0.01]], 0.001, 1.0).unwrap();
        assert!((r.length_m() - 0.02).abs() < 1e-12);
        assert!((r.end_time_s() - 21.0).abs() < 1e-9);
        let before = r.sample(0.5);
        assert_eq!(before.position_m, Vector2::zeros());
        assert_eq!(before.velocity_mps, Vector2::zeros());
        let mid = r.sample(6.0);
        assert!((mid.position_m - Vector2::new(0.005, 0.0)).norm() < 1e-12);
        assert!((mid.velocity_mps - Vector2::new(0.001, 0.0)).norm() < 1e-12);
        let second = r.sample(16.0);
        assert!((second.position_m - Vector2::new(0.01, 0.005)).norm() < 1e-12);
        let end = r.sample(100.0);
        assert!(end.finished);
        assert!((end.position_m - Vector2::new(0.01, 0.01)).norm() < 1e-12);
        assert_eq!(end.velocity_mps, Vector2::zeros());
    }

    #[test]
    fn rejects_degenerate_input() {
        assert!(Reference::new(&[[0.0, 0.0]], 1.0, 0.0).is_err());
        assert!(Reference::new(&[[0.0, 0.0], [0.0, 0.0]], 1.0, 0.0).is_err());
        assert!(Reference::new(&[[0.0, 0.0], [f64::NAN, 0.0]], 1.0, 0.0).is_err());
        assert!(Reference::new(&[[0.0, 0.0], [1.0, 0.0]], 0.0, 0.0).is_err());
    }

    #[test]
    fn distance_to_path() {
        let r = Reference::new(&[[0.0, 0.0], [0.01, 0.0]], 0.001, 0.0).unwrap();
        assert!((r.distance_to_path(&Vector2::new(0.005, 0.002)) - 0.002).abs() < 1e-12);
        assert!((r.distance_to_path(&Vector2::new(-0.003, 0.004)) - 0.005).abs() < 1e-12);
    }
}
