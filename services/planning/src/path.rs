//! Polyline smoothing and resampling.

use nalgebra::Vector2;

/// Centered moving average with the window shrunk symmetrically at the ends (so both
/// endpoints are kept exactly).
pub fn moving_average(points: &[[f64; 2]], window: usize) -> Vec<[f64; 2]> {
    let half = window.max(1) / 2;
    let n = points.len();
    (0..n)
        .map(|i| {
            let h = half.min(i).min(n - 1 - i);
            let slice = &points[i - h..=i + h];
            let k = slice.len() as f64;
            let sum = slice
                .iter()
                .fold([0.0, 0.0], |acc, p| [acc[0] + p[0], acc[1] + p[1]]);
            [sum[0] / k, sum[1] / k]
        })
        .collect()
}

/// `count` points evenly spaced by arc length along the polyline (both ends included).
pub fn resample(points: &[[f64; 2]], count: usize) -> Vec<[f64; 2]> {
    if points.is_empty() || count == 0 {
        return Vec::new();
    }
    let mut cumulative = vec![0.0];
    for w in points.windows(2) {
        let d = ((w[1][0] - w[0][0]).powi(2) + (w[1][1] - w[0][1]).powi(2)).sqrt();
        cumulative.push(cumulative[cumulative.len() - 1] + d);
    }
    let total = cumulative[cumulative.len() - 1];
    if count == 1 || total <= 0.0 {
        return vec![points[0]; count];
    }
    let mut out = Vec::with_capacity(count);
    let mut seg = 0;
    for i in 0..count {
        let s = total * i as f64 / (count - 1) as f64;
        while seg + 2 < cumulative.len() && cumulative[seg + 1] < s {
            seg += 1;
        }
        let len = cumulative[seg + 1] - cumulative[seg];
        let t = if len > 0.0 {
            ((s - cumulative[seg]) / len).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let (a, b) = (points[seg], points[seg + 1]);
        out.push([a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t]);
    }
    out
}

/// Polyline length.
pub fn path_length(points: &[Vector2<f64>]) -> f64 {
    points.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn moving_average_keeps_ends_and_smooths() {
        let pts: Vec<[f64; 2]> = (0..10).map(|i| [i as f64, (i % 2) as f64]).collect();
        let s = moving_average(&pts, 7);
        assert_eq!(s[0], pts[0]);
        assert_eq!(s[9], pts[9]);
        assert!((s[5][1] - 3.0 / 7.0).abs() < 1e-12 || (s[5][1] - 4.0 / 7.0).abs() < 1e-12);
    }

    #[test]
    fn resample_is_even() {
        let pts = vec![[0.0, 0.0], [3.0, 0.0], [3.0, 6.0]];
        let r = resample(&pts, 4);
        assert_eq!(r.len(), 4);
        assert_eq!(r[0], [0.0, 0.0]);
        assert!((r[1][0] - 3.0).abs() < 1e-12 && r[1][1].abs() < 1e-12);
        assert!((r[2][1] - 3.0).abs() < 1e-12);
        assert_eq!(r[3], [3.0, 6.0]);
    }
}
