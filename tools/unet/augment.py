"""Camera shifts for training the UNet (domain randomization), on the GPU, per sample.

Each family a real camera brings and the twin's renderer does not, drawn independently for every
crop of a batch, at strengths past the robustness suite's highest severity so that severity is
inside what the model saw: scale and shift (camera height, tracking offset), partial occlusion
(truth mask cut where hidden), colour cast and channel mixing, lighting gain / offset / gamma,
saturation, half-plane shadow and illumination gradient, specular glare, air bubbles, floor
texture, motion and defocus blur, sensor noise, JPEG (8x8 DCT quantization with chroma 4:2:0).

This is its own implementation, not the suite's (services/vision/src/perturb.rs, Rust/OpenCV):
the suite measures what this teaches, so the two share the families, not the code or ranges.
All functions take and return image (N,3,H,W) float in [0,1], mask (N,H,W) and keypoints
(N,3,2) in input pixels; they run under torch.no_grad(). Each family's chance per crop `p` comes
from DEFAULT_CHANCE (or train.py --shift-chance) through camera_shifts.
"""
import math

import torch
import torch.nn.functional as F


def _uniform(n, lo, hi, device):
    return torch.empty(n, device=device).uniform_(lo, hi)


def _chance(n, p, device):
    return torch.rand(n, device=device) < p


def _grid(h, w, device):
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=torch.float32, device=device),
        torch.arange(w, dtype=torch.float32, device=device),
        indexing="ij",
    )
    return xs, ys


def _col(v):
    """(N,) -> (N,1,1,1) for broadcasting over images."""
    return v[:, None, None, None]


def scale_shift(img, mask, kps, p, lo=0.85, hi=1.18, shift_px=6.0):
    """Zoom about the centre and shift: keypoint p -> c + s (p - c) + t."""
    n, _, h, w = img.shape
    dev = img.device
    on = _chance(n, p, dev)
    s = torch.where(on, _uniform(n, lo, hi, dev), torch.ones(n, device=dev))
    t = torch.where(on[:, None], torch.empty(n, 2, device=dev).uniform_(-shift_px, shift_px), torch.zeros(n, 2, device=dev))
    theta = torch.zeros(n, 2, 3, device=dev)
    theta[:, 0, 0] = 1.0 / s
    theta[:, 1, 1] = 1.0 / s
    theta[:, 0, 2] = -(2.0 * t[:, 0] / (w - 1)) / s
    theta[:, 1, 2] = -(2.0 * t[:, 1] / (h - 1)) / s
    grid = F.affine_grid(theta, list(img.shape), align_corners=True)
    img = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=True)
    m = F.grid_sample(mask[:, None].float(), grid, mode="nearest", padding_mode="zeros", align_corners=True)
    c = torch.tensor([(w - 1) / 2.0, (h - 1) / 2.0], device=dev)
    kps = c + s[:, None, None] * (kps - c) + t[:, None, :]
    return img, m[:, 0].to(mask.dtype), kps


def occlude(img, mask, kps, p):
    """An opaque ellipse over part of the capsule (or anywhere), or a bar across it (a tube, a
    wire, a phantom rib); the truth mask loses what it hides."""
    n, _, h, w = img.shape
    dev = img.device
    xs, ys = _grid(h, w, dev)
    # Centre: a point along the capsule's axis, or anywhere in the crop.
    t = torch.rand(n, 1, device=dev)
    centre = kps[:, 2] + t * (kps[:, 0] - kps[:, 2])
    anywhere = _chance(n, 0.25, dev)
    centre = torch.where(anywhere[:, None], torch.rand(n, 2, device=dev) * (w - 1), centre)
    centre = centre + torch.empty(n, 2, device=dev).uniform_(-4.0, 4.0)
    bar = _chance(n, 0.5, dev)
    a = torch.where(bar, _uniform(n, 8.0, 40.0, dev), _uniform(n, 4.0, 18.0, dev))
    b = torch.where(bar, _uniform(n, 0.7, 7.0, dev), _uniform(n, 3.0, 12.0, dev))
    angle = _uniform(n, 0.0, math.pi, dev)
    dx = xs[None] - centre[:, 0, None, None]
    dy = ys[None] - centre[:, 1, None, None]
    u = dx * torch.cos(angle)[:, None, None] + dy * torch.sin(angle)[:, None, None]
    v = -dx * torch.sin(angle)[:, None, None] + dy * torch.cos(angle)[:, None, None]
    a, b = a[:, None, None], b[:, None, None]
    ellipse = (u / a) ** 2 + (v / b) ** 2 <= 1.0
    rectangle = (u.abs() <= a) & (v.abs() <= b)
    inside = torch.where(bar[:, None, None], rectangle, ellipse)
    inside &= _chance(n, p, dev)[:, None, None]
    # Occluder colour: near the crop's border mean (a wall or tube), a grey, or any colour.
    border = torch.cat([img[:, :, 0], img[:, :, -1], img[:, :, :, 0], img[:, :, :, -1]], dim=2).mean(2)
    kind = torch.rand(n, 1, device=dev)
    grey = torch.rand(n, 1, device=dev).expand(n, 3)
    colour = torch.where(kind < 0.35, border + torch.empty(n, 3, device=dev).uniform_(-0.1, 0.1),
                         torch.where(kind < 0.7, grey, torch.rand(n, 3, device=dev)))
    img = torch.where(inside[:, None], colour[:, :, None, None].clamp(0, 1), img)
    mask = torch.where(inside, torch.zeros_like(mask), mask)
    return img, mask


def photometric(img):
    """Colour cast, channel mixing, gain / offset / gamma and saturation."""
    n = img.shape[0]
    dev = img.device
    gains = torch.where(_chance(n, 0.8, dev)[:, None], torch.empty(n, 3, device=dev).uniform_(0.6, 1.4), torch.ones(n, 3, device=dev))
    mix = torch.diag_embed(gains)
    cross = torch.where(_chance(n, 0.3, dev)[:, None, None], torch.randn(n, 3, 3, device=dev) * 0.07, torch.zeros(n, 3, 3, device=dev))
    mix = mix + cross * (1 - torch.eye(3, device=dev))
    img = torch.einsum("nij,njhw->nihw", mix, img)
    grey = img.mean(1, keepdim=True)
    sat = torch.where(_chance(n, 0.4, dev), _uniform(n, 0.5, 1.4, dev), torch.ones(n, device=dev))
    img = grey + _col(sat) * (img - grey)
    gain = torch.where(_chance(n, 0.8, dev), _uniform(n, 0.5, 1.5, dev), torch.ones(n, device=dev))
    offset = torch.where(_chance(n, 0.6, dev), _uniform(n, -0.16, 0.16, dev), torch.zeros(n, device=dev))
    img = (_col(gain) * img + _col(offset)).clamp(0, 1)
    gamma = torch.where(_chance(n, 0.5, dev), torch.exp(_uniform(n, -0.55, 0.55, dev)), torch.ones(n, device=dev))
    return img.clamp_min(1e-6) ** _col(gamma)


def shading(img, p_shadow, p_gradient):
    """A soft-edged half-plane shadow and a linear illumination gradient."""
    n, _, h, w = img.shape
    dev = img.device
    xs, ys = _grid(h, w, dev)
    angle = _uniform(n, 0.0, 2 * math.pi, dev)
    d = (xs[None] - w / 2) * torch.cos(angle)[:, None, None] + (ys[None] - h / 2) * torch.sin(angle)[:, None, None]
    d = d - _uniform(n, -0.3 * w, 0.3 * w, dev)[:, None, None]
    soft = _uniform(n, 0.5, 10.0, dev)[:, None, None]
    dark = torch.where(_chance(n, p_shadow, dev), _uniform(n, 0.3, 0.9, dev), torch.ones(n, device=dev))
    factor = 1.0 - (1.0 - dark)[:, None, None] * torch.sigmoid(d / soft)
    angle2 = _uniform(n, 0.0, 2 * math.pi, dev)
    ramp = ((xs[None] - w / 2) * torch.cos(angle2)[:, None, None] + (ys[None] - h / 2) * torch.sin(angle2)[:, None, None]) / w
    slope = torch.where(_chance(n, p_gradient, dev), _uniform(n, -0.6, 0.6, dev), torch.zeros(n, device=dev))
    factor = factor * (1.0 + slope[:, None, None] * ramp)
    return img * factor[:, None]


def glare(img, p):
    """One or two specular spots (additive, saturating)."""
    n, _, h, w = img.shape
    dev = img.device
    xs, ys = _grid(h, w, dev)
    for k in range(2):
        on = _chance(n, p if k == 0 else p / 2, dev)
        cx, cy = _uniform(n, 0.1 * w, 0.9 * w, dev), _uniform(n, 0.1 * h, 0.9 * h, dev)
        r = _uniform(n, 3.0, 16.0, dev)
        peak = torch.where(on, _uniform(n, 0.15, 1.0, dev), torch.zeros(n, device=dev))
        d2 = ((xs[None] - cx[:, None, None]) ** 2 + (ys[None] - cy[:, None, None]) ** 2) / (r[:, None, None] ** 2)
        img = img + (peak[:, None, None] * torch.exp(-d2))[:, None]
    return img


def bubbles(img, p, most=6):
    """Air bubbles: a bright thin rim, a faintly lighter inside (over anything: truth kept)."""
    n, _, h, w = img.shape
    dev = img.device
    xs, ys = _grid(h, w, dev)
    count = torch.where(_chance(n, p, dev), torch.randint(1, most + 1, (n,), device=dev), torch.zeros(n, dtype=torch.long, device=dev))
    for k in range(most):
        on = (count > k).float()
        cx, cy = _uniform(n, 0, w, dev), _uniform(n, 0, h, dev)
        r = _uniform(n, 2.0, 8.0, dev)
        d = torch.sqrt((xs[None] - cx[:, None, None]) ** 2 + (ys[None] - cy[:, None, None]) ** 2) / r[:, None, None]
        rim = torch.exp(-(((d - 0.92) / 0.08) ** 2)) * _uniform(n, 0.15, 0.45, dev)[:, None, None]
        inner = (d < 0.85).float() * _uniform(n, 0.0, 0.12, dev)[:, None, None]
        img = img + (on[:, None, None] * (rim + inner))[:, None]
    return img


def texture(img, mask, p):
    """Smooth floor texture (printed or scratched phantom), mostly behind the capsule."""
    n, _, h, w = img.shape
    dev = img.device
    cells = torch.randint(3, 12, (1,)).item()
    field = F.interpolate(torch.randn(n, 1, cells, cells, device=dev), size=(h, w), mode="bicubic", align_corners=False)
    amp = torch.where(_chance(n, p, dev), _uniform(n, 0.02, 0.12, dev), torch.zeros(n, device=dev))
    behind = torch.where(_chance(n, 0.7, dev)[:, None, None], (mask == 0).float(), torch.ones_like(mask, dtype=torch.float32))
    return img + _col(amp) * field * behind[:, None]


def blur(img, p, size=11):
    """Motion streak (length 1-10 px, any direction) or defocus (Gaussian sigma 0.3-1.8 px)."""
    n, c, h, w = img.shape
    dev = img.device
    r = size // 2
    xs, ys = _grid(size, size, dev)
    xs, ys = xs - r, ys - r
    angle = _uniform(n, 0.0, math.pi, dev)
    length = _uniform(n, 1.0, 10.0, dev)
    along = xs[None] * torch.cos(angle)[:, None, None] + ys[None] * torch.sin(angle)[:, None, None]
    across = -xs[None] * torch.sin(angle)[:, None, None] + ys[None] * torch.cos(angle)[:, None, None]
    streak = (1.0 - across.abs()).clamp(min=0) * (along.abs() <= length[:, None, None] / 2).float()
    sigma = _uniform(n, 0.3, 1.8, dev)
    gauss = torch.exp(-(xs[None] ** 2 + ys[None] ** 2) / (2 * sigma[:, None, None] ** 2))
    identity = ((xs == 0) & (ys == 0)).float()[None].expand(n, -1, -1)
    kind = torch.rand(n, device=dev)
    on = _chance(n, p, dev)
    kernel = torch.where((on & (kind < 0.5))[:, None, None], streak, torch.where(on[:, None, None], gauss, identity))
    kernel = kernel / kernel.sum(dim=(1, 2), keepdim=True).clamp_min(1e-6)
    weight = kernel[:, None].repeat_interleave(c, dim=0)
    padded = F.pad(img.reshape(1, n * c, h, w), (r, r, r, r), mode="replicate")
    return F.conv2d(padded, weight, groups=n * c).reshape(n, c, h, w)


def noise(img, p):
    n = img.shape[0]
    dev = img.device
    sigma = torch.where(_chance(n, p, dev), _uniform(n, 0.0, 0.09, dev), torch.zeros(n, device=dev))
    return img + _col(sigma) * torch.randn_like(img)


_LUMA_Q = torch.tensor([
    [16, 11, 10, 16, 24, 40, 51, 61], [12, 12, 14, 19, 26, 58, 60, 55],
    [14, 13, 16, 24, 40, 57, 69, 56], [14, 17, 22, 29, 51, 87, 80, 62],
    [18, 22, 37, 56, 68, 109, 103, 77], [24, 35, 55, 64, 81, 104, 113, 92],
    [49, 64, 78, 87, 103, 121, 120, 101], [72, 92, 95, 98, 112, 100, 103, 99]], dtype=torch.float32)
_CHROMA_Q = torch.full((8, 8), 99.0)
_CHROMA_Q[:4, :4] = torch.tensor([[17, 18, 24, 47], [18, 21, 26, 66], [24, 26, 56, 99], [47, 66, 99, 99]], dtype=torch.float32)


def _dct_matrix(device):
    k = torch.arange(8, dtype=torch.float32, device=device)
    d = torch.cos((2 * k[None, :] + 1) * k[:, None] * math.pi / 16) * math.sqrt(2 / 8)
    d[0] /= math.sqrt(2)
    return d


def _quantize_blocks(x, table, scale):
    """x (N,H,W) level-shifted; 8x8 DCT, quantized with table*scale per sample, inverse DCT."""
    n, h, w = x.shape
    d = _dct_matrix(x.device)
    blocks = x.reshape(n, h // 8, 8, w // 8, 8).permute(0, 1, 3, 2, 4)
    coeffs = d @ blocks @ d.T
    q = torch.clamp(torch.floor((table.to(x.device)[None] * scale[:, None, None] + 50) / 100), min=1)[:, None, None]
    coeffs = torch.round(coeffs / q) * q
    back = d.T @ coeffs @ d
    return back.permute(0, 1, 3, 2, 4).reshape(n, h, w)


def jpeg(img, p, lo=10, hi=85):
    """JPEG round trip at quality lo..hi (libjpeg's table scaling, 4:2:0 chroma)."""
    n, _, h, w = img.shape
    dev = img.device
    on = _chance(n, p, dev)
    if not on.any():
        return img
    x = img[on].clamp(0, 1) * 255.0
    k = x.shape[0]
    quality = _uniform(k, lo, hi, dev)
    scale = torch.where(quality < 50, 5000.0 / quality, 200.0 - 2.0 * quality)
    r, g, b = x[:, 0], x[:, 1], x[:, 2]
    y = 0.299 * r + 0.587 * g + 0.114 * b
    cb = 128 - 0.168736 * r - 0.331264 * g + 0.5 * b
    cr = 128 + 0.5 * r - 0.418688 * g - 0.081312 * b
    y = _quantize_blocks(y - 128, _LUMA_Q, scale) + 128
    chroma = F.avg_pool2d(torch.stack([cb, cr], 1), 2)
    cb2 = _quantize_blocks(chroma[:, 0] - 128, _CHROMA_Q, scale) + 128
    cr2 = _quantize_blocks(chroma[:, 1] - 128, _CHROMA_Q, scale) + 128
    up = F.interpolate(torch.stack([cb2, cr2], 1), scale_factor=2, mode="nearest")
    cb, cr = up[:, 0] - 128, up[:, 1] - 128
    out = torch.stack([y + 1.402 * cr, y - 0.344136 * cb - 0.714136 * cr, y + 1.772 * cb], 1) / 255.0
    img = img.clone()
    img[on] = out.clamp(0, 1)
    return img


# Each family's chance per crop in `camera_shifts`, unless given (train.py --shift-chance).
DEFAULT_CHANCE = {
    "scale": 0.5, "occlusion": 0.3, "texture": 0.4, "shadow": 0.35, "gradient": 0.3,
    "glare": 0.35, "bubbles": 0.3, "blur": 0.45, "noise": 0.5, "jpeg": 0.3,
}
FAMILIES = tuple(DEFAULT_CHANCE)


def camera_shifts(img, mask, kps, chance=None):
    """Every family above, in the order a camera would apply them. `chance` maps a family of
    FAMILIES to its probability per crop instead of DEFAULT_CHANCE's."""
    p = dict(DEFAULT_CHANCE)
    for family, value in (chance or {}).items():
        if family not in p:
            raise ValueError(f"unknown shift family {family!r} (one of {', '.join(FAMILIES)})")
        p[family] = value
    with torch.no_grad():
        img, mask, kps = scale_shift(img, mask, kps, p=p["scale"])
        img, mask = occlude(img, mask, kps, p=p["occlusion"])
        img = texture(img, mask, p=p["texture"])
        img = photometric(img)
        img = shading(img, p_shadow=p["shadow"], p_gradient=p["gradient"])
        img = glare(img, p=p["glare"])
        img = bubbles(img, p=p["bubbles"])
        img = blur(img.clamp(0, 1), p=p["blur"])
        img = noise(img, p=p["noise"])
        img = jpeg(img.clamp(0, 1), p=p["jpeg"])
        return img.clamp(0, 1), mask, kps
