"""Camera shifts for training the UNet (domain randomization), in JAX, per sample.

Each family a real camera brings and the twin's renderer does not, drawn independently for every
crop of a batch, at strengths past the robustness suite's highest severity so that severity is
inside what the model saw: scale and shift (camera height, tracking offset), partial occlusion
(truth mask cut where hidden), colour cast and channel mixing, lighting gain / offset / gamma,
saturation, half-plane shadow and illumination gradient, specular glare, air bubbles, floor
texture, motion and defocus blur, sensor noise, JPEG (8x8 DCT quantization with chroma 4:2:0).

This is its own implementation, not the suite's (tools/vision_eval/src/perturb.rs, Rust/OpenCV):
the suite measures what this teaches, so the two share the families, not the code or ranges.
All functions take and return image (N,3,H,W) float in [0,1], mask (N,H,W) and keypoints
(N,3,2) in input pixels, and draw from `r` (a _Draws on a jax.random key); camera_shifts runs
them as one compiled function, outside the gradient. Each family's chance per crop `p` comes
from DEFAULT_CHANCE (or train.py --shift-chance) through camera_shifts.
"""
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np


# Numbers a batch's shifts draw per crop, at most: uniform ones, and normal ones besides the
# image's sensor noise (channel mixing, texture field).
_UNIFORMS = 128
_NORMALS = 3 * 3 + 11 * 11


class _Draws:
    """Random draws for a batch of n crops (C,H,W) from one jax.random key, all from a single
    generator call: each call compiles into code of its own, and the shifts draw about a hundred
    times. Each draw takes the next columns of a uniform table or of a normal one (Box-Muller
    from more of the same call's uniform numbers)."""

    def __init__(self, key, n, c, h, w):
        pairs = (_NORMALS + c * h * w + 1) // 2
        table = jax.random.uniform(key, (n, _UNIFORMS + 2 * pairs), minval=jnp.finfo(jnp.float32).tiny)
        u1, u2 = table[:, _UNIFORMS::2], table[:, _UNIFORMS + 1::2]
        radius = jnp.sqrt(-2.0 * jnp.log(u1))
        self.tables = {
            "uniform": [table[:, :_UNIFORMS], 0],
            "normal": [jnp.concatenate([radius * jnp.cos(2 * math.pi * u2), radius * jnp.sin(2 * math.pi * u2)], axis=1), 0],
        }

    def _take(self, kind, shape):
        """shape: () (one number for the batch), (n,) or (n, k...)."""
        table, used = self.tables[kind]
        width = int(np.prod(shape[1:])) if shape else 1
        if used + width > table.shape[1]:
            raise RuntimeError(f"the shifts draw more {kind} numbers per crop than _Draws holds")
        self.tables[kind][1] = used + width
        columns = table[:, used:used + width]
        return columns[0, 0] if shape == () else columns.reshape(shape)

    def uniform(self, shape, lo=0.0, hi=1.0):
        return lo + (hi - lo) * self._take("uniform", shape)

    def normal(self, shape):
        return self._take("normal", shape)

    def integers(self, shape, lo, hi):
        """Integers in [lo, hi)."""
        return jnp.minimum(jnp.floor(self.uniform(shape, lo, hi)), hi - 1).astype(jnp.int32)

    def chance(self, n, p):
        return self.uniform((n,)) < p


def _grid(h, w):
    ys, xs = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32), indexing="ij")
    return xs, ys


def _col(v):
    """(N,) -> (N,1,1,1) for broadcasting over images."""
    return v[:, None, None, None]


def _gather(plane, xi, yi):
    """plane (N,C,H,W) at integer pixels xi, yi (N,H,W): (N,C,H,W)."""
    n, c, h, w = plane.shape
    flat = (yi * w + xi).reshape(n, 1, h * w)
    return jnp.take_along_axis(plane.reshape(n, c, h * w), jnp.broadcast_to(flat, (n, c, h * w)), axis=2).reshape(n, c, h, w)


def scale_shift(r, img, mask, kps, p, lo=0.85, hi=1.18, shift_px=6.0):
    """Zoom about the centre and shift: keypoint p -> c + s (p - c) + t. The image is sampled
    bilinearly with its border extended, the mask at the nearest pixel with nothing outside."""
    n, _, h, w = img.shape
    on = r.chance(n, p)
    s = jnp.where(on, r.uniform((n,), lo, hi), 1.0)
    t = jnp.where(on[:, None], r.uniform((n, 2), -shift_px, shift_px), 0.0)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    xs, ys = _grid(h, w)
    # The input pixel each output pixel shows: the inverse of the keypoints' map.
    sx = cx + (xs[None] - cx - t[:, 0, None, None]) / s[:, None, None]
    sy = cy + (ys[None] - cy - t[:, 1, None, None]) / s[:, None, None]
    bx, by = jnp.clip(sx, 0, w - 1), jnp.clip(sy, 0, h - 1)
    x0, y0 = jnp.floor(bx), jnp.floor(by)
    fx, fy = (bx - x0)[:, None], (by - y0)[:, None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    x1, y1 = jnp.minimum(x0 + 1, w - 1), jnp.minimum(y0 + 1, h - 1)
    img = ((1 - fy) * ((1 - fx) * _gather(img, x0, y0) + fx * _gather(img, x1, y0))
           + fy * ((1 - fx) * _gather(img, x0, y1) + fx * _gather(img, x1, y1)))
    nx, ny = jnp.round(sx), jnp.round(sy)
    inside = (nx >= 0) & (nx <= w - 1) & (ny >= 0) & (ny <= h - 1)
    picked = _gather(mask[:, None], jnp.clip(nx, 0, w - 1).astype(jnp.int32), jnp.clip(ny, 0, h - 1).astype(jnp.int32))[:, 0]
    mask = jnp.where(inside, picked, 0).astype(mask.dtype)
    c = jnp.array([cx, cy])
    kps = c + s[:, None, None] * (kps - c) + t[:, None, :]
    return img, mask, kps


def occlude(r, img, mask, kps, p):
    """An opaque ellipse over part of the capsule (or anywhere), or a bar across it (a tube, a
    wire, a phantom rib); the truth mask loses what it hides."""
    n, _, h, w = img.shape
    xs, ys = _grid(h, w)
    # Centre: a point along the capsule's axis, or anywhere in the crop.
    t = r.uniform((n, 1))
    centre = kps[:, 2] + t * (kps[:, 0] - kps[:, 2])
    anywhere = r.chance(n, 0.25)
    centre = jnp.where(anywhere[:, None], r.uniform((n, 2)) * (w - 1), centre)
    centre = centre + r.uniform((n, 2), -4.0, 4.0)
    bar = r.chance(n, 0.5)
    a = jnp.where(bar, r.uniform((n,), 8.0, 40.0), r.uniform((n,), 4.0, 18.0))
    b = jnp.where(bar, r.uniform((n,), 0.7, 7.0), r.uniform((n,), 3.0, 12.0))
    angle = r.uniform((n,), 0.0, math.pi)
    cos, sin = jnp.cos(angle)[:, None, None], jnp.sin(angle)[:, None, None]
    dx = xs[None] - centre[:, 0, None, None]
    dy = ys[None] - centre[:, 1, None, None]
    u = dx * cos + dy * sin
    v = -dx * sin + dy * cos
    a, b = a[:, None, None], b[:, None, None]
    ellipse = (u / a) ** 2 + (v / b) ** 2 <= 1.0
    rectangle = (jnp.abs(u) <= a) & (jnp.abs(v) <= b)
    inside = jnp.where(bar[:, None, None], rectangle, ellipse) & r.chance(n, p)[:, None, None]
    # Occluder colour: near the crop's border mean (a wall or tube), a grey, or any colour.
    border = jnp.concatenate([img[:, :, 0], img[:, :, -1], img[:, :, :, 0], img[:, :, :, -1]], axis=2).mean(2)
    kind = r.uniform((n, 1))
    grey = jnp.broadcast_to(r.uniform((n, 1)), (n, 3))
    colour = jnp.where(kind < 0.35, border + r.uniform((n, 3), -0.1, 0.1),
                       jnp.where(kind < 0.7, grey, r.uniform((n, 3))))
    img = jnp.where(inside[:, None], jnp.clip(colour, 0, 1)[:, :, None, None], img)
    mask = jnp.where(inside, 0, mask).astype(mask.dtype)
    return img, mask


def photometric(r, img):
    """Colour cast, channel mixing, gain / offset / gamma and saturation."""
    n = img.shape[0]
    eye = jnp.eye(3)
    gains = jnp.where(r.chance(n, 0.8)[:, None], r.uniform((n, 3), 0.6, 1.4), 1.0)
    cross = jnp.where(r.chance(n, 0.3)[:, None, None], r.normal((n, 3, 3)) * 0.07, 0.0)
    mix = gains[:, :, None] * eye + cross * (1 - eye)
    img = jnp.einsum("nij,njhw->nihw", mix, img)
    grey = img.mean(1, keepdims=True)
    sat = jnp.where(r.chance(n, 0.4), r.uniform((n,), 0.5, 1.4), 1.0)
    img = grey + _col(sat) * (img - grey)
    gain = jnp.where(r.chance(n, 0.8), r.uniform((n,), 0.5, 1.5), 1.0)
    offset = jnp.where(r.chance(n, 0.6), r.uniform((n,), -0.16, 0.16), 0.0)
    img = jnp.clip(_col(gain) * img + _col(offset), 0, 1)
    gamma = jnp.where(r.chance(n, 0.5), jnp.exp(r.uniform((n,), -0.55, 0.55)), 1.0)
    return jnp.maximum(img, 1e-6) ** _col(gamma)


def shading(r, img, p_shadow, p_gradient):
    """A soft-edged half-plane shadow and a linear illumination gradient."""
    n, _, h, w = img.shape
    xs, ys = _grid(h, w)
    angle = r.uniform((n,), 0.0, 2 * math.pi)
    d = (xs[None] - w / 2) * jnp.cos(angle)[:, None, None] + (ys[None] - h / 2) * jnp.sin(angle)[:, None, None]
    d = d - r.uniform((n,), -0.3 * w, 0.3 * w)[:, None, None]
    soft = r.uniform((n,), 0.5, 10.0)[:, None, None]
    dark = jnp.where(r.chance(n, p_shadow), r.uniform((n,), 0.3, 0.9), 1.0)
    factor = 1.0 - (1.0 - dark)[:, None, None] * jax.nn.sigmoid(d / soft)
    angle2 = r.uniform((n,), 0.0, 2 * math.pi)
    ramp = ((xs[None] - w / 2) * jnp.cos(angle2)[:, None, None] + (ys[None] - h / 2) * jnp.sin(angle2)[:, None, None]) / w
    slope = jnp.where(r.chance(n, p_gradient), r.uniform((n,), -0.6, 0.6), 0.0)
    factor = factor * (1.0 + slope[:, None, None] * ramp)
    return img * factor[:, None]


def glare(r, img, p):
    """One or two specular spots (additive, saturating)."""
    n, _, h, w = img.shape
    xs, ys = _grid(h, w)
    for k in range(2):
        on = r.chance(n, p if k == 0 else p / 2)
        cx, cy = r.uniform((n,), 0.1 * w, 0.9 * w), r.uniform((n,), 0.1 * h, 0.9 * h)
        radius = r.uniform((n,), 3.0, 16.0)
        peak = jnp.where(on, r.uniform((n,), 0.15, 1.0), 0.0)
        d2 = ((xs[None] - cx[:, None, None]) ** 2 + (ys[None] - cy[:, None, None]) ** 2) / (radius[:, None, None] ** 2)
        img = img + (peak[:, None, None] * jnp.exp(-d2))[:, None]
    return img


def bubbles(r, img, p, most=6):
    """Air bubbles: a bright thin rim, a faintly lighter inside (over anything: truth kept)."""
    n, _, h, w = img.shape
    xs, ys = _grid(h, w)
    count = jnp.where(r.chance(n, p), r.integers((n,), 1, most + 1), 0)
    for k in range(most):
        on = (count > k).astype(img.dtype)
        cx, cy = r.uniform((n,), 0, w), r.uniform((n,), 0, h)
        radius = r.uniform((n,), 2.0, 8.0)
        d = jnp.sqrt((xs[None] - cx[:, None, None]) ** 2 + (ys[None] - cy[:, None, None]) ** 2) / radius[:, None, None]
        rim = jnp.exp(-(((d - 0.92) / 0.08) ** 2)) * r.uniform((n,), 0.15, 0.45)[:, None, None]
        inner = (d < 0.85) * r.uniform((n,), 0.0, 0.12)[:, None, None]
        img = img + (on[:, None, None] * (rim + inner))[:, None]
    return img


# Texture cells per side, one count per batch: 3 to 11.
_CELLS = (3, 12)


@functools.lru_cache(maxsize=None)
def _bicubic_upsampling(size):
    """Matrices (cells, size, largest cells) that upsample a cells x cells field to size x size as
    bicubic interpolation does (A = -0.75, pixel centres aligned, edge samples repeated); the
    columns past `cells` are zero, so one random field of the largest count serves every count."""
    a = -0.75
    near = lambda t: ((a + 2) * t - (a + 3)) * t * t + 1  # noqa: E731  |t| <= 1
    far = lambda t: ((a * t - 5 * a) * t + 8 * a) * t - 4 * a  # noqa: E731  1 < |t| < 2
    largest = _CELLS[1] - 1
    out = np.zeros((_CELLS[1] - _CELLS[0], size, largest), np.float32)
    for i, cells in enumerate(range(*_CELLS)):
        src = (np.arange(size) + 0.5) * cells / size - 0.5
        base = np.floor(src).astype(int)
        t = src - base
        for offset, weight in ((-1, far(t + 1)), (0, near(t)), (1, near(1 - t)), (2, far(2 - t))):
            np.add.at(out[i], (np.arange(size), np.clip(base + offset, 0, cells - 1)), weight)
    return out


def texture(r, img, mask, p):
    """Smooth floor texture (printed or scratched phantom), mostly behind the capsule."""
    n, _, h, w = img.shape
    cells = r.integers((), *_CELLS) - _CELLS[0]
    up_y = jnp.asarray(_bicubic_upsampling(h))[cells]
    up_x = jnp.asarray(_bicubic_upsampling(w))[cells]
    largest = _CELLS[1] - 1
    field = jnp.einsum("yi,nij,xj->nyx", up_y, r.normal((n, largest, largest)), up_x)
    amp = jnp.where(r.chance(n, p), r.uniform((n,), 0.02, 0.12), 0.0)
    behind = jnp.where(r.chance(n, 0.7)[:, None, None], (mask == 0).astype(img.dtype), 1.0)
    return img + _col(amp) * (field * behind)[:, None]


def blur(r, img, p, size=11):
    """Motion streak (length 1-10 px, any direction) or defocus (Gaussian sigma 0.3-1.8 px)."""
    n, c, h, w = img.shape
    half = size // 2
    xs, ys = _grid(size, size)
    xs, ys = xs - half, ys - half
    angle = r.uniform((n,), 0.0, math.pi)
    length = r.uniform((n,), 1.0, 10.0)
    cos, sin = jnp.cos(angle)[:, None, None], jnp.sin(angle)[:, None, None]
    along = xs[None] * cos + ys[None] * sin
    across = -xs[None] * sin + ys[None] * cos
    streak = jnp.maximum(1.0 - jnp.abs(across), 0) * (jnp.abs(along) <= length[:, None, None] / 2)
    sigma = r.uniform((n,), 0.3, 1.8)
    gauss = jnp.exp(-(xs[None] ** 2 + ys[None] ** 2) / (2 * sigma[:, None, None] ** 2))
    identity = jnp.broadcast_to(((xs == 0) & (ys == 0)).astype(img.dtype), (n, size, size))
    kind = r.uniform((n,))
    on = r.chance(n, p)
    kernel = jnp.where((on & (kind < 0.5))[:, None, None], streak, jnp.where(on[:, None, None], gauss, identity))
    kernel = kernel / jnp.maximum(kernel.sum(axis=(1, 2), keepdims=True), 1e-6)
    # One kernel per crop, the same for its three channels: a correlation with the edge-extended
    # crop, through the FFT (a grouped convolution over N*C runs ten times slower). The padded
    # crop is larger than the kernel's reach, so the FFT's wrap-around stays outside the output.
    padded = jnp.pad(img, ((0, 0), (0, 0), (half, half), (half, half)), mode="edge")
    shape = padded.shape[2:]
    spectrum = jnp.fft.rfft2(padded) * jnp.fft.rfft2(kernel[:, ::-1, ::-1], s=shape)[:, None]
    return jnp.fft.irfft2(spectrum, s=shape)[:, :, size - 1:size - 1 + h, size - 1:size - 1 + w]


def noise(r, img, p):
    n = img.shape[0]
    sigma = jnp.where(r.chance(n, p), r.uniform((n,), 0.0, 0.09), 0.0)
    return img + _col(sigma) * r.normal(img.shape)


_LUMA_Q = np.array([
    [16, 11, 10, 16, 24, 40, 51, 61], [12, 12, 14, 19, 26, 58, 60, 55],
    [14, 13, 16, 24, 40, 57, 69, 56], [14, 17, 22, 29, 51, 87, 80, 62],
    [18, 22, 37, 56, 68, 109, 103, 77], [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101], [72, 92, 95, 98, 112, 100, 103, 99]], dtype=np.float32)
_CHROMA_Q = np.full((8, 8), 99.0, dtype=np.float32)
_CHROMA_Q[:4, :4] = [[17, 18, 24, 47], [18, 21, 26, 66], [24, 26, 56, 99], [47, 66, 99, 99]]


def _dct_matrix():
    k = np.arange(8, dtype=np.float64)
    d = np.cos((2 * k[None, :] + 1) * k[:, None] * math.pi / 16) * math.sqrt(2 / 8)
    d[0] /= math.sqrt(2)
    return d.astype(np.float32)


_DCT = _dct_matrix()


def _quantize_blocks(x, table, scale):
    """x (N,H,W) level-shifted; 8x8 DCT, quantized with table*scale per sample, inverse DCT."""
    n, h, w = x.shape
    d = jnp.asarray(_DCT)
    blocks = x.reshape(n, h // 8, 8, w // 8, 8).transpose(0, 1, 3, 2, 4)
    coeffs = d @ blocks @ d.T
    q = jnp.maximum(jnp.floor((jnp.asarray(table)[None] * scale[:, None, None] + 50) / 100), 1)[:, None, None]
    coeffs = jnp.round(coeffs / q) * q
    back = d.T @ coeffs @ d
    return back.transpose(0, 1, 3, 2, 4).reshape(n, h, w)


def jpeg(r, img, p, lo=10, hi=85):
    """JPEG round trip at quality lo..hi (libjpeg's table scaling, 4:2:0 chroma)."""
    n, _, h, w = img.shape
    on = r.chance(n, p)
    x = jnp.clip(img, 0, 1) * 255.0
    quality = r.uniform((n,), lo, hi)
    scale = jnp.where(quality < 50, 5000.0 / quality, 200.0 - 2.0 * quality)
    red, green, blue = x[:, 0], x[:, 1], x[:, 2]
    y = 0.299 * red + 0.587 * green + 0.114 * blue
    cb = 128 - 0.168736 * red - 0.331264 * green + 0.5 * blue
    cr = 128 + 0.5 * red - 0.418688 * green - 0.081312 * blue
    y = _quantize_blocks(y - 128, _LUMA_Q, scale) + 128
    chroma = jnp.stack([cb, cr], 1).reshape(n, 2, h // 2, 2, w // 2, 2).mean((3, 5))
    cb = _quantize_blocks(chroma[:, 0] - 128, _CHROMA_Q, scale)
    cr = _quantize_blocks(chroma[:, 1] - 128, _CHROMA_Q, scale)
    cb, cr = (jnp.repeat(jnp.repeat(c, 2, axis=1), 2, axis=2) for c in (cb, cr))
    out = jnp.stack([y + 1.402 * cr, y - 0.344136 * cb - 0.714136 * cr, y + 1.772 * cb], 1) / 255.0
    return jnp.where(_col(on), jnp.clip(out, 0, 1), img)


# Each family's chance per crop in `camera_shifts`, unless given (train.py --shift-chance).
DEFAULT_CHANCE = {
    "scale": 0.5, "occlusion": 0.3, "texture": 0.4, "shadow": 0.35, "gradient": 0.3,
    "glare": 0.35, "bubbles": 0.3, "blur": 0.45, "noise": 0.5, "jpeg": 0.3,
}
FAMILIES = tuple(DEFAULT_CHANCE)


def chances(chance=None):
    """The chance of each family of FAMILIES, in that order: DEFAULT_CHANCE's, or `chance`'s
    (a dict from family to probability) where it names the family."""
    p = dict(DEFAULT_CHANCE)
    for family, value in (chance or {}).items():
        if family not in p:
            raise ValueError(f"unknown shift family {family!r} (one of {', '.join(FAMILIES)})")
        p[family] = value
    return np.array([p[family] for family in FAMILIES], dtype=np.float32)


@jax.jit
def _camera_shifts(key, img, mask, kps, p):
    p = dict(zip(FAMILIES, p))
    r = _Draws(key, *img.shape)
    img, mask, kps = scale_shift(r, img, mask, kps, p=p["scale"])
    img, mask = occlude(r, img, mask, kps, p=p["occlusion"])
    img = texture(r, img, mask, p=p["texture"])
    img = photometric(r, img)
    img = shading(r, img, p_shadow=p["shadow"], p_gradient=p["gradient"])
    img = glare(r, img, p=p["glare"])
    img = bubbles(r, img, p=p["bubbles"])
    img = blur(r, jnp.clip(img, 0, 1), p=p["blur"])
    img = noise(r, img, p=p["noise"])
    img = jpeg(r, jnp.clip(img, 0, 1), p=p["jpeg"])
    return jnp.clip(img, 0, 1), mask, kps


def camera_shifts(key, img, mask, kps, chance=None):
    """Every family above, in the order a camera would apply them, drawn from the jax.random
    `key`. `chance` maps a family of FAMILIES to its probability per crop instead of
    DEFAULT_CHANCE's, or is the array chances() makes."""
    p = chance if isinstance(chance, np.ndarray) else chances(chance)
    return _camera_shifts(key, jnp.asarray(img, jnp.float32), jnp.asarray(mask), jnp.asarray(kps, jnp.float32), p)
