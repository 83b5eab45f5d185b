//! The exact Euclidean distance transform of a mask (Felzenszwalb & Huttenlocher, "Distance
//! Transforms of Sampled Functions", Theory of Computing 8, 2012): a squared distance along
//! each column, then the lower envelope of parabolas along each row. It is the algorithm
//! behind OpenCV's `distanceTransform(DIST_L2, DIST_MASK_PRECISE)`, and gives the same values
//! (the `planner` tool's tests compare the two on random masks), without linking OpenCV into
//! the services that plan.

use crate::Mask;

/// A squared distance that no wall pixel reaches (a column or row without one).
const UNREACHED: i64 = i64::MAX;

/// Per-pixel distance to the nearest wall (zero) pixel, px; 0 on the walls. Pixels outside
/// the image are not walls. A mask without any wall pixel gives `f32::INFINITY` everywhere.
pub fn distance_transform(mask: &Mask) -> Vec<f32> {
    let (w, h) = (mask.width as usize, mask.height as usize);
    let columns = column_squared_distances(mask);
    let mut out = vec![0.0f32; w * h];
    let mut row = vec![0i64; w];
    let mut envelope = Envelope::with_capacity(w);
    for r in 0..h {
        row.copy_from_slice(&columns[r * w..(r + 1) * w]);
        envelope.lower(&row);
        for (c, d) in out[r * w..(r + 1) * w].iter_mut().enumerate() {
            *d = match envelope.at(c) {
                UNREACHED => f32::INFINITY,
                // Exact in f32 below 2^24 px², so the root is the correctly rounded one.
                squared => (squared as f32).sqrt(),
            };
        }
    }
    out
}

/// Squared distance to the nearest wall pixel in the same column (two scans).
fn column_squared_distances(mask: &Mask) -> Vec<i64> {
    let (w, h) = (mask.width as usize, mask.height as usize);
    let mut out = vec![UNREACHED; w * h];
    let mut along = vec![None::<i64>; h];
    for c in 0..w {
        let mut last_wall = None;
        for (r, slot) in along.iter_mut().enumerate() {
            if mask.data[r * w + c] == 0 {
                last_wall = Some(r as i64);
            }
            *slot = last_wall.map(|wall| r as i64 - wall);
        }
        let mut next_wall = None;
        for r in (0..h).rev() {
            if mask.data[r * w + c] == 0 {
                next_wall = Some(r as i64);
            }
            let below = next_wall.map(|wall| wall - r as i64);
            let nearest = match (along[r], below) {
                (Some(a), Some(b)) => Some(a.min(b)),
                (a, b) => a.or(b),
            };
            out[r * w + c] = nearest.map_or(UNREACHED, |d| d * d);
        }
    }
    out
}

/// The lower envelope of the parabolas `(q − v)² + f(v)` over a row's sampled `f`.
struct Envelope {
    /// Apexes of the parabolas on the envelope, left to right.
    apex: Vec<usize>,
    /// `bounds[k]..bounds[k + 1]` is where parabola `apex[k]` is lowest.
    bounds: Vec<f64>,
    values: Vec<i64>,
}

impl Envelope {
    fn with_capacity(n: usize) -> Self {
        Self {
            apex: Vec::with_capacity(n),
            bounds: Vec::with_capacity(n + 1),
            values: Vec::with_capacity(n),
        }
    }

    fn lower(&mut self, f: &[i64]) {
        self.apex.clear();
        self.bounds.clear();
        self.values.clear();
        self.values.extend_from_slice(f);
        self.bounds.push(f64::NEG_INFINITY);
        for q in (0..f.len()).filter(|&q| f[q] != UNREACHED) {
            while let Some(&v) = self.apex.last() {
                let s = self.intersection(v, q);
                if s <= self.bounds[self.bounds.len() - 1] {
                    self.apex.pop();
                    self.bounds.pop();
                } else {
                    self.bounds.push(s);
                    break;
                }
            }
            if self.apex.is_empty() {
                self.bounds.clear();
                self.bounds.push(f64::NEG_INFINITY);
            }
            self.apex.push(q);
        }
        self.bounds.push(f64::INFINITY);
    }

    /// Where the parabolas of apexes `v < q` cross.
    fn intersection(&self, v: usize, q: usize) -> f64 {
        let (fv, fq) = (self.values[v] as f64, self.values[q] as f64);
        let (v, q) = (v as f64, q as f64);
        ((fq + q * q) - (fv + v * v)) / (2.0 * (q - v))
    }

    /// The envelope's value at `q`; `UNREACHED` when the row has no parabola.
    fn at(&self, q: usize) -> i64 {
        if self.apex.is_empty() {
            return UNREACHED;
        }
        let x = q as f64;
        // bounds[0] = -inf, bounds[k] for k >= 1 the left bound of apex[k].
        let k = self.bounds[1..=self.apex.len()].partition_point(|&b| b < x);
        let k = k.min(self.apex.len() - 1);
        let v = self.apex[k];
        let dq = q as i64 - v as i64;
        dq * dq + self.values[v]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute_force(mask: &Mask) -> Vec<f32> {
        let (w, h) = (mask.width as i64, mask.height as i64);
        let walls: Vec<(i64, i64)> = (0..w * h)
            .filter(|&i| mask.data[i as usize] == 0)
            .map(|i| (i % w, i / w))
            .collect();
        (0..w * h)
            .map(|i| {
                let (c, r) = (i % w, i / w);
                walls
                    .iter()
                    .map(|&(wc, wr)| (c - wc).pow(2) + (r - wr).pow(2))
                    .min()
                    .map_or(f32::INFINITY, |d| (d as f32).sqrt())
            })
            .collect()
    }

    #[test]
    fn equals_brute_force_on_random_masks() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for case in 0..60 {
            let (w, h) = (rng.random_range(1..40u32), rng.random_range(1..40u32));
            let walls = rng.random_range(0.0..0.5);
            let data = (0..w * h)
                .map(|_| if rng.random_bool(walls) { 0 } else { 255 })
                .collect();
            let mask = Mask::new(w, h, data).unwrap();
            assert_eq!(
                distance_transform(&mask),
                brute_force(&mask),
                "case {case}: {w}x{h}"
            );
        }
    }

    #[test]
    fn a_mask_without_walls_is_unreached() {
        let mask = Mask::new(3, 2, vec![1; 6]).unwrap();
        assert!(distance_transform(&mask).iter().all(|d| d.is_infinite()));
    }
}
