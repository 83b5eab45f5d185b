#!/usr/bin/env python3
"""Train millinav's UNet localizer (segmentation + tip/centroid/tail keypoints) and export ONNX.

Follows the paper's recipe (RIG.md, Vision): loss = cross-entropy (mask) + 0.5 * L1 (keypoints),
Adam lr 1e-3, ReduceLROnPlateau, early stopping, flips and 90-degree rotations. Differences,
chosen for a 2-core CPU at inference: input is a 96x96 ROI (192 px crop downsampled 2x, see
services/roi/src/roi.rs) instead of 572x572, a 3-level UNet with 16/32/64 channels, and batch 32.

Keypoints come from 3 heatmaps through a spatial soft-argmax, so the exported graph outputs
coordinates directly:
  input  "image"     float32 [1, 3, 96, 96], RGB in [0, 1]
  output "seg"       float32 [1, 2, 96, 96], logits (class 1 = capsule)
  output "keypoints" float32 [1, 3, 2], (x, y) of tip, centroid, tail in input pixels
  output "presence"  float32 [1, 1], logit that a capsule is in the crop

Training applies the camera's shifts to every batch (augment.py: scale, occlusion, colour cast,
lighting, shadow, glare, bubbles, texture, blur, noise, JPEG) on top of flips and rotations;
early stopping watches the validation loss on clean crops and on a fixed shifted copy of them.
Beside the ONNX file (export.py) it writes the weights (.npz, weights.py), from which --init
fine-tunes; --init also reads a PyTorch state dict (.pt) of the earlier trainer.
Two departures from the paper's recipe, off by default: --iou-weight adds a soft-IoU term to
the loss, --ema keeps a moving average of the weights (README, Vision: tried on a GPU, no gain).

Runs on JAX, on the CPU with the CPU wheels that scripts/setup_training.sh installs; on a
machine with an NVIDIA GPU, `pip install "jax[cuda12]==0.10.2"` in the same venv makes JAX (and
so this script) use the GPU.

Usage: python3 train.py --data DATASET_DIR [--data MORE_TRAIN_DIR ...] --out model.onnx
       [--epochs 60] [--init model.npz --lr 3e-4] [--augment flips] [--iou-weight 0.5] [--ema 0.999]
"""
import argparse
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import lax

# Compiled steps are kept across runs (seconds of compile each on a CPU); JAX's own
# JAX_COMPILATION_CACHE_DIR, when set, says where instead.
if jax.config.jax_compilation_cache_dir is None:
    jax.config.update("jax_compilation_cache_dir", os.path.expanduser("~/.cache/millinav/jax"))

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import augment as camera  # noqa: E402  (beside this script)
import export  # noqa: E402
import weights as weight_files  # noqa: E402

INPUT = 96
HEADER = "index,has_robot,tip_x,tip_y,centroid_x,centroid_y,tail_x,tail_y,crop_col0,crop_row0,mm_per_px"
BN_EPS = 1e-5
BN_MOMENTUM = 0.1
# Crops per forward pass when evaluating.
EVAL_BATCH = 256


def load_labels(directory):
    path = f"{directory}/labels.csv"
    if not os.path.isfile(path):
        sys.exit(f"{path}: no such file (want a split of unet-dataset or unet-import)")
    with open(path) as f:
        header = f.readline().strip()
    if header != HEADER:
        sys.exit(f"{path}: unexpected header (want {HEADER})")
    return np.genfromtxt(path, delimiter=",", skip_header=1, dtype=np.float64).reshape(-1, 11)


def load_split(directory):
    """(images (N,96,96,3) uint8, masks (N,96,96) uint8, has (N,), keypoints (N,3,2))."""
    labels = load_labels(directory)
    n = labels.shape[0]
    if n == 0:
        sys.exit(f"{directory}: empty split")
    images = np.fromfile(f"{directory}/images.u8", dtype=np.uint8)
    masks = np.fromfile(f"{directory}/masks.u8", dtype=np.uint8)
    if images.size != n * INPUT * INPUT * 3 or masks.size != n * INPUT * INPUT:
        sys.exit(f"{directory}: images.u8/masks.u8 do not hold {n} crops of {INPUT}x{INPUT}")
    images = images.reshape(n, INPUT, INPUT, 3)
    masks = masks.reshape(n, INPUT, INPUT)
    has = labels[:, 1].astype(np.float32)
    kps = labels[:, 2:8].reshape(n, 3, 2).astype(np.float32)
    return images, masks, has, kps


def save_split(directory, images, masks, has, kps, mm_per_px):
    """Writes crops as training holds them (images (N,3,H,W) float in [0,1]) in unet-dataset's
    split format."""
    os.makedirs(directory, exist_ok=True)
    img = np.round(np.clip(np.asarray(images).transpose(0, 2, 3, 1), 0, 1) * 255).astype(np.uint8)
    img.tofile(f"{directory}/images.u8")
    np.asarray(masks).astype(np.uint8).tofile(f"{directory}/masks.u8")
    k = np.asarray(kps).reshape(-1, 6)
    has = np.asarray(has)
    with open(f"{directory}/labels.csv", "w") as f:
        f.write(HEADER + "\n")
        for i in range(img.shape[0]):
            coords = ",".join(f"{v:.4f}" for v in k[i])
            f.write(f"{i},{int(has[i] > 0.5)},{coords},0,0,{mm_per_px}\n")


def to_input(images):
    """uint8 crops (N,H,W,3) -> the model's input (N,3,H,W) float in [0,1]."""
    return jnp.asarray(images).transpose(0, 3, 1, 2).astype(jnp.float32) / 255.0


# The UNet. Its weights are a dict of arrays named and shaped as PyTorch's state dict of the
# earlier trainer (weights.py): `levels` resolutions (the input's and levels - 1 halvings),
# `width` channels at the first, doubling at each. Blocks enc1.., bottom, decK are
# Conv(3x3, no bias)-BN-ReLU twice (conv .0/.3, batch norm .1/.4); upK a 2x2 transposed
# convolution of stride 2; seg and heat 1x1 convolutions; presence a linear layer on the bottom
# block's spatial mean. The default, 3 levels of 16/32/64, is the committed model.

def check_shape(levels, width):
    if levels < 2 or width < 1 or INPUT % 2 ** (levels - 1):
        raise ValueError(f"a UNet of {levels} levels and width {width} does not fit a {INPUT} px input")


def block_names(levels):
    """The Conv-BN-ReLU blocks in the order the forward pass meets them."""
    return [f"enc{k}" for k in range(1, levels)] + ["bottom"] + [f"dec{k}" for k in range(levels - 1, 0, -1)]


def shape_of(arrays):
    """(levels, width) of the UNet whose weights these are."""
    levels = 1 + sum(1 for key in arrays if key.startswith("enc") and key.endswith(".0.weight"))
    return levels, arrays["enc1.0.weight"].shape[0]


def expected_shapes(levels, width):
    """{name: shape} of every array of a UNet of this shape (learned and batch-norm statistics)."""
    c = [width * 2 ** i for i in range(levels)]
    ins = {f"enc{k}": 3 if k == 1 else c[k - 2] for k in range(1, levels)}
    outs = {f"enc{k}": c[k - 1] for k in range(1, levels)}
    ins["bottom"], outs["bottom"] = c[-2], c[-1]
    for k in range(1, levels):
        ins[f"dec{k}"], outs[f"dec{k}"] = 2 * c[k - 1], c[k - 1]
    shapes = {}
    for name in block_names(levels):
        for conv, bn, cin in ((0, 1, ins[name]), (3, 4, outs[name])):
            shapes[f"{name}.{conv}.weight"] = (outs[name], cin, 3, 3)
            for part in ("weight", "bias", "running_mean", "running_var"):
                shapes[f"{name}.{bn}.{part}"] = (outs[name],)
    for k in range(1, levels):
        shapes[f"up{k}.weight"], shapes[f"up{k}.bias"] = (c[k], c[k - 1], 2, 2), (c[k - 1],)
    shapes["seg.weight"], shapes["seg.bias"] = (2, c[0], 1, 1), (2,)
    shapes["heat.weight"], shapes["heat.bias"] = (3, c[0], 1, 1), (3,)
    shapes["presence.weight"], shapes["presence.bias"] = (1, c[-1]), (1,)
    return shapes


def init_arrays(levels, width, seed):
    """Fresh weights as PyTorch initializes these layers: weights and biases uniform in
    +-1/sqrt(fan in), batch norm scale 1, shift 0, statistics of a unit normal."""
    check_shape(levels, width)
    rng = np.random.default_rng(seed)
    shapes = expected_shapes(levels, width)
    arrays = {}
    for name, shape in shapes.items():
        layer, part = name.rsplit(".", 1)
        batch_norm = f"{layer}.running_mean" in shapes
        if part == "running_var" or (batch_norm and part == "weight"):
            arrays[name] = np.ones(shape, np.float32)
        elif part == "running_mean" or (batch_norm and part == "bias"):
            arrays[name] = np.zeros(shape, np.float32)
        else:
            # The fan in of upK's (in, out, 2, 2) weight is out x 4: PyTorch's too.
            bound = 1.0 / np.sqrt(np.prod(shapes[f"{layer}.weight"][1:]))
            arrays[name] = rng.uniform(-bound, bound, shape).astype(np.float32)
    return arrays


def from_arrays(arrays, source):
    """(params, state): the learned arrays and the batch-norm statistics, as jax arrays, from
    weights of any shape train.py builds; exits naming `source` if an array is missing or
    misshapen. Arrays the model does not use (PyTorch's grids and batch counters) are dropped."""
    if "enc1.0.weight" not in arrays:
        sys.exit(f"{source}: no enc1.0.weight: not weights of this UNet")
    levels, width = shape_of(arrays)
    shapes = expected_shapes(levels, width)
    for name, shape in shapes.items():
        if name not in arrays:
            sys.exit(f"{source}: no {name} (a UNet of {levels} levels and width {width} has one)")
        if tuple(arrays[name].shape) != shape:
            sys.exit(f"{source}: {name} is {tuple(arrays[name].shape)}, want {shape}")
    statistics = [name for name in shapes if name.endswith(("running_mean", "running_var"))]
    params = {k: jnp.asarray(arrays[k], jnp.float32) for k in shapes if k not in statistics}
    state = {k: jnp.asarray(arrays[k], jnp.float32) for k in statistics}
    return params, state


def to_arrays(params, state):
    return {k: np.asarray(v) for k, v in {**params, **state}.items()}


def _conv(x, weight, bias=None, pad=1):
    """NHWC x, PyTorch's OIHW weight."""
    y = lax.conv_general_dilated(x, weight, (1, 1), ((pad, pad), (pad, pad)),
                                 dimension_numbers=("NHWC", "OIHW", "NHWC"))
    return y if bias is None else y + bias


def _batch_norm(x, params, state, new_state, name, train):
    scale, shift = params[f"{name}.weight"], params[f"{name}.bias"]
    mean_key, var_key = f"{name}.running_mean", f"{name}.running_var"
    if train:
        mean = x.mean((0, 1, 2))
        var = x.var((0, 1, 2))
        count = x.size // x.shape[-1]
        # The running variance is the unbiased one, as PyTorch keeps it.
        new_state[mean_key] = (1 - BN_MOMENTUM) * state[mean_key] + BN_MOMENTUM * lax.stop_gradient(mean)
        new_state[var_key] = (1 - BN_MOMENTUM) * state[var_key] + BN_MOMENTUM * lax.stop_gradient(var) * count / max(count - 1, 1)
    else:
        mean, var = state[mean_key], state[var_key]
    return (x - mean) * (scale * lax.rsqrt(var + BN_EPS)) + shift


def _block(x, params, state, new_state, name, train):
    for conv, bn in ((0, 1), (3, 4)):
        x = _conv(x, params[f"{name}.{conv}.weight"])
        x = jax.nn.relu(_batch_norm(x, params, state, new_state, f"{name}.{bn}", train))
    return x


def _max_pool(x):
    n, h, w, c = x.shape
    return x.reshape(n, h // 2, 2, w // 2, 2, c).max((2, 4))


def _up(x, weight, bias):
    """2x2 transposed convolution of stride 2: each input pixel paints its own 2x2 patch."""
    n, h, w, _ = x.shape
    y = jnp.einsum("nijc,coab->niajbo", x, weight).reshape(n, 2 * h, 2 * w, weight.shape[1])
    return y + bias


def _grid():
    ys, xs = np.meshgrid(np.arange(INPUT, dtype=np.float32), np.arange(INPUT, dtype=np.float32), indexing="ij")
    return np.stack([xs.ravel(), ys.ravel()], axis=1)  # (H*W, 2): (x, y) of each pixel


GRID = _grid()


def forward(params, state, image, train):
    """image (N,3,96,96) in [0,1] -> ((seg (N,2,96,96), keypoints (N,3,2), presence (N,1)),
    batch-norm state): the state updated from the batch's statistics when training, else as
    given (the statistics normalize)."""
    levels = shape_of(params)[0]
    new_state = dict(state)
    x = image.transpose(0, 2, 3, 1)
    skips = []
    for k in range(1, levels):
        x = _block(x if k == 1 else _max_pool(x), params, state, new_state, f"enc{k}", train)
        skips.append(x)
    bottom = _block(_max_pool(x), params, state, new_state, "bottom", train)
    d = bottom
    for k in range(levels - 1, 0, -1):
        up = _up(d, params[f"up{k}.weight"], params[f"up{k}.bias"])
        d = _block(jnp.concatenate([up, skips[k - 1]], axis=3), params, state, new_state, f"dec{k}", train)
    seg = _conv(d, params["seg.weight"], params["seg.bias"], pad=0).transpose(0, 3, 1, 2)
    heat = _conv(d, params["heat.weight"], params["heat.bias"], pad=0)
    n = heat.shape[0]
    prob = jax.nn.softmax(heat.reshape(n, -1, 3).transpose(0, 2, 1), axis=2)
    keypoints = prob @ GRID
    presence = bottom.mean((1, 2)) @ params["presence.weight"].T + params["presence.bias"]
    return (seg, keypoints, presence), new_state


def flips(rng, img, mask, kps):
    """Random flips and 90-degree rotations of a batch (N,H,W,3), (N,H,W), (N,3,2), one draw of
    `rng` (numpy Generator) for the whole batch."""
    s = INPUT - 1
    kps = kps.copy()
    if rng.random() < 0.5:
        img, mask = img[:, :, ::-1], mask[:, :, ::-1]
        kps[..., 0] = s - kps[..., 0]
    if rng.random() < 0.5:
        img, mask = img[:, ::-1], mask[:, ::-1]
        kps[..., 1] = s - kps[..., 1]
    k = int(rng.integers(4))
    for _ in range(k):
        # rot90 counter-clockwise in the (H, W) plane: (x, y) -> (y, s - x)
        img, mask = np.rot90(img, 1, (1, 2)), np.rot90(mask, 1, (1, 2))
        kps = np.stack([kps[..., 1], s - kps[..., 0]], axis=-1)
    return np.ascontiguousarray(img), np.ascontiguousarray(mask), kps


def soft_jaccard(seg, mask):
    """1 - soft IoU of the capsule class over the whole batch: the same pixel-pooled overlap that
    evaluate() and vision-eval report, made differentiable with the softmax probability."""
    p = jax.nn.softmax(seg, axis=1)[:, 1]
    t = mask.astype(jnp.float32)
    inter = (p * t).sum()
    return 1.0 - inter / ((p + t).sum() - inter + 1.0)


def loss_fn(seg, kp, presence, mask, kps, has, iou_weight=0.0):
    logp = jax.nn.log_softmax(seg, axis=1)
    ce = -jnp.where(mask == 1, logp[:, 1], logp[:, 0]).mean()
    weight = has[:, None, None]
    l1 = (weight * jnp.abs(kp - kps) / INPUT).sum() / (weight.sum() * 6 + 1e-6)
    logit = presence[:, 0]
    pres = (jax.nn.softplus(logit) - logit * has).mean()
    loss = ce + 0.5 * l1 + 0.1 * pres
    if iou_weight > 0.0:
        loss = loss + iou_weight * soft_jaccard(seg, mask)
    return loss


def make_train_step(optimizer, iou_weight):
    def step(params, state, opt_state, image, mask, kps, has):
        def objective(p):
            (seg, kp, pres), new_state = forward(p, state, image, train=True)
            return loss_fn(seg, kp, pres, mask, kps, has, iou_weight), new_state
        (loss, new_state), grads = jax.value_and_grad(objective, has_aux=True)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), new_state, opt_state, loss
    return jax.jit(step)


@jax.jit
def _ema(decay, average, current):
    return jax.tree.map(lambda a, c: decay * a + (1 - decay) * c, average, current)


def _eval_batch(params, state, image, mask, kps, has, iou_weight):
    (seg, kp, pres), _ = forward(params, state, image, train=False)
    pred = seg.argmax(1)
    counts = jnp.stack([((pred == 1) & (mask == 1)).sum(), ((pred == 1) & (mask == 0)).sum(),
                        ((pred == 0) & (mask == 1)).sum()])
    loss = loss_fn(seg, kp, pres, mask, kps, has, iou_weight)
    return loss, counts, jnp.linalg.norm(kp - kps, axis=2)


_eval_batch_jit = jax.jit(_eval_batch, static_argnums=6)


def evaluate(params, state, data, iou_weight=0.0, batch=EVAL_BATCH):
    """data: (images (N,3,H,W) float, masks, has, keypoints)."""
    images, masks, has, kps = data
    tp = fp = fn = 0
    errors = []
    total = 0.0
    for i in range(0, images.shape[0], batch):
        h = has[i:i + batch]
        loss, counts, err = _eval_batch_jit(params, state, images[i:i + batch], masks[i:i + batch],
                                            kps[i:i + batch], h, iou_weight)
        total += float(loss) * h.shape[0]
        c = np.asarray(counts)
        tp, fp, fn = tp + int(c[0]), fp + int(c[1]), fn + int(c[2])
        errors.append(np.asarray(err)[np.asarray(h) > 0.5])
    err = np.concatenate(errors)
    return {
        "loss": total / images.shape[0],
        "precision": tp / max(tp + fp, 1),
        "recall": tp / max(tp + fn, 1),
        "iou": tp / max(tp + fp + fn, 1),
        "centroid_err_px_median": float(np.median(err[:, 1])) if len(err) else float("nan"),
        "tip_err_px_median": float(np.median(err[:, 0])) if len(err) else float("nan"),
    }


class ReduceLROnPlateau:
    """PyTorch's scheduler of that name with its defaults (mode min, relative threshold 1e-4)."""

    def __init__(self, lr, factor=0.5, patience=4, threshold=1e-4):
        self.lr, self.factor, self.patience, self.threshold = lr, factor, patience, threshold
        self.best, self.bad = float("inf"), 0

    def step(self, score):
        if score < self.best * (1 - self.threshold):
            self.best, self.bad = score, 0
        else:
            self.bad += 1
        if self.bad > self.patience:
            self.lr *= self.factor
            self.bad = 0
        return self.lr


def shifted_copy(key, data, batch=EVAL_BATCH):
    """The camera shifts applied once to a clean split (N,3,H,W) float, batch by batch."""
    images, masks, has, kps = data
    parts = [camera.camera_shifts(jax.random.fold_in(key, i), images[i:i + batch], masks[i:i + batch], kps[i:i + batch])
             for i in range(0, images.shape[0], batch)]
    img, mask, k = (jnp.concatenate(xs) for xs in zip(*parts))
    return img, mask, has, k


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, action="append",
                    help="dataset dir with train/ (val/ test/ from the first); repeat to add training crops")
    ap.add_argument("--out", required=True, help="output .onnx path (the .npz weights go beside it)")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--patience", type=int, default=10, help="early stopping patience (epochs)")
    ap.add_argument("--max-minutes", type=float, default=None, help="stop after this long (best weights kept)")
    ap.add_argument("--augment", choices=["camera", "flips"], default="camera",
                    help="camera: flips + camera shifts (augment.py); flips: flips and rotations only")
    ap.add_argument("--init", default=None,
                    help="start from these weights (.npz written by this script, or a PyTorch .pt state dict)")
    ap.add_argument("--dump-augmented", default=None,
                    help="also write this many shifted training crops as a split to DIR (e.g. quantization calibration)",
                    nargs=2, metavar=("DIR", "COUNT"))
    ap.add_argument("--shift-chance", action="append", default=[], metavar="FAMILY=P",
                    help="train with this chance per crop for one camera-shift family (augment.FAMILIES: "
                         + ", ".join(camera.FAMILIES) + "); repeat for more. Validation keeps the defaults")
    ap.add_argument("--iou-weight", type=float, default=0.0,
                    help="add this weight x (1 - soft IoU of the mask) to the paper's loss (CE + 0.5 L1); 0: the paper's")
    ap.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                    help="evaluate, early-stop and export an exponential moving average of the weights "
                         "(e.g. 0.999 per step); 0: the weights as trained")
    ap.add_argument("--levels", type=int, default=None,
                    help="resolutions of the UNet (default 3, or --init's); each more sees twice as far and costs more per crop")
    ap.add_argument("--width", type=int, default=None,
                    help="channels at full resolution, doubling per level (default 16, or --init's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--metrics", default=None, help="write final metrics JSON here")
    args = ap.parse_args()
    chance = {}
    for item in args.shift_chance:
        family, _, value = item.partition("=")
        try:
            p = float(value)
        except ValueError:
            p = float("nan")
        if family not in camera.FAMILIES or not 0.0 <= p <= 1.0:
            ap.error(f"--shift-chance {item!r}: expected FAMILY=P with FAMILY one of "
                     f"{', '.join(camera.FAMILIES)} and P a number in [0, 1]")
        chance[family] = p
    if not 0.0 <= args.iou_weight <= 10.0:
        ap.error(f"--iou-weight {args.iou_weight}: expected a number in [0, 10]")
    if args.levels is not None and not 2 <= args.levels <= 5:
        ap.error(f"--levels {args.levels}: expected 2 to 5 (the 96 px input halves at each)")
    if args.width is not None and not 4 <= args.width <= 64:
        ap.error(f"--width {args.width}: expected 4 to 64 channels")
    if not (args.ema == 0.0 or 0.9 <= args.ema < 1.0):
        ap.error(f"--ema {args.ema}: expected 0 (off) or a decay in [0.9, 1)")
    # The starting weights before any data is read, so a wrong --init fails at once.
    shape = (args.levels or 3, args.width or 16)
    if args.init:
        if not os.path.isfile(args.init):
            ap.error(f"--init {args.init}: no such file")
        params, state = from_arrays(weight_files.load(args.init), args.init)
        shape = shape_of(params)
        if (args.levels or shape[0], args.width or shape[1]) != shape:
            sys.exit(f"--init {args.init}: a UNet of {shape[0]} levels and width {shape[1]}, "
                     f"not the --levels {args.levels or shape[0]} --width {args.width or shape[1]} asked for")
        print(f"fine-tuning from {args.init} ({shape[0]} levels, width {shape[1]})")
    else:
        params, state = from_arrays(init_arrays(*shape, args.seed), "fresh weights")
    # The output folders now, not after the training: a run is never lost to a missing folder.
    for path in (args.out, args.metrics):
        if path and os.path.dirname(path):
            os.makedirs(os.path.dirname(path), exist_ok=True)
    rng = np.random.default_rng(args.seed)
    key = jax.random.PRNGKey(args.seed)
    parts = [load_split(f"{d}/train") for d in args.data]
    train = tuple(np.concatenate(xs) for xs in zip(*parts))

    def clean(split):
        images, masks, has, kps = split
        return to_input(images), jnp.asarray(masks), jnp.asarray(has), jnp.asarray(kps)

    val = clean(load_split(f"{args.data[0]}/val"))
    test_dir = f"{args.data[0]}/test"
    test = clean(load_split(test_dir)) if os.path.isdir(test_dir) else val
    # A fixed shifted copy of val (and test), so early stopping sees robustness too; drawn from
    # their own key, so the training's draws do not depend on the split sizes.
    val_key, test_key = jax.random.split(jax.random.PRNGKey(args.seed + 1))
    val_shifted = shifted_copy(val_key, val)
    test_shifted = shifted_copy(test_key, test)
    p_train = camera.chances(chance)
    if args.dump_augmented:
        directory, count = args.dump_augmented[0], int(args.dump_augmented[1])
        idx = rng.permutation(train[0].shape[0])[:count]
        key, dump_key = jax.random.split(key)
        img, mask, kps = camera.camera_shifts(dump_key, to_input(train[0][idx]), train[1][idx], train[3][idx])
        mm_per_px = load_labels(f"{args.data[0]}/train")[0, 10]
        save_split(directory, img, mask, train[2][idx], kps, mm_per_px)
        print(f"wrote {idx.shape[0]} shifted training crops to {directory}")
    print(f"training on {jax.devices()[0].platform}", flush=True)
    optimizer = optax.inject_hyperparams(optax.adam)(learning_rate=args.lr)
    opt_state = optimizer.init(params)
    train_step = make_train_step(optimizer, args.iou_weight)
    sched = ReduceLROnPlateau(args.lr)
    # The weights that are evaluated and exported: the trained ones, or their moving average
    # (batch-norm statistics averaged too), which starts at the weights after the first step.
    averaged = None
    best, best_weights, stale = float("inf"), None, 0
    n = train[0].shape[0]
    start = time.time()
    epoch = -1
    for epoch in range(args.epochs):
        perm = rng.permutation(n)
        for i in range(0, n, args.batch):
            # Every batch full: the last is topped up from the start of the epoch's order, so
            # one compiled step (seconds to compile on a CPU) serves the whole run.
            idx = perm[np.arange(i, i + args.batch) % n]
            x, m, k = flips(rng, train[0][idx], train[1][idx], train[3][idx])
            x = to_input(x)
            if args.augment == "camera":
                key, batch_key = jax.random.split(key)
                x, m, k = camera.camera_shifts(batch_key, x, m, k, p_train)
            params, state, opt_state, _ = train_step(params, state, opt_state, x, m, k, train[2][idx])
            if args.ema > 0.0:
                averaged = (params, state) if averaged is None else _ema(args.ema, averaged, (params, state))
        scored = averaged if averaged is not None else (params, state)
        clean_metrics = evaluate(*scored, val, iou_weight=args.iou_weight)
        shifted = evaluate(*scored, val_shifted, iou_weight=args.iou_weight)
        score = clean_metrics["loss"] + shifted["loss"]
        opt_state.hyperparams["learning_rate"] = jnp.asarray(sched.step(score), jnp.float32)
        summary = {k: round(v, 4) for k, v in clean_metrics.items()}
        summary.update({f"shifted_{k}": round(v, 4) for k, v in shifted.items() if k in ("loss", "precision", "recall", "iou")})
        print(f"epoch {epoch:3d} val {json.dumps(summary)} lr {sched.lr:.1e} t {time.time() - start:.0f}s", flush=True)
        if score < best - 1e-5:
            best, stale = score, 0
            best_weights = scored
        else:
            stale += 1
            if stale >= args.patience:
                print(f"early stop at epoch {epoch}")
                break
        if args.max_minutes is not None and time.time() - start > 60 * args.max_minutes:
            print(f"time limit at epoch {epoch}")
            break
    params, state = best_weights if best_weights is not None else (params, state)
    final = evaluate(params, state, test, iou_weight=args.iou_weight)
    final["shifted"] = evaluate(params, state, test_shifted, iou_weight=args.iou_weight)
    final["epochs"] = epoch + 1
    final["train_samples"] = n
    final["augment"] = args.augment
    final["init"] = args.init
    final["shift_chance"] = chance
    final["levels"], final["width"] = shape
    final["iou_weight"] = args.iou_weight
    final["ema"] = args.ema
    print("test", json.dumps(final))
    if args.metrics:
        with open(args.metrics, "w") as f:
            json.dump(final, f, indent=2)
    arrays = to_arrays(params, state)
    weight_files.save(os.path.splitext(args.out)[0] + ".npz", arrays)
    export.export(arrays, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
