//! Image shifts a real camera brings and the twin's renderer does not, at graded severity, for
//! the robustness suite of `vision-eval --robustness`: lighting (gain, offset, gamma), colour
//! cast, background texture, air bubbles, specular glare, shadow, motion blur, sensor noise, JPEG
//! artefacts, scale ±10 % and partial occlusion. Each is applied to a split's ROI crops (RGB,
//! [`INPUT_PX`]²) with its ground truth kept consistent: scale moves the keypoints and the mask,
//! occlusion removes the hidden pixels from the truth mask, the rest leave the truth alone.
//! Deterministic per (family, severity, crop, seed).

use millinav_roi::dataset::{Label, Split};
use millinav_roi::roi::INPUT_PX;
use opencv::core::{self, Mat, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

/// A family of image shifts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    Lighting,
    ColourCast,
    Background,
    Bubbles,
    Glare,
    Shadow,
    Blur,
    Noise,
    Jpeg,
    Scale,
    Occlusion,
}

impl Family {
    pub const ALL: [Family; 11] = [
        Family::Lighting,
        Family::ColourCast,
        Family::Background,
        Family::Bubbles,
        Family::Glare,
        Family::Shadow,
        Family::Blur,
        Family::Noise,
        Family::Jpeg,
        Family::Scale,
        Family::Occlusion,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Family::Lighting => "lighting",
            Family::ColourCast => "colour cast",
            Family::Background => "background texture",
            Family::Bubbles => "bubbles",
            Family::Glare => "glare",
            Family::Shadow => "shadow",
            Family::Blur => "motion blur",
            Family::Noise => "noise",
            Family::Jpeg => "JPEG",
            Family::Scale => "scale",
            Family::Occlusion => "occlusion",
        }
    }

    /// What severity `s` (1..=3) means, for the table.
    pub fn describe(self, s: u32) -> String {
        let s = f64::from(s);
        match self {
            Family::Lighting => format!(
                "gain ×(1±{:.2}), offset ±{:.0}, gamma 1±{:.2}",
                0.15 * s,
                10.0 * s,
                0.15 * s
            ),
            Family::ColourCast => format!("channel gains 1±{:.2}", 0.1 * s),
            Family::Background => format!("texture ±{:.0} grey levels", 10.0 * s),
            Family::Bubbles => format!("{:.0} bubbles", 2.0 * s),
            Family::Glare => format!("spot +{:.0}, r {:.0} px", 70.0 * s, 5.0 + 3.0 * s),
            Family::Shadow => format!("×{:.2} over a half-plane", 1.0 - 0.2 * s),
            Family::Blur => format!("{:.0} px streak", 2.0 * s + 1.0),
            Family::Noise => format!("σ {:.0}", 5.0 * s),
            Family::Jpeg => format!("quality {}", jpeg_quality(s as u32)),
            Family::Scale => format!("×(1±{:.3})", 0.1 * s / 3.0),
            Family::Occlusion => format!("{:.0} % of the length hidden", 10.0 * s),
        }
    }
}

fn jpeg_quality(s: u32) -> i32 {
    match s {
        1 => 60,
        2 => 35,
        _ => 15,
    }
}

/// SplitMix64: a small deterministic generator (no dependency for a test harness).
struct Rng(u64);

impl Rng {
    fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    fn sign(&mut self) -> f64 {
        if self.uniform() < 0.5 {
            -1.0
        } else {
            1.0
        }
    }

    fn normal(&mut self) -> f64 {
        let u1 = self.uniform().max(1e-300);
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
    }
}

fn clamp_u8(v: f64) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

const N: usize = INPUT_PX;

/// `f` applied to every pixel (col, row, rgb).
fn map_pixels(image: &mut [u8], mut f: impl FnMut(usize, usize, &mut [u8])) {
    for (i, px) in image.chunks_mut(3).enumerate() {
        f(i % N, i / N, px);
    }
}

fn to_mat(image: &[u8]) -> opencv::Result<Mat> {
    Mat::from_slice(image)?.reshape(3, N as i32)?.try_clone()
}

fn from_mat(mat: &Mat) -> opencv::Result<Vec<u8>> {
    Ok(mat.data_bytes()?.to_vec())
}

/// One crop shifted by `family` at severity `s`; image, truth mask and label updated together.
pub fn perturb(
    family: Family,
    s: u32,
    image: &[u8],
    mask: &[u8],
    label: &Label,
    seed: u64,
) -> opencv::Result<(Vec<u8>, Vec<u8>, Label)> {
    let mut rng = Rng::new(seed);
    let mut shifted = Shifted {
        img: image.to_vec(),
        truth: mask.to_vec(),
        label: *label,
    };
    let shift = match family {
        Family::Lighting => lighting,
        Family::ColourCast => colour_cast,
        Family::Background => background,
        Family::Bubbles => bubbles,
        Family::Glare => glare,
        Family::Shadow => shadow,
        Family::Blur => blur,
        Family::Noise => noise,
        Family::Jpeg => jpeg,
        Family::Scale => scale,
        Family::Occlusion => occlusion,
    };
    shift(&mut shifted, &mut rng, s)?;
    Ok((shifted.img, shifted.truth, shifted.label))
}

/// A crop being shifted: its image, its truth mask and its label, changed together.
struct Shifted {
    img: Vec<u8>,
    truth: Vec<u8>,
    label: Label,
}

fn lighting(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let gain = 1.0 + rng.sign() * 0.15 * sf;
    let offset = rng.sign() * 10.0 * sf;
    let gamma = 1.0 + rng.sign() * 0.15 * sf;
    map_pixels(&mut x.img, |_, _, px| {
        for v in px {
            let lin = (gain * f64::from(*v) + offset).clamp(0.0, 255.0) / 255.0;
            *v = clamp_u8(255.0 * lin.powf(gamma));
        }
    });
    Ok(())
}

fn colour_cast(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let k: [f64; 3] = std::array::from_fn(|_| 1.0 + rng.range(-1.0, 1.0) * 0.1 * sf);
    map_pixels(&mut x.img, |_, _, px| {
        for (v, k) in px.iter_mut().zip(k) {
            *v = clamp_u8(f64::from(*v) * k);
        }
    });
    Ok(())
}

fn background(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    // A few random plane waves: the phantom's printed or scratched floor.
    let waves: Vec<(f64, f64, f64, f64)> = (0..4)
        .map(|_| {
            let angle = rng.range(0.0, std::f64::consts::TAU);
            let k = rng.range(0.08, 0.5);
            (
                k * angle.cos(),
                k * angle.sin(),
                rng.range(0.0, 6.3),
                rng.range(0.5, 1.0),
            )
        })
        .collect();
    let amp = 10.0 * sf / 2.0;
    map_pixels(&mut x.img, |c, r, px| {
        if x.truth[r * N + c] > 0 {
            return;
        }
        let t: f64 = waves
            .iter()
            .map(|(kx, ky, ph, a)| a * (kx * c as f64 + ky * r as f64 + ph).sin())
            .sum();
        for v in px {
            *v = clamp_u8(f64::from(*v) + amp * t);
        }
    });
    Ok(())
}

fn bubbles(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    for _ in 0..2 * s {
        let (bc, br, radius) = (
            rng.range(0.0, N as f64),
            rng.range(0.0, N as f64),
            rng.range(2.5, 7.0),
        );
        map_pixels(&mut x.img, |c, r, px| {
            let d = ((c as f64 - bc).powi(2) + (r as f64 - br).powi(2)).sqrt() / radius;
            // A bright thin rim, a faintly lighter inside.
            let lift = if (0.8..1.05).contains(&d) {
                90.0
            } else if d < 0.8 {
                25.0
            } else {
                0.0
            };
            for v in px {
                *v = clamp_u8(f64::from(*v) + lift);
            }
        });
    }
    Ok(())
}

fn glare(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let (gc, gr) = (
        rng.range(0.2, 0.8) * N as f64,
        rng.range(0.2, 0.8) * N as f64,
    );
    let radius = 5.0 + 3.0 * sf;
    let peak = 70.0 * sf;
    map_pixels(&mut x.img, |c, r, px| {
        let d2 = ((c as f64 - gc).powi(2) + (r as f64 - gr).powi(2)) / (radius * radius);
        let lift = peak * (-d2).exp();
        for v in px {
            *v = clamp_u8(f64::from(*v) + lift);
        }
    });
    Ok(())
}

fn shadow(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let angle = rng.range(0.0, std::f64::consts::TAU);
    let (nx, ny) = (angle.cos(), angle.sin());
    let offset = rng.range(-0.25, 0.25) * N as f64;
    let dark = 1.0 - 0.2 * sf;
    let h = N as f64 / 2.0;
    map_pixels(&mut x.img, |c, r, px| {
        let d = (c as f64 - h) * nx + (r as f64 - h) * ny - offset;
        // Soft 4 px penumbra.
        let w = 1.0 / (1.0 + (-d / 2.0).exp());
        let k = 1.0 - (1.0 - dark) * w;
        for v in px {
            *v = clamp_u8(f64::from(*v) * k);
        }
    });
    Ok(())
}

fn blur(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let len = 2 * s as i32 + 1;
    let angle = rng.range(0.0, std::f64::consts::PI);
    let mut kernel = Mat::zeros(len, len, core::CV_32F)?.to_mat()?;
    let c = f64::from(len - 1) / 2.0;
    for k in 0..len {
        let t = f64::from(k) - c;
        let (x, y) = (
            (c + t * angle.cos()).round() as i32,
            (c + t * angle.sin()).round() as i32,
        );
        *kernel.at_2d_mut::<f32>(y, x)? = 1.0;
    }
    let total = core::sum_elems(&kernel)?[0];
    let mut normalized = Mat::default();
    kernel.convert_to(&mut normalized, core::CV_32F, 1.0 / total, 0.0)?;
    let src = to_mat(&x.img)?;
    let mut dst = Mat::default();
    imgproc::filter_2d(
        &src,
        &mut dst,
        -1,
        &normalized,
        core::Point::new(-1, -1),
        0.0,
        core::BORDER_REFLECT,
    )?;
    x.img = from_mat(&dst)?;
    Ok(())
}

fn noise(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let sigma = 5.0 * sf;
    map_pixels(&mut x.img, |_, _, px| {
        for v in px {
            *v = clamp_u8(f64::from(*v) + sigma * rng.normal());
        }
    });
    Ok(())
}

fn jpeg(x: &mut Shifted, _rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let src = to_mat(&x.img)?;
    let mut buf = Vector::<u8>::new();
    let params = Vector::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, jpeg_quality(s)]);
    imgcodecs::imencode(".jpg", &src, &mut buf, &params)?;
    let decoded = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_COLOR)?;
    x.img = from_mat(&decoded)?;
    Ok(())
}

fn scale(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    let k = 1.0 + rng.sign() * 0.1 * sf / 3.0;
    let h = (N as f64 - 1.0) / 2.0;
    // p' = k (p − centre) + centre.
    let m = Mat::from_slice_2d(&[[k, 0.0, h * (1.0 - k)], [0.0, k, h * (1.0 - k)]])?;
    let size = core::Size::new(N as i32, N as i32);
    let mut dst = Mat::default();
    imgproc::warp_affine(
        &to_mat(&x.img)?,
        &mut dst,
        &m,
        size,
        imgproc::INTER_LINEAR,
        core::BORDER_REFLECT,
        core::Scalar::default(),
    )?;
    x.img = from_mat(&dst)?;
    // The x.truth is resampled linearly and cut at half, so its edge moves with the image
    // to a fraction of a pixel (nearest-neighbour moved it by up to half a pixel).
    let levels: Vec<u8> = x
        .truth
        .iter()
        .map(|&t| if t > 0 { 255 } else { 0 })
        .collect();
    let mask_mat = Mat::from_slice(&levels)?
        .reshape(1, N as i32)?
        .try_clone()?;
    let mut mask_dst = Mat::default();
    imgproc::warp_affine(
        &mask_mat,
        &mut mask_dst,
        &m,
        size,
        imgproc::INTER_LINEAR,
        core::BORDER_CONSTANT,
        core::Scalar::default(),
    )?;
    x.truth = from_mat(&mask_dst)?
        .into_iter()
        .map(|v| u8::from(v >= 128))
        .collect();
    let scale = |p: (f64, f64)| (k * (p.0 - h) + h, k * (p.1 - h) + h);
    x.label.tip = scale(x.label.tip);
    x.label.centroid = scale(x.label.centroid);
    x.label.tail = scale(x.label.tail);
    // The capsule now spans k times the pixels: the world is unchanged.
    x.label.mm_per_px /= k;
    Ok(())
}

fn occlusion(x: &mut Shifted, rng: &mut Rng, s: u32) -> opencv::Result<()> {
    let sf = f64::from(s);
    if x.label.has_robot {
        // A grey bar across the capsule at a random place along its axis.
        let (tx, ty) = (x.label.tail.0, x.label.tail.1);
        let (dx, dy) = (x.label.tip.0 - tx, x.label.tip.1 - ty);
        let length = (dx * dx + dy * dy).sqrt().max(1.0);
        let (ux, uy) = (dx / length, dy / length);
        let hidden = 0.1 * sf * length;
        let start = rng.range(0.0, length - hidden);
        let grey = rng.range(90.0, 170.0);
        map_pixels(&mut x.img, |c, r, px| {
            let (pc, pr) = (c as f64 - tx, r as f64 - ty);
            let along = pc * ux + pr * uy;
            let across = (-pc * uy + pr * ux).abs();
            if (start..start + hidden).contains(&along) && across < length * 0.35 {
                px.fill(clamp_u8(grey));
                x.truth[r * N + c] = 0;
            }
        });
    }
    Ok(())
}

/// Every crop of `split` shifted by `family` at severity `s`.
pub fn perturb_split(split: &Split, family: Family, s: u32, seed: u64) -> opencv::Result<Split> {
    let mut out = Split::default();
    for i in 0..split.len() {
        let crop_seed = seed
            .wrapping_mul(0x100_0000_01B3)
            .wrapping_add((family as u64) << 40 | u64::from(s) << 32 | i as u64);
        let (img, mask, label) = perturb(
            family,
            s,
            split.image(i),
            split.mask(i),
            &split.labels[i],
            crop_seed,
        )?;
        out.push(&img, &mask, label);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn crop() -> (Vec<u8>, Vec<u8>, Label) {
        // Grey background, a blue bar (the capsule) from (30, 48) to (66, 48).
        let mut img = vec![150u8; N * N * 3];
        let mut mask = vec![0u8; N * N];
        for r in 44..53 {
            for c in 30..67 {
                img[(r * N + c) * 3..(r * N + c) * 3 + 3].copy_from_slice(&[40, 60, 200]);
                mask[r * N + c] = 1;
            }
        }
        let label = Label {
            has_robot: true,
            tip: (66.0, 48.0),
            centroid: (48.0, 48.0),
            tail: (30.0, 48.0),
            crop_col0: 0,
            crop_row0: 0,
            mm_per_px: 0.18,
        };
        (img, mask, label)
    }

    #[test]
    fn every_family_changes_the_image_deterministically() {
        let (img, mask, label) = crop();
        for family in Family::ALL {
            for s in 1..=3 {
                let a = perturb(family, s, &img, &mask, &label, 7).unwrap();
                let b = perturb(family, s, &img, &mask, &label, 7).unwrap();
                assert_eq!(a.0, b.0, "{family:?}");
                assert_eq!(a.0.len(), img.len());
                assert_ne!(a.0, img, "{family:?} {s} left the image alone");
                assert!(!family.describe(s).is_empty());
            }
        }
    }

    #[test]
    fn scale_moves_truth_with_the_image_and_occlusion_hides_pixels() {
        let (img, mask, label) = crop();
        let (_, m, l) = perturb(Family::Scale, 3, &img, &mask, &label, 3).unwrap();
        let k = (l.tip.0 - l.tail.0) / (label.tip.0 - label.tail.0);
        assert!((k - 1.1).abs() < 1e-9 || (k - 0.9).abs() < 1e-9, "{k}");
        // Same world length: pixels × mm/px is unchanged.
        assert!(((l.tip.0 - l.tail.0) * l.mm_per_px - 36.0 * 0.18).abs() < 1e-9);
        let area = |m: &[u8]| m.iter().filter(|&&v| v > 0).count() as f64;
        assert!((area(&m) / area(&mask) - k * k).abs() < 0.15);
        let (o, m, _) = perturb(Family::Occlusion, 3, &img, &mask, &label, 3).unwrap();
        let hidden = area(&mask) - area(&m);
        assert!(
            hidden > 0.2 * area(&mask) && hidden < 0.4 * area(&mask),
            "{hidden}"
        );
        assert_ne!(o, img);
    }
}
